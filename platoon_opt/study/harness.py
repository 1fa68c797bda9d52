"""Comparison harness: every allocator configuration on identical scenarios, over many seeds.

A *run* is one scenario (optionally changed by an ablation ``Variant``), one allocator
configuration and one seed; the seed fixes the initial state and the obstacles
(``Scenario.initial``), so every configuration of a seed starts from the same state and
chases the same target. Runs execute in worker processes (or on a Dask cluster) and each
finished run is written at once, atomically, to ``runs/<scenario>/<variant>/<config>/seed-<s>.json``
together with a fingerprint of everything that determines it; rerunning the same study
skips runs whose file matches, so an interrupted study resumes where it stopped.

The model never imports a solver: configurations are plain data (``AllocatorConfig``)
and the caller passes the allocator factory (``solvers.get_allocator``), which must be
picklable (a module-level function) to reach the workers.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import io
import json
import math
import os
import re
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.errors import AllocationError
from platoon_opt.metrics import integrated_errors
from platoon_opt.problem import Allocator
from platoon_opt.scenarios import Scenario
from platoon_opt.simulation import Trajectory, simulate
from platoon_opt.study.output import write_atomic, write_json

AllocatorFactory = Callable[..., Allocator]

# Fields of a run's result that depend on wall-clock time; every other field is a
# deterministic function of the run's fingerprint (serial, parallel and Dask runs agree).
TIMING_FIELDS = (
    "solve_time_median",
    "solve_time_p95",
    "wall_time",
    "cpu_time",
    "step_time",
    "step_cpu_time",
)


@dataclass(frozen=True)
class AllocatorConfig:
    """One allocator configuration as plain data.

    Attributes:
        name: the allocator's registry name (``solvers.get_allocator(name, **options)``).
        options: keyword options as sorted ``(key, value)`` pairs (JSON-serialisable values).
        label: the configuration's name in tables and file names, unique within a study
            ("m=4" for the paper's iteration, else the name and its options).
    """

    name: str
    options: tuple[tuple[str, Any], ...] = ()
    label: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("AllocatorConfig.name must be a registry name, got ''")
        object.__setattr__(self, "options", tuple(sorted(dict(self.options).items())))
        if not self.label:
            text = ",".join(f"{k}={v}" for k, v in self.options)
            object.__setattr__(self, "label", f"{self.name}:{text}" if text else self.name)

    @classmethod
    def make(cls, name: str, label: str = "", **options: Any) -> AllocatorConfig:
        """``AllocatorConfig.make("qp", backend="osqp")``."""
        return cls(name, tuple(options.items()), label)

    @property
    def iteration_count(self) -> int | None:
        """The paper's m for the iterative allocator, else None."""
        if self.name != "iterative":
            return None
        return int(dict(self.options).get("max_iterations", 4))

    def build(self, factory: AllocatorFactory) -> Allocator:
        """The allocator object, from ``factory(name, **options)``."""
        return factory(self.name, **dict(self.options))

    def as_dict(self) -> dict[str, Any]:
        """``{"name", "options", "label"}`` for JSON."""
        return {"name": self.name, "options": dict(self.options), "label": self.label}


def iterative_configs(iterations: Sequence[int]) -> list[AllocatorConfig]:
    """The paper's iteration for each m in ``iterations``, labelled "m=<m>"."""
    return [AllocatorConfig.make("iterative", f"m={m}", max_iterations=int(m)) for m in iterations]


def parse_config(text: str) -> AllocatorConfig:
    """``"qp"``, ``"qp:backend=osqp,rho=100"`` or ``"m=3"`` (the paper's iteration) as a config.

    Values are Python literals where they parse (numbers, True, tuples), else strings.

    Raises:
        ValueError: malformed text.
    """
    match = re.fullmatch(r"m=(\d+)", text)
    if match:
        return iterative_configs([int(match.group(1))])[0]
    name, _, rest = text.partition(":")
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
        raise ValueError(f"solver must look like NAME or NAME:key=value,..., got {text!r}")
    options: dict[str, Any] = {}
    # Commas inside brackets belong to a value: "nmpc:task_weights=(4,1,4,1),intervals=20".
    for pair in filter(None, re.split(r",(?![^([]*[)\]])", rest)):
        key, sep, value = pair.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"solver option must look like key=value, got {pair!r} in {text!r}")
        try:
            options[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            options[key] = value
    return AllocatorConfig(name, tuple(options.items()))


def default_configs(available: Sequence[str], iterations: Sequence[int] = range(9)) -> list[AllocatorConfig]:
    """The paper's iteration for every m in ``iterations`` (m = 0 first: the baseline), then
    every other registered allocator with its default options, in name order."""
    return iterative_configs(iterations) + [
        AllocatorConfig(name) for name in available if name != "iterative"
    ]


@dataclass(frozen=True)
class Variant:
    """A modelling choice the paper leaves open, applied to a scenario (the ablation).

    Attributes:
        name: file-safe name ("base", "no-hysteresis", ...).
        title: name in the report.
        gear_hysteresis_deg: replaces ``VehicleLimits.gear_hysteresis`` (degrees) if given.
        ahead_reference: replaces ``AvoidanceParams.ahead_reference`` ("heading" or
            "travel") if given.
        dt_scale: multiplies the scenario's time step.
    """

    name: str
    title: str = ""
    gear_hysteresis_deg: float | None = None
    ahead_reference: str | None = None
    dt_scale: float = 1.0

    def apply(self, scenario: Scenario) -> Scenario:
        """The scenario with this variant's choices."""
        changes: dict[str, Any] = {}
        if self.gear_hysteresis_deg is not None:
            limits = replace(scenario.limits, gear_hysteresis=math.radians(self.gear_hysteresis_deg))
            changes["limits"] = limits
        if self.ahead_reference is not None:
            changes["avoidance"] = replace(scenario.avoidance, ahead_reference=self.ahead_reference)
        if self.dt_scale != 1.0:
            changes["dt"] = scenario.dt * self.dt_scale
        return replace(scenario, **changes) if changes else scenario

    def affects(self, scenario: Scenario) -> bool:
        """False for variants that change the Eq. 6 "ahead" test in a scenario without
        obstacles: the test never fires there, so the variant repeats another one."""
        return self.ahead_reference is None or len(scenario.obstacles) > 0


BASE = Variant("base", "as in the scenario file")
# The modelling choices of DESIGN.md's pitfalls, one at a time and the two chattering
# ones together (the most literal reading of the paper).
ABLATION_VARIANTS = (
    Variant("no-hysteresis", "gear rule without hysteresis", gear_hysteresis_deg=0.0),
    Variant("travel-ahead", 'Eq. 6 "ahead" on the travel direction', ahead_reference="travel"),
    Variant(
        "no-hysteresis-travel",
        "both of the above",
        gear_hysteresis_deg=0.0,
        ahead_reference="travel",
    ),
    Variant("half-dt", "dt / 2", dt_scale=0.5),
)


def scenario_definition(scenario: Scenario) -> dict[str, Any]:
    """Everything that determines a scenario's runs, as JSON-ready data (the report's
    scenario table and the runs' fingerprints)."""
    limits = scenario.limits
    return {
        "name": scenario.name,
        "source": scenario.source,
        "n": scenario.n,
        "dt": scenario.dt,
        "duration": scenario.duration,
        "transient": scenario.transient,
        "center": scenario.center.tolist(),
        "variance": scenario.variance.tolist(),
        "heading": scenario.heading,
        "seed_varies": {
            "ring_phase": scenario.vary_ring_phase,
            "headings": scenario.vary_headings,
            "obstacle_jitter": scenario.obstacle_jitter,
        },
        "target": {"speed": scenario.target.speed, "waypoints": scenario.target.waypoints.tolist()},
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
        scenario = self.variant.apply(self.scenario)
        return int(round((self.duration or scenario.duration) / scenario.dt))

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


def _simulate(spec: RunSpec, factory: AllocatorFactory) -> tuple[Scenario, Trajectory, tuple[float, float]]:
    """The run's scenario, trajectory and (wall, CPU) seconds of the simulation.

    Raises:
        AllocationError: a strict run's allocation failed (naming the scenario and the seed).
    """
    scenario = spec.variant.apply(spec.scenario)
    allocator = spec.config.build(factory)
    start, cpu = time.perf_counter(), time.process_time()
    try:
        trajectory = simulate(scenario, allocator, seed=spec.seed, duration=spec.duration, strict=spec.strict)
    except AllocationError as error:
        name = scenario.name if spec.variant.name == BASE.name else f"{scenario.name} ({spec.variant.name})"
        raise error.within(scenario=name, seed=spec.seed) from error
    return scenario, trajectory, (time.perf_counter() - start, time.process_time() - cpu)


def run_spec(spec: RunSpec, factory: AllocatorFactory) -> dict[str, Any]:
    """Simulate one run and score it.

    Returns:
        ``{"key", "fingerprint", "scenario", "variant", "config", "allocator", "options",
        "seed", "dt", "steps"}`` and the scores of ``integrated_errors`` (with the scenario's
        transient), ``wall_time`` and ``cpu_time`` (s, the whole simulation) and
        ``step_time``, ``step_cpu_time`` (the same per step).
    """
    return _result(spec, *_simulate(spec, factory))


def _result(
    spec: RunSpec, scenario: Scenario, trajectory: Trajectory, times: tuple[float, float]
) -> dict[str, Any]:
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
        "steps": trajectory.steps,
        **integrated_errors(trajectory, scenario.transient),
        "wall_time": times[0],
        "cpu_time": times[1],
        "step_time": times[0] / max(trajectory.steps, 1),
        "step_cpu_time": times[1] / max(trajectory.steps, 1),
    }


def trajectory_of(spec: RunSpec, factory: AllocatorFactory) -> Trajectory:
    """The full trajectory of one run (for figures; not cached)."""
    return _simulate(spec, factory)[1]


# Figures need a run's trajectory, not every step of it: keep every TRACK_STRIDE-th instant.
TRACK_STRIDE = 5
_TRACK_ARRAYS = (
    "t", "x", "y", "theta", "alpha", "gear", "task_value", "desired", "target",
    "status", "iterations", "task_residual", "deviation", "solve_time", "fell_back", "exempt",
)  # fmt: skip


def thin(trajectory: Trajectory, stride: int) -> Trajectory:
    """Every ``stride``-th instant of ``trajectory`` (and the steps starting there), as a
    trajectory with time step ``stride * dt``; trailing steps that do not fill a stride are
    dropped."""
    steps = trajectory.steps // stride
    instants, starts = slice(0, steps * stride + 1, stride), slice(0, steps * stride, stride)
    per_step = {"status", "iterations", "task_residual", "deviation", "solve_time", "fell_back", "exempt"}
    arrays = {
        name: getattr(trajectory, name)[starts if name in per_step else instants] for name in _TRACK_ARRAYS
    }
    return replace(trajectory, **arrays, dt=trajectory.dt * stride)


def _track_bytes(trajectory: Trajectory) -> bytes:
    thinned = thin(trajectory, TRACK_STRIDE)
    meta = {k: getattr(thinned, k) for k in ("task_names", "scenario", "allocator", "seed", "dt")}
    arrays = {name: getattr(thinned, name) for name in _TRACK_ARRAYS}
    arrays["status"] = arrays["status"].astype(str)
    buffer = io.BytesIO()
    np.savez_compressed(
        buffer,
        **arrays,
        obstacle_centers=thinned.obstacles.centers,
        obstacle_radii=thinned.obstacles.radii,
        meta=np.array(json.dumps(meta)),
    )
    return buffer.getvalue()


def load_track(path: str | Path) -> Trajectory:
    """A thinned trajectory kept by a run with ``keep_track`` (every ``TRACK_STRIDE``-th instant)."""
    with np.load(path) as data:
        meta = json.loads(str(data["meta"]))
        arrays = {name: data[name] for name in _TRACK_ARRAYS}
        obstacles = CircularObstacles(data["obstacle_centers"].reshape(-1, 2), data["obstacle_radii"])
    arrays["status"] = arrays["status"].astype(object)
    return Trajectory(**arrays, obstacles=obstacles, **{**meta, "task_names": tuple(meta["task_names"])})


def _run_job(spec: RunSpec, factory: AllocatorFactory) -> tuple[dict[str, Any], bytes | None]:
    """A worker's job: the run's result and, if asked for, its thinned trajectory."""
    scenario, trajectory, times = _simulate(spec, factory)
    return _result(spec, scenario, trajectory, times), _track_bytes(trajectory) if spec.keep_track else None


class ProgressLine:
    """A one-line progress bar on a stream (stderr): runs done, reused, elapsed, time left.

    On a terminal the line is redrawn in place; elsewhere (logs, CI) a line is printed at
    every tenth of the work, at least every 30 s while runs finish, and at the end.
    """

    def __init__(self, total: int, label: str, *, reused: int = 0, stream: TextIO | None = None) -> None:
        self.total, self.label, self.reused = total, label, reused
        self.stream = stream if stream is not None else sys.stderr
        self.done = reused
        self.start = time.perf_counter()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._printed_tenth, self._printed_at = -1, self.start
        self._draw()

    def advance(self, count: int = 1) -> None:
        """Count ``count`` more finished runs."""
        self.done += count
        self._draw()

    def _draw(self) -> None:
        elapsed = time.perf_counter() - self.start
        computed, remaining = self.done - self.reused, self.total - self.done
        left = f", ~{_clock(elapsed / computed * remaining)} left" if computed and remaining else ""
        width = 24
        filled = width * self.done // max(self.total, 1)
        line = (
            f"{self.label} [{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} runs"
            + (f" ({self.reused} reused)" if self.reused else "")
            + f", {_clock(elapsed)} elapsed{left}"
        )
        if self._tty:
            print(
                "\r" + line + ("\n" if self.done >= self.total else ""), end="", file=self.stream, flush=True
            )
            return
        tenth = 10 * self.done // max(self.total, 1)
        if tenth > self._printed_tenth or time.perf_counter() - self._printed_at > 30:
            self._printed_tenth, self._printed_at = tenth, time.perf_counter()
            print(line, file=self.stream, flush=True)


def _clock(seconds: float) -> str:
    minutes, seconds = divmod(int(round(seconds)), 60)
    return f"{minutes}:{seconds:02d}"


def _execute(
    function: Callable[[Any], Any],
    items: Sequence[Any],
    *,
    workers: int,
    scheduler: Any = None,
) -> Iterator[tuple[int, Any]]:
    """Yield ``(index, function(item))`` as each item finishes: in this process
    (``workers <= 1``), in a process pool, or on a Dask scheduler (an address or a
    ``distributed.Client``). Pending work is cancelled if the consumer stops (Ctrl-C)."""
    if not items:
        return
    if scheduler is not None:
        yield from _execute_dask(function, items, scheduler)
    elif workers <= 1 or len(items) == 1:
        for index, item in enumerate(items):
            yield index, function(item)
    else:
        pool = ProcessPoolExecutor(max_workers=min(workers, len(items)))
        futures = {pool.submit(function, item): index for index, item in enumerate(items)}
        try:
            for future in as_completed(futures):
                yield futures[future], future.result()
        except BaseException:
            # Ctrl-C, a kill of the consumer or an error: stop the runs under way instead of
            # letting the interpreter wait for them (their results would be dropped anyway).
            _terminate_workers(pool)  # before shutdown, which forgets the processes
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()


def _terminate_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate the pool's worker processes (Python >= 3.14 has a method for it)."""
    if hasattr(pool, "terminate_workers"):
        pool.terminate_workers()
        return
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.terminate()


def _execute_dask(
    function: Callable[[Any], Any], items: Sequence[Any], scheduler: Any
) -> Iterator[tuple[int, Any]]:
    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ImportError as error:
        raise ImportError(
            "a Dask scheduler needs dask.distributed: pip install 'platoon-opt[dask]'"
        ) from error
    client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
    try:
        futures = {client.submit(function, item, pure=False): index for index, item in enumerate(items)}
        try:
            for future in dask_completed(futures):
                yield futures[future], future.result()
        finally:
            client.cancel(list(futures))
    finally:
        if client is not scheduler:
            client.close()


def _load(path: Path, fingerprint: str) -> dict[str, Any] | None:
    """A finished run's result if its file exists and matches ``fingerprint``."""
    try:
        result = json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    if result.get("fingerprint") != fingerprint:
        return None
    # JSON has no infinity: write_json stores it as a string.
    return {k: float(v) if v in ("inf", "-inf", "nan") else v for k, v in result.items()}


def run_specs(
    specs: Sequence[RunSpec],
    factory: AllocatorFactory,
    *,
    runs_dir: str | Path | None = None,
    workers: int | None = None,
    scheduler: Any = None,
    fresh: bool = False,
    progress: ProgressLine | None = None,
) -> list[dict[str, Any]]:
    """Run every spec (each at most once) and return their results in the order of ``specs``.

    Args:
        factory: ``solvers.get_allocator`` (module-level, so workers can unpickle it).
        runs_dir: folder of per-run result files; a run whose file holds a matching
            fingerprint is reused, every newly finished run is written there at once.
            None keeps nothing.
        workers: worker processes (default: the CPU count); 1 runs in this process.
        scheduler: a Dask scheduler address or ``distributed.Client``: run there instead.
        fresh: ignore finished runs in ``runs_dir`` (they are overwritten).
        progress: advanced once per finished (or reused) run.

    Raises:
        AllocationError: a strict spec's run failed (runs finished before are kept in ``runs_dir``).
    """
    workers = workers if workers is not None else (os.cpu_count() or 1)
    results: list[dict[str, Any] | None] = [None] * len(specs)
    unique: dict[str, int] = {}
    pending: list[int] = []
    for index, spec in enumerate(specs):
        if spec.key in unique:
            continue
        unique[spec.key] = index
        path = Path(runs_dir) / f"{spec.key}.json" if runs_dir is not None else None
        cached = None if fresh or path is None else _load(path, spec.fingerprint())
        if cached is not None and spec.strict and cached.get("fallback_steps", 0):
            cached = None  # it fell back: recompute, so that the strict run raises
        if cached is not None:
            results[index] = cached
        else:
            pending.append(index)
    if progress is not None:
        reused = len(unique) - len(pending)
        progress.reused += reused
        progress.advance(reused)
    # Longest runs first (smaller time step), so no worker idles at the end behind one.
    pending.sort(key=lambda index: -specs[index].steps)
    items = [specs[index] for index in pending]
    jobs = _execute(functools.partial(_run_job, factory=factory), items, workers=workers, scheduler=scheduler)
    for position, (result, track) in jobs:
        index = pending[position]
        # This process's fingerprint, the one the next call checks: it names the code this
        # process loaded (and forked into its workers), even if the files change meanwhile.
        result["fingerprint"] = specs[index].fingerprint()
        if runs_dir is not None:
            # The track first: a result file then always has its track (if it keeps one).
            if track is not None:
                write_atomic(Path(runs_dir) / f"{specs[index].key}.npz", track)
            write_json(Path(runs_dir) / f"{specs[index].key}.json", result)
        results[index] = result
        if progress is not None:
            progress.advance()
    return [results[unique[spec.key]] for spec in specs]  # type: ignore[misc]


def trajectories_of(
    specs: Sequence[RunSpec],
    factory: AllocatorFactory,
    *,
    workers: int | None = None,
    scheduler: Any = None,
) -> list[Trajectory]:
    """Full trajectories of ``specs`` (for figures), computed in parallel like ``run_specs``."""
    workers = workers if workers is not None else (os.cpu_count() or 1)
    trajectories: list[Trajectory | None] = [None] * len(specs)
    for index, trajectory in _execute(
        functools.partial(trajectory_of, factory=factory), list(specs), workers=workers, scheduler=scheduler
    ):
        trajectories[index] = trajectory
    return trajectories  # type: ignore[return-value]


# --- studies ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Study:
    """A comparison: every configuration on every scenario and seed, plus an ablation.

    Attributes:
        scenarios: the scenarios.
        configs: allocator configurations; the first is the baseline of every comparison
            (the paper's m = 0 by default).
        seeds: scenario seeds of the main comparison.
        duration: simulated time per run (s); None for each scenario's.
        variants: ablation variants (none for a plain comparison).
        ablation_seeds: seeds of the ablation runs (defaults to ``seeds``).
        ablation_roles: which configurations the ablation runs besides the baseline:
            "paper_m" (the paper's best m), "best_m" (ours), "best_other" (the best
            allocator other than the paper's iteration), as found by ``report.roles``.
        paper_iterations: scenario name -> the paper's best m.
        strict: every run ends with ``AllocationError`` at its first failed allocation
            (``RunSpec.strict``).
    """

    scenarios: tuple[Scenario, ...]
    configs: tuple[AllocatorConfig, ...]
    seeds: tuple[int, ...]
    duration: float | None = None
    variants: tuple[Variant, ...] = ()
    ablation_seeds: tuple[int, ...] = ()
    ablation_roles: tuple[str, ...] = ("paper_m", "best_m", "best_other")
    paper_iterations: Mapping[str, int] = field(default_factory=dict)
    strict: bool = False

    def __post_init__(self) -> None:
        if not self.scenarios or not self.configs or not self.seeds:
            raise ValueError("a study needs at least one scenario, configuration and seed")
        labels = [c.label for c in self.configs]
        if len(set(labels)) != len(labels):
            raise ValueError(f"configuration labels must be unique, got {labels}")
        names = [s.name for s in self.scenarios]
        if len(set(names)) != len(names):
            raise ValueError(f"scenario names must be unique, got {names}")
        if not self.ablation_seeds:
            object.__setattr__(self, "ablation_seeds", self.seeds)
        unknown = set(self.ablation_roles) - {"paper_m", "best_m", "best_other"}
        if unknown:
            raise ValueError(f"ablation_roles must be paper_m, best_m or best_other, got {sorted(unknown)}")

    @property
    def baseline(self) -> AllocatorConfig:
        """The configuration every other one is compared with."""
        return self.configs[0]

    def main_specs(self) -> list[RunSpec]:
        """Every scenario x configuration x seed, unchanged scenarios; the first seed's runs
        keep their tracks for the figures."""
        return [
            RunSpec(
                scenario,
                BASE,
                config,
                seed,
                self.duration,
                keep_track=seed == self.seeds[0],
                strict=self.strict,
            )
            for scenario in self.scenarios
            for config in self.configs
            for seed in self.seeds
        ]

    def ablation_specs(self, configs: Mapping[str, Sequence[AllocatorConfig]]) -> list[RunSpec]:
        """Every affecting variant x ``configs[scenario name]`` x ablation seed."""
        return [
            RunSpec(scenario, variant, config, seed, self.duration, strict=self.strict)
            for scenario in self.scenarios
            for variant in self.variants
            if variant.affects(scenario)
            for config in configs[scenario.name]
            for seed in self.ablation_seeds
        ]


@dataclass
class StudyResult:
    """Results of a study: per-run result dicts and the figure trajectories.

    Attributes:
        study: what was run.
        runs: one result dict per run (main and ablation), in a fixed order.
        ablation_configs: scenario name -> configurations the ablation ran.
        figures: scenario name -> (panel title, trajectory) of the first seed's figure runs
            (thinned: every ``TRACK_STRIDE``-th instant).
        wall_time: seconds the study took (reused runs cost nothing).
        computed: runs computed now (the rest were reused).
    """

    study: Study
    runs: list[dict[str, Any]]
    ablation_configs: dict[str, list[AllocatorConfig]]
    figures: dict[str, list[tuple[str, Trajectory]]]
    wall_time: float
    computed: int


def run_study(
    study: Study,
    factory: AllocatorFactory,
    out: str | Path,
    *,
    workers: int | None = None,
    scheduler: Any = None,
    fresh: bool = False,
    stream: TextIO | None = None,
    label: str = "runs",
    command: str = "",
) -> StudyResult:
    """Run a study into ``out/runs/`` (resumable) and write its report into ``out``.

    Order: the main comparison; then, per scenario, the ablation of the baseline and of
    ``study.ablation_roles`` (found from the main comparison); then the figures of the
    first seed (baseline, best m, best other allocator) from the tracks the main runs kept.

    Args:
        factory: ``solvers.get_allocator``.
        workers, scheduler, fresh: as in ``run_specs``.
        stream: where the progress lines go (default stderr).
        label: the progress lines' prefix.
        command: the command line, quoted in the report.

    Returns:
        The study's results (the report is ``out/report.md``).
    """
    from platoon_opt.study import report

    start = time.perf_counter()
    runs_dir = Path(out) / "runs"
    options = {"runs_dir": runs_dir, "workers": workers, "scheduler": scheduler, "fresh": fresh}
    main = study.main_specs()
    progress = ProgressLine(len(main), f"{label}: main", stream=stream)
    main_runs = run_specs(main, factory, progress=progress, **options)
    computed = progress.done - progress.reused
    roles = {scenario.name: report.roles(main_runs, study, scenario.name) for scenario in study.scenarios}
    ablation_configs = {
        name: _unique([study.baseline, *(role[k] for k in study.ablation_roles)])
        for name, role in roles.items()
    }
    ablation_runs: list[dict[str, Any]] = []
    ablation = study.ablation_specs(ablation_configs) if study.variants else []
    if ablation:
        progress = ProgressLine(len(ablation), f"{label}: ablation", stream=stream)
        ablation_runs = run_specs(ablation, factory, progress=progress, **options)
        computed += progress.done - progress.reused
    titled = [
        (scenario, title, config)
        for scenario in study.scenarios
        for title, config in _figure_configs(study, roles[scenario.name])
    ]
    specs = [
        RunSpec(scenario, BASE, config, study.seeds[0], study.duration, strict=study.strict)
        for scenario, _, config in titled
    ]
    tracks = [runs_dir / f"{spec.key}.npz" for spec in specs]
    # A track is missing when its run was reused from a study that kept none (other seeds).
    missing = [i for i, path in enumerate(tracks) if not path.exists()]
    simulated = trajectories_of([specs[i] for i in missing], factory, workers=workers, scheduler=scheduler)
    computed_tracks = dict(zip(missing, simulated))
    figures: dict[str, list[tuple[str, Trajectory]]] = {scenario.name: [] for scenario in study.scenarios}
    for i, ((scenario, title, _), path) in enumerate(zip(titled, tracks)):
        figures[scenario.name].append(
            (title, computed_tracks[i] if i in computed_tracks else load_track(path))
        )
    result = StudyResult(
        study=study,
        runs=main_runs + ablation_runs,
        ablation_configs=ablation_configs,
        figures=figures,
        wall_time=time.perf_counter() - start,
        computed=computed,
    )
    report.write_report(result, out, command=command)
    return result


def _figure_configs(
    study: Study, roles: Mapping[str, AllocatorConfig | None]
) -> list[tuple[str, AllocatorConfig]]:
    """(panel title, configuration) of a scenario's figures: the baseline, the best m and the
    best other allocator."""
    panels = [("baseline", study.baseline), ("best m", roles["best_m"]), ("best other", roles["best_other"])]
    seen: set[str] = set()
    titled = []
    for title, config in panels:
        if config is not None and config.label not in seen:
            seen.add(config.label)
            titled.append((f"{title}: {config.label}", config))
    return titled


def _unique(configs: Sequence[AllocatorConfig | None]) -> list[AllocatorConfig]:
    seen: dict[str, AllocatorConfig] = {}
    for config in configs:
        if config is not None and config.label not in seen:
            seen[config.label] = config
    return list(seen.values())


def seeds_range(count: int) -> tuple[int, ...]:
    """Seeds 0 .. count - 1.

    Raises:
        ValueError: ``count < 1``.
    """
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"seeds must be an integer >= 1, got {count!r}")
    return tuple(range(int(count)))


# The paper's best m per scenario (Sec. 4): the ablation runs it and the report compares at it.
PAPER_ITERATIONS = {"paper_no_obstacles": 4, "paper_obstacles": 3}

# ``reproduce`` defaults, chosen to finish within 10 minutes on 2 cores (measured; see README):
# 6 seeds for the main table, 3 for the ablation (7 and 3 took 10 min 54 s); --seeds 20 for the
# intervals the README quotes.
DEFAULT_SEEDS = 6
DEFAULT_ABLATION_SEEDS = 3
# ``reproduce --quick``: a check of the whole pipeline in under 2 minutes, not a result.
QUICK = {"seeds": 2, "ablation_seeds": 1, "duration": 8.0}
# The ablation asks whether the modelling choices explain the paper's magnitudes, which it
# states at its m: it runs m = 0 and the paper's m (``compare`` and ``--solvers`` studies can
# add the best m and the best other allocator).
REPRODUCE_ABLATION_ROLES = ("paper_m",)
# Registered allocators ``reproduce`` leaves out unless named with --solvers (``compare``
# runs them): too slow for the time budget, or a cross-check of another allocator.
REPRODUCE_EXCLUDED = {
    "nmpc": "receding horizon, 15-75 ms per step (a 45 s run takes minutes)",
    "casadi-qp": "cross-check of qp: the same QP through CasADi's qpOASES",
    "dual": "cross-check of qp: the same QP solved exactly through its 4-dimensional dual",
}


def reproduce_configs(available: Sequence[str]) -> list[AllocatorConfig]:
    """``default_configs`` without the allocators of ``REPRODUCE_EXCLUDED``."""
    return default_configs([name for name in available if name not in REPRODUCE_EXCLUDED])


def paper_study(
    available: Sequence[str],
    *,
    seeds: int = DEFAULT_SEEDS,
    ablation_seeds: int | None = DEFAULT_ABLATION_SEEDS,
    duration: float | None = None,
    configs: Sequence[AllocatorConfig] | None = None,
    variants: Sequence[Variant] = ABLATION_VARIANTS,
    strict: bool = False,
) -> Study:
    """The reproduction: both paper scenarios; m = 0..8 and every other registered allocator
    (``available``: ``solvers.available_allocators()``) but ``REPRODUCE_EXCLUDED``, unless
    ``configs`` are given; seeds 0..seeds-1; the ablation over ``variants`` of m = 0, the
    paper's m and the best other allocator on the first ``ablation_seeds`` seeds (None: all);
    ``strict``: see ``Study.strict``."""
    from platoon_opt.scenarios import PAPER_SCENARIOS, load_scenario

    main_seeds = seeds_range(seeds)
    ablation = main_seeds if ablation_seeds is None else main_seeds[: max(int(ablation_seeds), 1)]
    return Study(
        scenarios=tuple(load_scenario(name) for name in PAPER_SCENARIOS),
        configs=tuple(configs if configs is not None else reproduce_configs(available)),
        seeds=main_seeds,
        duration=duration,
        variants=tuple(variants),
        ablation_seeds=ablation,
        ablation_roles=REPRODUCE_ABLATION_ROLES,
        paper_iterations=PAPER_ITERATIONS,
        strict=strict,
    )
