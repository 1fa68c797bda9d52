"""One closed-loop run of a study: its specification, fingerprint, simulation and scores.

A *run* is one scenario (optionally changed by an ablation ``Variant``), one allocator
configuration and one seed; the seed fixes the initial state and the obstacles
(``Scenario.initial``), so every configuration of a seed starts from the same state and chases
the same target. ``run_specs`` runs many through the executor (serial, process pool or Dask)
and keeps each finished result in a ``ResultCache`` under ``runs/<scenario>/<variant>/<config>/
seed-<s>.json`` with the fingerprint of everything that determines it, so that an interrupted
study resumes where it stopped.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from platoon_opt.errors import AllocationError
from platoon_opt.metrics import integrated_errors
from platoon_opt.obstacle_fields import ObstacleField
from platoon_opt.scenarios import SCENARIO_DIR, Scenario
from platoon_opt.simulation import simulate
from platoon_opt.study.config import AllocatorConfig, AllocatorFactory
from platoon_opt.study.fallbacks import first_fallback
from platoon_opt.study.tracks import track_bytes
from platoon_opt.study.variants import BASE, Variant
from platoon_opt.trajectory import Trajectory

# Fields of a run's result that depend on wall-clock time; every other field is a
# deterministic function of the run's fingerprint (serial, parallel and Dask runs agree).
TIMING_FIELDS = (
    "solve_time_median",
    "solve_time_p95",
    "solve_time_per_solve_median",
    "solve_time_per_solve_p95",
    "wall_time",
    "cpu_time",
    "step_time",
    "step_cpu_time",
)


def scenario_source(scenario: Scenario, folder: str | Path) -> str:
    """Where ``scenario`` was read from, as results files record it: a shipped file by its place in
    the package, any other relative to ``folder`` (the output folder), never an absolute path of
    this machine."""
    source = Path(scenario.source).resolve()
    if source.parent == SCENARIO_DIR:
        return f"platoon_opt/scenario_files/{source.name} (shipped with platoon-opt)"
    return os.path.relpath(source, Path(folder).resolve())


def scenario_definition(scenario: Scenario, folder: str | Path = ".") -> dict[str, Any]:
    """Everything that determines a scenario's runs, as JSON-ready data (the report's
    scenario table and the runs' fingerprints); ``source`` relative to ``folder``."""
    limits = scenario.limits
    return {
        "name": scenario.name,
        "source": scenario_source(scenario, folder),
        "n": scenario.n,
        "dt": scenario.dt,
        "duration": scenario.duration,
        "transient": scenario.transient,
        "center": scenario.center.tolist(),
        "variance": scenario.variance.tolist(),
        "heading": scenario.heading,
        "formation": scenario.formation,
        "positions": None if scenario.positions is None else scenario.positions.tolist(),
        "headings": scenario.headings,
        "seed_varies": {
            "ring_phase": scenario.vary_ring_phase,
            "headings": scenario.vary_headings,
            "obstacle_jitter": scenario.obstacle_jitter,
            "obstacle_field": _field(scenario.obstacle_field),
        },
        "target": {
            # The file's table says which path and how it was built (a curve's arc-length table
            # is code); the points and the speed are the path as the runs follow it.
            "kind": scenario.raw.get("target", {}).get("kind", "polyline"),
            "table": scenario.raw.get("target", {}),
            "speed": float(scenario.target.speed),
            "length": scenario.target.length,
            "waypoints": np.asarray(scenario.target.waypoints).tolist(),
        },
        "task": {"kind": scenario.task_kind, "gains": scenario.gains.tolist(), "desired": scenario.desired},
        "avoidance": {
            "d_minr": scenario.avoidance.d_minr,
            "d_mino": scenario.avoidance.d_mino,
            "ahead_reference": scenario.avoidance.ahead_reference,
        },
        "obstacles": [
            {"center": c.tolist(), "radius": float(r)}
            for c, r in zip(scenario.obstacles.centers, scenario.obstacles.radii)
        ],
        "vehicle": {
            "wheel_radius": limits.wheel_radius,
            "length": limits.length,
            "max_speed": limits.max_speed,
            "max_steering_deg": math.degrees(limits.max_steering),
            "max_steering_rate": limits.max_steering_rate,
            "steering_gain": limits.steering_gain,
            "gear_hysteresis_deg": math.degrees(limits.gear_hysteresis),
        },
    }


def _field(field: ObstacleField | None) -> dict[str, Any] | None:
    """An obstacle field as JSON-ready data, or None."""
    if field is None:
        return None
    return {
        "count": field.count,
        "radius_range": field.radius_range.tolist(),
        "region": field.region.tolist(),
        "path_gap": field.path_gap,
        "start_gap": field.start_gap,
        "obstacle_gap": field.obstacle_gap,
    }


# The package whose source determines a run's result: the model and the allocators, not the
# study (this package: reporting, the command line).
_PACKAGE = Path(__file__).resolve().parents[1]


@functools.cache
def code_version() -> str:
    """Hash of the model's and the allocators' source (``platoon_opt`` but ``platoon_opt.study``),
    so that a finished run is reused only by the code that produced it."""
    digest = hashlib.sha256()
    for path in sorted(_PACKAGE.rglob("*.py")):
        relative = path.relative_to(_PACKAGE)
        if relative.parts[0] != "study":
            digest.update(f"{relative.as_posix()}\n".encode() + path.read_bytes())
    return digest.hexdigest()[:20]


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9=.,_-]", "_", text)


@dataclass(frozen=True)
class RunSpec:
    """One run: ``scenario`` changed by ``variant``, under ``config``, from ``seed``.

    Attributes:
        scenario: the scenario as read (the variant is applied when the run starts).
        variant: the ablation variant (``BASE`` for none).
        config: the allocator configuration.
        seed: the scenario seed.
        duration: simulated time (s); None for the scenario's.
        keep_track: also keep a thinned copy of the trajectory for figures (``load_track``);
            not part of the run's identity.
        strict: end the run with ``AllocationError`` at the first step whose allocation fails or
            falls back (``PlatoonController.strict``) instead of carrying on with the fallback.
            Not part of the fingerprint: a strict run that completes never fell back and is
            identical to the same run without strict. A finished run is reused by a strict study
            only if it never fell back (``run_specs``), so a strict rerun still stops on it.
    """

    scenario: Scenario
    variant: Variant
    config: AllocatorConfig
    seed: int
    duration: float | None = None
    keep_track: bool = False
    strict: bool = False

    @property
    def key(self) -> str:
        """Relative path of the run's result file, without suffix."""
        return f"{_slug(self.scenario.name)}/{self.variant.name}/{_slug(self.config.label)}/seed-{self.seed}"

    @property
    def steps(self) -> int:
        """Simulation steps of the run."""
        return self.variant.apply(self.scenario).run_steps(self.duration)

    def fingerprint(self) -> str:
        """Hash of everything the run's deterministic result depends on: the scenario after
        the variant, the configuration, the seed, the duration and the code (``code_version``);
        not ``strict`` (see the class docstring)."""
        scenario = self.variant.apply(self.scenario)
        # Every field of the limits and avoidance parameters (also ones the report omits),
        # not the file's location.
        definition = {k: v for k, v in scenario_definition(scenario).items() if k != "source"}
        definition.update(limits=asdict(scenario.limits), avoidance=asdict(scenario.avoidance))
        text = json.dumps(
            {
                "scenario": definition,
                "config": self.config.as_dict(),
                "seed": self.seed,
                "duration": self.duration,
                "code": code_version(),
            },
            sort_keys=True,
            default=str,
        )
        return hashlib.sha256(text.encode()).hexdigest()[:20]


def _simulate(
    spec: RunSpec, factory: AllocatorFactory, compiled: bool | None = None
) -> tuple[Scenario, Trajectory, tuple[float, float]]:
    """The run's scenario, trajectory and (wall, CPU) seconds of the simulation (``compiled`` as
    ``simulate``'s).

    Raises:
        AllocationError: a strict run's allocation failed (naming the scenario and the seed).
    """
    scenario = spec.variant.apply(spec.scenario)
    allocator = spec.config.build(factory)
    start, cpu = time.perf_counter(), time.process_time()
    try:
        trajectory = simulate(
            scenario, allocator, seed=spec.seed, duration=spec.duration, strict=spec.strict, compiled=compiled
        )
    except AllocationError as error:
        name = scenario.name if spec.variant.name == BASE.name else f"{scenario.name} ({spec.variant.name})"
        raise error.within(scenario=name, seed=spec.seed) from error
    return scenario, trajectory, (time.perf_counter() - start, time.process_time() - cpu)


def run_spec(spec: RunSpec, factory: AllocatorFactory) -> dict[str, Any]:
    """Simulate one run and score it.

    Returns:
        ``{"key", "fingerprint", "scenario", "variant", "config", "allocator", "options",
        "seed", "dt", "steps", "path"}`` (path: "compiled" or "host", which loop ran it), the
        scores of ``integrated_errors`` (with the scenario's
        transient), ``first_fallback`` and ``first_fallback_t`` (the status and time of the first
        step that fell back: "" and None if none), ``wall_time`` and ``cpu_time`` (s, the whole
        simulation) and
        ``step_time``, ``step_cpu_time`` (the same per step).
    """
    return _result(spec, *_simulate(spec, factory))


def _result(
    spec: RunSpec, scenario: Scenario, trajectory: Trajectory, times: tuple[float, float]
) -> dict[str, Any]:
    scores = integrated_errors(trajectory, scenario.transient)
    path = "compiled" if trajectory.compiled else "host"
    return run_result(spec, scenario, trajectory.steps, scores, first_fallback(trajectory), times, path=path)


def run_result(
    spec: RunSpec,
    scenario: Scenario,
    steps: int,
    scores: dict[str, float],
    fallback: tuple[str, float | None],
    times: tuple[float, float],
    *,
    path: str,
) -> dict[str, Any]:
    """A run's result dict (see ``run_spec``) from its scores (``metrics.score``), its first
    fallback (status, time) and its (wall, CPU) seconds; ``path`` is "compiled" (the engine) or
    "host" (the host loop)."""
    return {
        "key": spec.key,
        "fingerprint": spec.fingerprint(),
        "scenario": scenario.name,
        "variant": spec.variant.name,
        "config": spec.config.label,
        "allocator": spec.config.name,
        "options": dict(spec.config.options),
        "seed": spec.seed,
        "dt": scenario.dt,
        "steps": steps,
        "path": path,
        **scores,
        "first_fallback": fallback[0],
        "first_fallback_t": fallback[1],
        "wall_time": times[0],
        "cpu_time": times[1],
        "step_time": times[0] / max(steps, 1),
        "step_cpu_time": times[1] / max(steps, 1),
    }


def trajectory_of(spec: RunSpec, factory: AllocatorFactory) -> Trajectory:
    """The full trajectory of one run (for figures; not cached)."""
    return _simulate(spec, factory)[1]


def run_job(
    spec: RunSpec, factory: AllocatorFactory, *, compiled: bool | None = None
) -> tuple[dict[str, Any], bytes | None]:
    """A worker's job: the run's result and, if asked for, its thinned trajectory (``compiled``
    as ``simulate``'s)."""
    scenario, trajectory, times = _simulate(spec, factory, compiled)
    return _result(spec, scenario, trajectory, times), track_bytes(trajectory) if spec.keep_track else None
