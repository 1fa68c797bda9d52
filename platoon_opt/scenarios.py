"""Scenario files (TOML): the platoon, its target path, task, gains, avoidance and obstacles.

A scenario is read with ``tomllib`` only and validated field by field; an error is one
line naming the file, the key path and the value. ``Scenario.initial(seed)`` draws what
the scenario says a seed varies (ring phase, headings, obstacle jitter) from
``numpy.random.default_rng(seed)``, so a seed fixes the initial state and the obstacles.
"""

from __future__ import annotations

import importlib
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.errors import ScenarioError
from platoon_opt.tasks import MeanVarianceTask, Task
from platoon_opt.vehicle import PlatoonState, VehicleLimits

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# The scenario files shipped with the package; ``load_scenario`` finds them by bare name.
SCENARIO_DIR = Path(__file__).resolve().parent / "scenario_files"
PAPER_SCENARIOS = ("paper_no_obstacles", "paper_obstacles")

# Task kinds a scenario file may name (``[task] kind``): a factory of the task, or
# "module:function" naming one that is imported on first use (the CasADi-defined tasks, so that
# ``import platoon_opt`` does not load CasADi).
TASKS: dict[str, Callable[[], Task] | str] = {
    "mean_variance": MeanVarianceTask,
    "symbolic_mean_variance": "platoon_opt.symbolic:symbolic_mean_variance_task",
    "covariance": "platoon_opt.symbolic:covariance_task",
}


def register_task(kind: str, factory: Callable[[], Task] | str) -> None:
    """Let scenario files name ``[task] kind = kind``."""
    TASKS[kind] = factory


def task_factory(kind: str) -> Callable[[], Task] | None:
    """The factory of task ``kind``, or None if no such kind is registered."""
    factory = TASKS.get(kind)
    if isinstance(factory, str):
        module, _, name = factory.partition(":")
        factory = getattr(importlib.import_module(module), name)
    return factory


@dataclass(frozen=True)
class TargetPath:
    """A holonomic target moving at constant ``speed`` (m/s) through ``waypoints`` (k, 2) m,
    then holding at the last one."""

    waypoints: np.ndarray
    speed: float

    @cached_property
    def _cumulative(self) -> np.ndarray:
        """Arc length at each waypoint (k,), m."""
        legs = np.linalg.norm(np.diff(self.waypoints, axis=0), axis=1)
        return np.concatenate(([0.0], np.cumsum(legs)))

    @cached_property
    def _directions(self) -> np.ndarray:
        """Unit direction of each leg (k - 1, 2)."""
        legs = np.diff(self.waypoints, axis=0)
        return legs / np.linalg.norm(legs, axis=1)[:, None]

    @property
    def length(self) -> float:
        """Path length (m)."""
        return float(self._cumulative[-1])

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Position (2,) m and velocity (2,) m/s at time ``t`` (s)."""
        cumulative = self._cumulative
        travelled = self.speed * max(t, 0.0)
        if travelled >= cumulative[-1]:
            return self.waypoints[-1].copy(), np.zeros(2)
        leg = int(np.searchsorted(cumulative, travelled, side="right")) - 1
        direction = self._directions[leg]
        return self.waypoints[leg] + (travelled - cumulative[leg]) * direction, self.speed * direction


@dataclass(frozen=True)
class Scenario:
    """A closed-loop experiment, as read from a scenario file.

    Attributes:
        name: scenario name.
        n: number of units.
        dt, duration, transient: simulation step, length and the initial transient that the
            after-transient metrics exclude (s).
        center: initial mean position (2,), m.
        variance: initial sample variances (var_x, var_y) (2,), m^2, met exactly.
        heading: initial heading (rad) when the seed does not vary headings.
        vary_ring_phase, vary_headings: what a seed varies.
        obstacle_jitter: standard deviation (m) of the seed's offset of obstacle centres.
        target: the target path.
        task_kind: key in ``TASKS``.
        gains: K's diagonal, one per task component.
        desired: constant f_d components by name; "mean_x"/"mean_y" follow the target.
        avoidance, obstacles, limits: as in the model.
        source: the file it was read from.
    """

    name: str
    n: int
    dt: float
    duration: float
    transient: float
    center: np.ndarray
    variance: np.ndarray
    heading: float
    vary_ring_phase: bool
    vary_headings: bool
    obstacle_jitter: float
    target: TargetPath
    task_kind: str
    gains: np.ndarray
    desired: dict[str, float]
    avoidance: AvoidanceParams
    obstacles: CircularObstacles
    limits: VehicleLimits
    description: str = ""
    source: str = ""
    raw: dict[str, Any] = field(default_factory=dict, repr=False)

    def task(self) -> Task:
        """A fresh task object of ``task_kind``."""
        factory = task_factory(self.task_kind)
        if factory is None:
            raise ScenarioError(f"{self.source}: task.kind {self.task_kind!r} is not registered")
        return factory()

    @property
    def steps(self) -> int:
        """Number of simulation steps."""
        return int(round(self.duration / self.dt))

    def initial(self, seed: int = 0) -> tuple[PlatoonState, CircularObstacles]:
        """The seed's initial state and obstacles.

        Units sit on a ring at phases ``phi_0 + 2 pi i / n`` around ``center``, scaled per
        axis so that the sample variances equal ``variance`` exactly; ``phi_0`` is drawn
        from the seed when the ring phase varies (else 0). Headings are ``heading`` or drawn
        uniformly in (-pi, pi]; steering starts at 0; gears forward.
        """
        rng = np.random.default_rng(seed)
        phase = rng.uniform(0.0, 2 * np.pi) if self.vary_ring_phase else 0.0
        angles = phase + 2 * np.pi * np.arange(self.n) / self.n
        offsets = np.column_stack((np.cos(angles), np.sin(angles)))
        offsets -= offsets.mean(axis=0)
        spread = offsets.var(axis=0, ddof=1)
        if np.any(spread <= 1e-12):
            raise ScenarioError(f"{self.source}: platoon.n = {self.n} ring is degenerate for seed {seed}")
        positions = self.center + offsets * np.sqrt(self.variance / spread)
        theta = rng.uniform(-np.pi, np.pi, self.n) if self.vary_headings else np.full(self.n, self.heading)
        centers = self.obstacles.centers
        if self.obstacle_jitter > 0 and len(self.obstacles):
            centers = centers + rng.normal(0.0, self.obstacle_jitter, centers.shape)
        state = PlatoonState(positions[:, 0], positions[:, 1], theta, np.zeros(self.n))
        return state, CircularObstacles(centers, self.obstacles.radii)

    def desired_at(self, names: tuple[str, ...], t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """f_d(t) and f_d'(t) for task components ``names``, and the target's position (2,), m."""
        position, velocity = self.target.at(t)
        follow = {"mean_x": (position[0], velocity[0]), "mean_y": (position[1], velocity[1])}
        value = np.array([follow[k][0] if k in follow else self.desired[k] for k in names])
        rate = np.array([follow[k][1] if k in follow else 0.0 for k in names])
        return value, rate, position


# --- reading and validation ---------------------------------------------------------------

_SCHEMA: dict[str, Any] = {
    "name": str,
    "description": str,
    "simulation": {"dt": float, "duration": float, "transient": float},
    "platoon": {"n": int, "center": list, "variance": list, "heading": float},
    "seed": {"ring_phase": bool, "headings": bool, "obstacle_jitter": float},
    "target": {"speed": float, "waypoints": list},
    "task": {"kind": str, "gains": list, "desired": dict},
    "avoidance": {"d_minr": float, "d_mino": float, "ahead_reference": str},
    "vehicle": {
        "wheel_radius": float,
        "length": float,
        "max_speed": float,
        "max_steering_deg": float,
        "max_steering_rate": float,
        "steering_gain": float,
        "gear_hysteresis_deg": float,
    },
    "obstacles": list,
}
_REQUIRED = ("name", "simulation", "platoon", "target", "task")


def _check(where: str, table: dict[str, Any], schema: dict[str, Any], path: str) -> None:
    for key, value in table.items():
        key_path = f"{path}.{key}" if path else key
        if key not in schema:
            raise ScenarioError(f"{where}: unknown key {key_path} = {value!r}")
        expected = schema[key]
        if isinstance(expected, dict):
            if not isinstance(value, dict):
                raise ScenarioError(f"{where}: {key_path} must be a table, got {value!r}")
            _check(where, value, expected, key_path)
        elif expected is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ScenarioError(f"{where}: {key_path} must be a finite number, got {value!r}")
        elif expected is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise ScenarioError(f"{where}: {key_path} must be an integer, got {value!r}")
        elif not isinstance(value, expected):
            raise ScenarioError(f"{where}: {key_path} must be a {expected.__name__}, got {value!r}")


def _vector(where: str, key_path: str, value: Any, length: int | None) -> np.ndarray:
    if not isinstance(value, list) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value
    ):
        raise ScenarioError(f"{where}: {key_path} must be a list of finite numbers, got {value!r}")
    if length is not None and len(value) != length:
        raise ScenarioError(f"{where}: {key_path} must have {length} entries, got {value!r}")
    return np.asarray(value, dtype=float)


def _positive(where: str, key_path: str, value: float, *, allow_zero: bool = False) -> float:
    if value < 0 or (value == 0 and not allow_zero):
        raise ScenarioError(f"{where}: {key_path} must be {'>=' if allow_zero else '>'} 0, got {value!r}")
    return float(value)


def parse_scenario(data: dict[str, Any], where: str = "<scenario>") -> Scenario:
    """Validate a scenario table (as from ``tomllib``) and build the ``Scenario``."""
    _check(where, data, _SCHEMA, "")
    for key in _REQUIRED:
        if key not in data:
            raise ScenarioError(f"{where}: missing key {key}")
    sim, platoon, target, task = data["simulation"], data["platoon"], data["target"], data["task"]
    for table, table_name, keys in (
        (sim, "simulation", ("dt", "duration")),
        (platoon, "platoon", ("n", "center", "variance")),
        (target, "target", ("speed", "waypoints")),
        (task, "task", ("kind", "gains")),
    ):
        for key in keys:
            if key not in table:
                raise ScenarioError(f"{where}: missing key {table_name}.{key}")
    dt = _positive(where, "simulation.dt", sim["dt"])
    duration = _positive(where, "simulation.duration", sim["duration"])
    if duration < dt:
        raise ScenarioError(f"{where}: simulation.duration must be >= simulation.dt, got {duration!r}")
    transient = _positive(where, "simulation.transient", sim.get("transient", 4.0), allow_zero=True)
    n = platoon["n"]
    if n < 2:
        raise ScenarioError(f"{where}: platoon.n must be >= 2, got {n!r}")
    center = _vector(where, "platoon.center", platoon["center"], 2)
    variance = _vector(where, "platoon.variance", platoon["variance"], 2)
    if np.any(variance <= 0):
        raise ScenarioError(f"{where}: platoon.variance must be > 0, got {platoon['variance']!r}")
    seed = data.get("seed", {})
    jitter = _positive(where, "seed.obstacle_jitter", seed.get("obstacle_jitter", 0.0), allow_zero=True)
    speed = _positive(where, "target.speed", target["speed"])
    waypoints = target["waypoints"]
    if not isinstance(waypoints, list) or len(waypoints) < 1:
        raise ScenarioError(
            f"{where}: target.waypoints must be a non-empty list of [x, y], got {waypoints!r}"
        )
    points = np.array([_vector(where, f"target.waypoints[{i}]", p, 2) for i, p in enumerate(waypoints)])
    if np.any(np.linalg.norm(np.diff(points, axis=0), axis=1) == 0):
        raise ScenarioError(
            f"{where}: target.waypoints must not repeat a point consecutively, got {waypoints!r}"
        )
    kind = task["kind"]
    factory = task_factory(kind)
    if factory is None:
        raise ScenarioError(f"{where}: task.kind must be one of {sorted(TASKS)}, got {kind!r}")
    names = factory().names
    gains = _vector(where, "task.gains", task["gains"], len(names))
    if np.any(gains < 0):
        raise ScenarioError(f"{where}: task.gains must be >= 0, got {task['gains']!r}")
    desired = dict(task.get("desired", {}))
    for name in names:
        if name in ("mean_x", "mean_y"):
            continue
        if name not in desired:
            raise ScenarioError(f"{where}: missing key task.desired.{name}")
    for key, value in desired.items():
        if key not in names or key in ("mean_x", "mean_y"):
            raise ScenarioError(f"{where}: unknown key task.desired.{key} = {value!r}")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ScenarioError(f"{where}: task.desired.{key} must be a finite number, got {value!r}")
    avoidance_table = data.get("avoidance", {})
    d_minr = _positive(where, "avoidance.d_minr", avoidance_table.get("d_minr", 1.0))
    d_mino = _positive(where, "avoidance.d_mino", avoidance_table.get("d_mino", 3.0))
    reference = avoidance_table.get("ahead_reference", "heading")
    if reference not in ("heading", "travel"):
        raise ScenarioError(
            f"{where}: avoidance.ahead_reference must be 'heading' or 'travel', got {reference!r}"
        )
    centers, radii = [], []
    for i, obstacle in enumerate(data.get("obstacles", [])):
        if not isinstance(obstacle, dict):
            raise ScenarioError(f"{where}: obstacles[{i}] must be a table, got {obstacle!r}")
        _check(where, obstacle, {"center": list, "radius": float}, f"obstacles[{i}]")
        if "center" not in obstacle or "radius" not in obstacle:
            raise ScenarioError(f"{where}: missing key obstacles[{i}].center or obstacles[{i}].radius")
        centers.append(_vector(where, f"obstacles[{i}].center", obstacle["center"], 2))
        radii.append(_positive(where, f"obstacles[{i}].radius", obstacle["radius"]))
    vehicle = dict(data.get("vehicle", {}))
    for degrees in ("max_steering_deg", "gear_hysteresis_deg"):
        if degrees in vehicle:
            vehicle[degrees.removesuffix("_deg")] = math.radians(vehicle.pop(degrees))
    try:
        limits = VehicleLimits(**vehicle)
    except ValueError as error:
        raise ScenarioError(f"{where}: vehicle: {error}") from None
    return Scenario(
        name=data["name"],
        description=data.get("description", ""),
        n=n,
        dt=dt,
        duration=duration,
        transient=transient,
        center=center,
        variance=variance,
        heading=float(platoon.get("heading", math.pi / 2)),
        vary_ring_phase=seed.get("ring_phase", True),
        vary_headings=seed.get("headings", False),
        obstacle_jitter=jitter,
        target=TargetPath(points, speed),
        task_kind=kind,
        gains=gains,
        desired={k: float(v) for k, v in desired.items()},
        avoidance=AvoidanceParams(d_minr=d_minr, d_mino=d_mino, ahead_reference=reference),
        obstacles=CircularObstacles(np.reshape(centers, (-1, 2)), np.asarray(radii)),
        limits=limits,
        source=where,
        raw=data,
    )


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file. A bare name ("paper_obstacles") is looked up in
    the scenario files shipped with the package (``SCENARIO_DIR``).

    Raises:
        ScenarioError: the file is missing, not TOML, or a field is wrong.
    """
    path = Path(path)
    if not path.suffix and not path.exists():
        path = SCENARIO_DIR / f"{path.name}.toml"
    try:
        with path.open("rb") as handle:
            data = tomllib.load(handle)
    except FileNotFoundError:
        raise ScenarioError(f"{path}: no such scenario file") from None
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{path}: not valid TOML: {error}") from None
    return parse_scenario(data, str(path))
