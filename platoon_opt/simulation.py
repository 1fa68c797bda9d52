"""Fixed-step closed-loop simulation of a scenario under one allocator: compiled
(``platoon_opt.engine``) when the allocator has a kernel, else the host loop
(``platoon_opt.host_loop``), which calls the allocator once per step on numpy arrays."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import jax
import numpy as np

from platoon_opt.allocation import Allocator, check_allocator
from platoon_opt.arrays import one_blas_thread
from platoon_opt.avoidance import CircularObstacles
from platoon_opt.engine import BATCH_SIZE, Batch, CompiledStep, Plant, compiled_step, run_batch
from platoon_opt.errors import AllocationError
from platoon_opt.host_loop import run_host_loop
from platoon_opt.metrics import integrated_errors, score
from platoon_opt.scenarios import Scenario, check_seed
from platoon_opt.trajectory import Trajectory


def simulate(
    scenario: Scenario,
    allocator: Allocator,
    *,
    seed: int = 0,
    duration: float | None = None,
    strict: bool = False,
    progress: Callable[[int, int], None] | None = None,
    compiled: bool | None = None,
) -> Trajectory:
    """Run ``scenario`` for ``duration`` seconds (default: the scenario's) under ``allocator``.

    Args:
        seed: picks the initial state and obstacle jitter (``Scenario.initial``), an integer >= 0.
        duration: at least one step ``scenario.dt`` and at most ``MAX_STEPS`` steps (s).
        strict: let an allocator exception end the run instead of falling back.
        progress: called as ``progress(step, total)`` every 100 steps (the host loop) or once at
            the end (compiled).
        compiled: run in the compiled engine (True), in the host loop (False), or the first where
            the allocator has a kernel for this scenario (None, ``engine.compiled_step``). A
            compiled run whose barrier constraints overflowed the kernel's capacity
            (``overflowed``) runs again in the host loop, which its trajectory says
            (``Trajectory.compiled``).

    Raises:
        ValueError: a bad ``seed`` or ``duration`` (naming it and the value), before any step.
        OptionError: the allocator's options do not fit the scenario's task
            (``allocation.check_allocator``), before any step; or any ``ConfigurationError`` an
            allocator raises during the run, which no fallback answers.
        AllocationError: with ``strict``, the first step whose allocation failed or fell back.
    """
    step = compiled_step(allocator, scenario) if compiled is not False else None
    if compiled and step is None:
        raise ValueError(
            f"simulate: {allocator.name} has no compiled kernel for {scenario.name}: compiled=True"
        )
    if step is not None:
        return _simulate_compiled(scenario, allocator, step, seed, duration, strict, progress)
    # One BLAS thread: the step's matrices are tiny, and OpenBLAS's idle threads spinning beside
    # parallel runs made the receding-horizon allocator six times slower (measured).
    with one_blas_thread():
        return run_host_loop(scenario, allocator, seed, duration, strict, progress)


def _simulate_compiled(
    scenario: Scenario,
    allocator: Allocator,
    step: CompiledStep,
    seed: int,
    duration: float | None,
    strict: bool,
    progress: Callable[[int, int], None] | None,
) -> Trajectory:
    state, obstacles = scenario.initial(check_seed(seed))
    steps = scenario.run_steps(duration)
    check_allocator(allocator, tuple(scenario.task().names))
    batch = run_batch(step, Plant.of(scenario), [state], [obstacles], steps, record=[0])
    if overflowed(batch, 0):
        with one_blas_thread():
            return run_host_loop(scenario, allocator, seed, duration, strict, progress)
    trajectory = batch_trajectory(batch, 0, scenario, obstacles, allocator.name, step, seed)
    if progress is not None:
        progress(steps, steps)
    if strict and trajectory.fell_back.any():
        k = int(np.argmax(trajectory.fell_back))
        raise AllocationError(
            allocator=allocator.name, reason=f"fell back: {trajectory.status[k]}", t=float(trajectory.t[k])
        )
    return trajectory


def simulate_batch(
    scenario: Scenario,
    allocator: Allocator,
    seeds: Iterable[int],
    *,
    duration: float | None = None,
    strict: bool = False,
) -> list[dict[str, float]]:
    """Run ``scenario`` under ``allocator`` from every seed of ``seeds`` and score each run
    (``metrics.integrated_errors``, with the scenario's transient): in the compiled engine when the
    allocator has a kernel for the scenario, in calls of ``engine.BATCH_SIZE`` platoons (the last
    padded) as a study runs them, so that a seed's scores are a study's to the bit; else one run
    after another in the host loop (and so is a run that ``overflowed``). ``duration`` and
    ``strict`` as ``simulate``.

    Raises:
        ValueError: a bad seed or duration; AllocationError: with ``strict``, a run that fell back.
    """
    seeds = [check_seed(seed) for seed in seeds]
    step = compiled_step(allocator, scenario)
    if step is None:
        return [
            integrated_errors(
                simulate(scenario, allocator, seed=seed, duration=duration, strict=strict), scenario.transient
            )
            for seed in seeds
        ]
    steps = scenario.run_steps(duration)
    check_allocator(allocator, tuple(scenario.task().names))
    plant, scores = Plant.of(scenario), []
    for first in range(0, len(seeds), BATCH_SIZE):
        starts = [scenario.initial(seed) for seed in seeds[first : first + BATCH_SIZE]]
        batch = run_batch(step, plant, [s for s, _ in starts], [o for _, o in starts], steps, size=BATCH_SIZE)
        for i, seed in enumerate(seeds[first : first + BATCH_SIZE]):
            if overflowed(batch, i):
                hosted = simulate(
                    scenario, allocator, seed=seed, duration=duration, strict=strict, compiled=False
                )
                scores.append(integrated_errors(hosted, scenario.transient))
                continue
            result, (status, t) = batch_scores(batch, i, scenario, step)
            if strict and status:
                raise AllocationError(allocator=allocator.name, reason=f"fell back: {status}", t=t)
            scores.append(result)
    return scores


def overflowed(batch: Batch, index: int) -> bool:
    """Whether run ``index`` of ``batch`` overflowed its kernel's barrier capacity on some step
    (``engine.StepInfo.overflow``): its sets lacked rows there, so it must run in the host loop."""
    return bool(np.any(batch.steps.overflow[index]))


def batch_scores(
    batch: Batch, index: int, scenario: Scenario, step: CompiledStep
) -> tuple[dict[str, float], tuple[str, float | None]]:
    """Run ``index`` of ``batch``'s scores (``metrics.score``, as ``integrated_errors`` gives them for
    a recorded trajectory) and its first fallback: the status and the time (s), or ("", None)."""
    instants = jax.tree_util.tree_map(lambda a: a[index], batch.instants)
    records = jax.tree_util.tree_map(lambda a: a[index], batch.steps)
    count = records.status.shape[0]
    scores = score(
        instants,
        dt=scenario.dt,
        transient=scenario.transient,
        names=tuple(scenario.task().names),
        gear_flips=int(records.flips.sum()),
        fell_back=records.fell_back,
        program_changed=records.program_changed,
        slack=records.slack,
        solved=np.ones(count, dtype=bool),
        solve_time=np.full(count, np.nan),
    )
    fell = np.flatnonzero(records.fell_back)
    if not fell.size:
        return scores, ("", None)
    return scores, (step.statuses[int(records.status[fell[0]])], float(fell[0] * scenario.dt))


def batch_trajectory(
    batch: Batch,
    index: int,
    scenario: Scenario,
    obstacles: CircularObstacles,
    allocator: str,
    step: CompiledStep,
    seed: int,
) -> Trajectory:
    """Run ``index`` of ``batch`` (``engine.run_batch``, which recorded it: ``record``) of
    ``scenario``, with its ``obstacles``, as a trajectory."""
    if index not in batch.recorded:
        raise ValueError(f"batch_trajectory: run {index} was not recorded (recorded: {list(batch.recorded)})")
    assert batch.record is not None  # a batch that recorded runs holds their record
    row = batch.recorded.index(index)
    record, steps = batch.record, batch.steps
    state = record.state
    count = steps.status.shape[1]
    return Trajectory(
        t=np.arange(count + 1) * scenario.dt,
        x=state.x[row],
        y=state.y[row],
        theta=state.theta[row],
        alpha=state.alpha[row],
        gear=state.gear[row],
        task_value=record.task_value[row],
        desired=record.desired[row],
        target=record.target[row],
        task_names=tuple(scenario.task().names),
        status=np.array([step.statuses[code] for code in steps.status[index]], dtype=object),
        iterations=steps.iterations[index],
        task_residual=steps.residual[index],
        deviation=steps.deviation[index],
        solve_time=np.full(count, np.nan),
        fell_back=steps.fell_back[index],
        exempt=steps.exempt[index],
        obstacles=obstacles,
        scenario=scenario.name,
        allocator=allocator,
        seed=seed,
        dt=scenario.dt,
        program_changed=steps.program_changed[index],
        slack=steps.slack[index],
        compiled=True,
    )
