"""Scenario files (TOML): the platoon, its target path, task, gains, avoidance and obstacles.

A scenario is read with ``tomllib`` only and validated field by field (``scenario_checks``,
``scenario_target``, ``scenario_tables``); an error is one line naming the file, the key path and
the value. ``Scenario.initial(seed)`` draws what the scenario says a seed varies (the ring's phase
or a disk formation, headings, obstacle jitter, an obstacle field) from
``numpy.random.default_rng(seed)``, so a seed fixes the initial state and the obstacles. The
target's path is ``paths`` and ``curves``; the formations are ``formations``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from platoon_opt import formations, paths, scenario_target
from platoon_opt import scenario_tables as tables
from platoon_opt.arrays import namespace, pytree
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.errors import ScenarioError
from platoon_opt.obstacle_fields import TRIES, ObstacleField

# Straight legs, the path of the files written before the other kinds: importable from here.
from platoon_opt.paths import TargetPath as TargetPath
from platoon_opt.safety import SafetyParams
from platoon_opt.scenario_checks import (
    MAX_STEPS,
    OBSTACLE,
    REQUIRED,
    SCHEMA,
    Checks,
    decode_error,
    show,
    toml_error,
)
from platoon_opt.tasks import CovarianceTask, MeanVarianceTask, Task
from platoon_opt.vehicle import PlatoonState, VehicleLimits

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# The scenario files shipped with the package; ``load_scenario`` finds them by bare name.
SCENARIO_DIR = Path(__file__).resolve().parent / "scenario_files"
PAPER_SCENARIOS = ("paper_no_obstacles", "paper_obstacles")

# Task kinds a scenario file may name (``[task] kind``) and their factories. The tasks written in
# CasADi (``symbolic_*``) are registered by the allocators' package, the floor that may use
# CasADi.
TASKS: dict[str, Callable[[], Task]] = {
    "mean_variance": MeanVarianceTask,
    "covariance": CovarianceTask,
}


def register_task(kind: str, factory: Callable[[], Task]) -> None:
    """Let scenario files name ``[task] kind = kind``."""
    TASKS[kind] = factory


def task_factory(kind: str) -> Callable[[], Task] | None:
    """The factory of task ``kind``, or None if no such kind is registered."""
    return TASKS.get(kind)


def check_seed(seed: Any) -> int:
    """``seed`` as an int, or ``ValueError`` naming it: a seed is an integer >= 0 (what
    ``numpy.random.default_rng`` takes)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    return int(seed)


@pytree(data=("target", "constants"), static=("names",))
@dataclass(frozen=True)
class Goal:
    """What the platoon must do over time, f_d(t) and f_d'(t) for the task components ``names``:
    "mean_x" and "mean_y" follow the target path, every other component holds its constant.

    Attributes:
        target: the target path.
        constants: (m,) the held values (0 for the components that follow the target).
        names: the m task component names.
    """

    target: paths.Path
    constants: Any
    names: tuple[str, ...]

    def at(self, t: Any) -> tuple[Any, Any, Any]:
        """f_d(t) (m,), f_d'(t) (m,) and the target's position (2,), m, at ``t`` (s; a float, or
        traced)."""
        xp = namespace(t, self.constants)
        position, velocity = self.target.at(t)
        axis = {"mean_x": 0, "mean_y": 1}
        value = [position[axis[k]] if k in axis else self.constants[i] for i, k in enumerate(self.names)]
        rate = [velocity[axis[k]] if k in axis else xp.zeros(()) for k in self.names]
        return xp.stack(value), xp.stack(rate), position


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
        heading: initial heading (rad) when ``headings`` is "fixed".
        vary_ring_phase: whether a seed draws the ring's phase.
        obstacle_jitter: standard deviation (m) of the seed's offset of obstacle centres.
        target: the target path (``paths.Path``).
        task_kind: key in ``TASKS``.
        gains: K's diagonal, one per task component.
        desired: constant f_d components by name; "mean_x"/"mean_y" follow the target.
        avoidance, obstacles, limits: as in the model (``obstacles``: the file's fixed ones).
        safety: the barrier constraints (``[safety]``; off unless ``mode = "barrier"``).
        formation: the initial formation (``formations.FORMATIONS``).
        positions: an explicit formation's positions (n, 2) m, else None.
        headings: how the initial headings are set (``formations.HEADINGS``).
        obstacle_field: the obstacles a seed draws besides the fixed ones, or None.
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
    obstacle_jitter: float
    target: paths.Path
    task_kind: str
    gains: np.ndarray
    desired: dict[str, float]
    avoidance: AvoidanceParams
    obstacles: CircularObstacles
    limits: VehicleLimits
    safety: SafetyParams = SafetyParams()
    formation: str = "ring"
    positions: np.ndarray | None = None
    headings: str = "fixed"
    obstacle_field: ObstacleField | None = None
    description: str = ""
    source: str = ""
    raw: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def vary_headings(self) -> bool:
        """Whether a seed draws the headings."""
        return self.headings == "random"

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

    def run_steps(self, duration: float | None = None, *, name: str = "duration") -> int:
        """Steps of a run of ``duration`` s (None: the scenario's own duration).

        Raises:
            ValueError: ``duration`` (called ``name`` in the message) is not a finite number,
                is shorter than one step ``dt`` (no run), or needs more than ``MAX_STEPS`` steps.
        """
        if duration is None:
            return self.steps
        real = (int, float, np.integer, np.floating)
        if isinstance(duration, bool) or not isinstance(duration, real) or not math.isfinite(duration):
            raise ValueError(f"{name} must be a finite number of seconds, got {duration!r}")
        if not duration >= self.dt:
            raise ValueError(
                f"{name} must be at least one step (dt = {self.dt:g} s of {self.name}), got {duration!r}"
            )
        if duration / self.dt > MAX_STEPS:
            raise ValueError(
                f"{name} must be at most {MAX_STEPS:,} steps of dt = {self.dt:g} s ({self.name}), "
                f"got {duration!r}"
            )
        return int(round(duration / self.dt))

    def initial(self, seed: int = 0) -> tuple[PlatoonState, CircularObstacles]:
        """The seed's initial state and obstacles (``formations``, ``obstacle_fields``).

        From ``numpy.random.default_rng(seed)``, in this order: the formation (a ring's phase, if
        it varies; a disk's positions), the headings (if "random"), the fixed obstacles' jitter
        (if any), the obstacle field (if any). Steering starts at 0; gears forward.

        Raises:
            ValueError: ``seed`` is not an integer >= 0 (naming it and the value).
            ScenarioError: the seed's formation or obstacle field cannot be placed.
        """
        rng = np.random.default_rng(check_seed(seed))
        positions = self._positions(rng, seed)
        if self.headings == "random":
            theta = rng.uniform(-np.pi, np.pi, self.n)
        elif self.headings == "toward_target":
            theta = formations.toward(positions, np.asarray(self.target.at(0.0)[0]))
        else:
            theta = np.full(self.n, self.heading)
        centers, radii = self.obstacles.centers, self.obstacles.radii
        if self.obstacle_jitter > 0 and len(self.obstacles):
            centers = centers + rng.normal(0.0, self.obstacle_jitter, centers.shape)
        if self.obstacle_field is not None:
            drawn = self.obstacle_field.draw(rng, positions, centers, radii)
            if isinstance(drawn, int):
                rule = (
                    f"placeable: obstacle {drawn} of the field found no place in {TRIES:,} draws for seed "
                    f"{seed} (fewer, smaller or less spaced obstacles, or a larger obstacle_field.region)"
                )
                raise ScenarioError(
                    f"{self.source}: obstacle_field.count must be {rule}, got {self.obstacle_field.count}"
                )
            centers, radii = np.vstack((centers, drawn[0])), np.concatenate((radii, drawn[1]))
        state = PlatoonState(positions[:, 0], positions[:, 1], theta, np.zeros(self.n))
        return state, CircularObstacles(centers, radii)

    def _positions(self, rng: np.random.Generator, seed: int) -> np.ndarray:
        """The units' initial positions (n, 2) m: the formation's pattern scaled per axis to the
        variances around the centre (``formations``), or the explicit positions."""
        if self.positions is not None:
            return self.positions.copy()
        if self.formation == "ring":
            offsets = formations.ring(self.n, rng.uniform(0.0, 2 * np.pi) if self.vary_ring_phase else 0.0)
        elif self.formation == "disk":
            drawn = formations.disk(self.n, rng)
            if drawn is None:  # never seen: the spacing leaves half the disk free to the last unit
                raise ScenarioError(
                    f"{self.source}: platoon.n must be drawable in a disk for seed {seed}, got {self.n}"
                )
            offsets = drawn
        else:
            offsets = formations.grid(self.n) if self.formation == "grid" else formations.line(self.n)
        if np.any(formations.spread(offsets) <= 1e-12):  # two units whose phase or draw puts them on one axis
            raise ScenarioError(
                f"{self.source}: platoon.n must be >= 3 for seed {seed}, whose {self.formation} puts both "
                f"units on one axis, got {self.n}"
            )
        return self.center + formations.scaled(offsets, self.variance)

    def goal(self, names: tuple[str, ...]) -> Goal:
        """f_d(t) and f_d'(t) for task components ``names`` (``Goal``)."""
        constants = np.array(
            [self.desired.get(k, 0.0) if k not in ("mean_x", "mean_y") else 0.0 for k in names]
        )
        return Goal(self.target, constants, tuple(names))

    def desired_at(self, names: tuple[str, ...], t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """f_d(t) and f_d'(t) for task components ``names``, and the target's position (2,), m."""
        return self.goal(names).at(t)


# --- reading and validation ---------------------------------------------------------------


def parse_scenario(data: dict[str, Any], where: str = "<scenario>") -> Scenario:
    """Validate a scenario table (as from ``tomllib``) and build the ``Scenario``.

    Raises:
        ScenarioError: one line naming ``where``, the key path and the value (``scenario_checks``).
    """
    checks = Checks(where)
    if not data:
        needs = ", ".join(REQUIRED[""])
        raise checks.error(f"missing key name (the file holds no keys; a scenario needs {needs})")
    checks.types(data, SCHEMA)
    checks.require(data, "", REQUIRED[""])
    sim, platoon, target, task = data["simulation"], data["platoon"], data["target"], data["task"]
    for table, name in ((sim, "simulation"), (platoon, "platoon"), (task, "task")):
        checks.require(table, name, REQUIRED[name])
    dt = checks.number("simulation.dt", sim["dt"], positive=True)
    duration = checks.number("simulation.duration", sim["duration"], positive=True)
    if duration < dt:
        raise checks.must("simulation.duration", f">= simulation.dt = {show(sim['dt'])}", sim["duration"])
    if duration / dt > MAX_STEPS:
        raise checks.must(
            "simulation.duration",
            f"at most {MAX_STEPS:,} steps of simulation.dt = {show(sim['dt'])}",
            sim["duration"],
        )
    transient = checks.number("simulation.transient", sim.get("transient", 4.0), at_least=0)
    if transient >= duration:
        # The after-transient errors would integrate nothing: 0 for every run.
        raise checks.must(
            "simulation.transient",
            f"shorter than simulation.duration = {show(sim['duration'])}",
            sim.get("transient", 4.0),
        )
    path = scenario_target.target(checks, target)
    seed = data.get("seed", {})
    start = np.asarray(path.at(0.0)[0])
    shape = tables.platoon(checks, platoon, seed, target, start)
    jitter = checks.number("seed.obstacle_jitter", seed.get("obstacle_jitter", 0.0), at_least=0)
    kind = task["kind"]
    factory = task_factory(kind)
    if factory is None:
        known = ", ".join(map(repr, sorted(TASKS)))
        # The CasADi-defined kinds exist once the allocators' floor is imported (the CLI does).
        hint = (
            " (symbolic_* kinds: import the allocators' package, solvers, first)"
            if str(kind).startswith("symbolic_")
            else ""
        )
        raise checks.must("task.kind", f"one of {known}{hint}", kind)
    names = factory().names
    gains = np.array(checks.vector("task.gains", task["gains"], len(names)))
    for i, value in enumerate(gains):
        if value < 0:
            raise checks.must(f"task.gains[{i}]", ">= 0 (1/s)", task["gains"][i])
    desired = tables.desired(checks, task.get("desired", {}), names)
    avoidance_table = data.get("avoidance", {})
    d_minr = checks.number("avoidance.d_minr", avoidance_table.get("d_minr", 1.0), positive=True)
    d_mino = checks.number("avoidance.d_mino", avoidance_table.get("d_mino", 3.0), positive=True)
    reference = avoidance_table.get("ahead_reference", "heading")
    if reference not in ("heading", "travel"):
        raise checks.must("avoidance.ahead_reference", "'heading' or 'travel'", reference)
    centers, radii = [], []
    for i, obstacle in enumerate(data.get("obstacles", [])):
        key = f"obstacles[{i}]"
        if not isinstance(obstacle, dict):
            raise checks.must(key, "a table", obstacle)
        checks.types(obstacle, OBSTACLE, key)
        checks.require(obstacle, key, REQUIRED["obstacles[]"])
        centers.append(checks.point(f"{key}.center", obstacle["center"]))
        radii.append(checks.number(f"{key}.radius", obstacle["radius"], positive=True))
    limits = tables.limits(checks, data.get("vehicle", {}))
    field = data.get("obstacle_field")
    return Scenario(
        name=checks.name(data["name"]),
        description=data.get("description", ""),
        dt=dt,
        duration=duration,
        transient=transient,
        obstacle_jitter=jitter,
        target=path,
        task_kind=kind,
        gains=gains,
        desired=desired,
        avoidance=AvoidanceParams(d_minr=d_minr, d_mino=d_mino, ahead_reference=reference),
        obstacles=CircularObstacles(np.reshape(centers, (-1, 2)), np.asarray(radii)),
        limits=limits,
        safety=tables.safety(checks, data.get("safety", {}), limits, dt),
        obstacle_field=None if field is None else tables.obstacle_field(checks, field, path),
        source=where,
        raw=data,
        **shape,
    )


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file (UTF-8 TOML; a leading byte-order mark is allowed). A
    bare name ("paper_obstacles") is looked up in the scenario files shipped with the package
    (``SCENARIO_DIR``).

    Raises:
        ScenarioError: the file is missing or unreadable, not UTF-8, not TOML, or a field is
            wrong; one line naming the file (and the key and the value).
    """
    if not str(path).strip():
        raise ScenarioError(f"{str(path)!r}: an empty path names no scenario file")
    given = path = Path(path)
    if not path.suffix and not path.exists() and (SCENARIO_DIR / f"{path.name}.toml").is_file():
        path = SCENARIO_DIR / f"{path.name}.toml"
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        names = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.toml")))
        raise ScenarioError(f"{given}: no such scenario file, nor a shipped scenario ({names})") from None
    except IsADirectoryError:
        raise ScenarioError(f"{given}: is a folder, not a scenario file") from None
    except OSError as error:
        raise ScenarioError(f"{given}: cannot read: {error.strerror or error}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise decode_error(str(path), data, error) from None
    text = text.removeprefix("\ufeff")  # a byte-order mark, as some editors write
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise toml_error(str(path), text, error) from None
    return parse_scenario(table, str(path))
