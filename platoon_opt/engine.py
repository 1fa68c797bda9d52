"""The compiled closed loop: a whole run, and a batch of runs, in one call.

The closed loop of ``platoon_opt.simulation`` (pose the problem, allocate, run the unit
controllers, move the vehicles) as one ``jax.lax.scan`` over the steps, for an allocator whose
step is itself a JAX kernel (``CompiledStep``), each step mapped over a batch of platoons with
``jax.vmap``, compiled with ``jax.jit``. The model's functions are the same ones the host loop
calls; only the driver differs. A batch shares the scenario (after its variant) and the
allocator's kernel; each platoon has its own initial state, obstacles, allocator numbers
(``CompiledStep.params``: m, rho, eps, ...) and carried state (warm starts).

What a run yields (``Batch``): the samples of every instant (``metrics.Instant``) and the records
of every step, from which ``metrics.score`` computes the run's scores exactly as
``metrics.integrated_errors`` does for a recorded trajectory; and the whole trajectories of the
platoons asked for (``record``), from the same program as the batch's other runs.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from platoon_opt.arrays import BATCH_AXIS, any_platoon, pytree
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.barrier_constraints import Capacity
from platoon_opt.controller import drive, standing_targets
from platoon_opt.metrics import Instant, instant
from platoon_opt.problem import AllocationProblem, pose, traceable
from platoon_opt.safety import SafetyParams
from platoon_opt.scenarios import Goal, Scenario
from platoon_opt.tasks import Task
from platoon_opt.vehicle import STANDING_SPEED, PlatoonState, VehicleLimits


class StepInfo(NamedTuple):
    """What a compiled allocator reports for one step (each a scalar).

    Attributes:
        iterations: iterations it ran.
        status: index into ``CompiledStep.statuses``.
        fell_back: whether its own method failed and a fallback answered.
        program_changed: whether the answer is another program's (``Allocation.program_changed``).
        slack: units whose barrier rows were relaxed (they started unsafe; 0 without barriers).
        overflow: whether some unit's barrier constraints did not fit the kernel's capacity
            (``barrier_constraints.Capacity``): the step's sets lack rows, and the run belongs in
            the host loop (``simulation``).
    """

    iterations: Any
    status: Any
    fell_back: Any
    program_changed: Any
    slack: Any = 0
    overflow: Any = False


class CompiledStep(NamedTuple):
    """An allocator as the engine runs it.

    ``kernel(static, params, problem, carry) -> (velocities (n, 2), carry, StepInfo)`` is a
    module-level function (the engine compiles one program per kernel and ``static``), pure and
    traceable; ``params`` are its numbers (a pytree: configurations that differ only in them share
    the compiled program); ``carry(n, m)`` builds what it carries from step to step for n units
    and m task rows (a pytree; e.g. warm-start multipliers); ``statuses`` name its status codes;
    ``safety`` are the barrier constraints its velocities keep (None: none), with which the unit
    controllers steer the units that stand (``controller.standing_targets``), as on the host.
    """

    kernel: Callable[..., tuple[Any, Any, StepInfo]]
    static: Hashable
    params: Any
    carry: Callable[[int, int], Any]
    statuses: tuple[str, ...]
    safety: SafetyParams | None = None


@runtime_checkable
class Compilable(Protocol):
    """An allocator that can run inside the engine."""

    def compiled(self, scenario: Scenario) -> CompiledStep | None:
        """Its step for ``scenario``; None when its options need the host (a feature the kernel
        lacks, e.g. the safety filter)."""
        ...


def compiled_step(allocator: Any, scenario: Scenario) -> CompiledStep | None:
    """``allocator``'s kernel for ``scenario``, or None if it runs on the host only (no kernel, a
    task written for a host library, or options the kernel lacks)."""
    if not isinstance(allocator, Compilable) or not traceable(scenario.task()):
        return None
    return allocator.compiled(scenario)


@pytree(data=("limits", "avoidance", "gains", "dt", "goal"), static=("task", "safety"))
@dataclass(frozen=True)
class Plant:
    """What every run of a batch shares: the vehicles, the avoidance, the gains K (m,) or (m, m),
    the step dt (s), the goal f_d(t), the task and the (scenario's) safety parameters."""

    limits: VehicleLimits
    avoidance: AvoidanceParams
    gains: Any
    dt: Any
    goal: Goal
    task: Task
    safety: SafetyParams

    @classmethod
    def of(cls, scenario: Scenario) -> Plant:
        """The plant of ``scenario``."""
        task = scenario.task()
        return cls(
            scenario.limits,
            scenario.avoidance,
            np.asarray(scenario.gains, dtype=float),
            float(scenario.dt),
            scenario.goal(tuple(task.names)),
            task,
            scenario.safety,
        )


@pytree(
    data=(
        "iterations",
        "status",
        "fell_back",
        "program_changed",
        "slack",
        "overflow",
        "residual",
        "deviation",
        "exempt",
        "flips",
    )
)
@dataclass(frozen=True)
class Steps:
    """The records of every step (a leading axis of T; with a batch, (B, T)).

    Attributes:
        iterations, status, fell_back, program_changed, slack, overflow: the allocator's
            ``StepInfo``.
        residual: ||J v - u|| of the handed velocities; deviation: ||v - q'_d|| (m/s).
        exempt: units under the precedence rule.
        flips: units whose gear changed in the step.
    """

    iterations: Any
    status: Any
    fell_back: Any
    program_changed: Any
    slack: Any
    overflow: Any
    residual: Any
    deviation: Any
    exempt: Any
    flips: Any


@pytree(data=("state", "task_value", "desired", "target"))
@dataclass(frozen=True)
class Record:
    """The recorded instants (a leading axis of T + 1): the platoon's state, f, f_d and the
    target's position (2,), m."""

    state: PlatoonState
    task_value: Any
    desired: Any
    target: Any


@pytree(data=("instants", "steps", "record", "final"), static=("recorded",))
@dataclass(frozen=True)
class Batch:
    """What ``run_batch`` returns, numpy arrays with a leading batch axis B.

    Attributes:
        instants: the samples of every instant (B, T + 1, ...) (``metrics.Instant``).
        steps: the records of every step (B, T) (``Steps``).
        record: the trajectories (R, T + 1, ...) of the R recorded platoons, or None (R = 0).
        recorded: the recorded platoons' indices, in the order of ``record``.
        final: the platoons' last states.
    """

    instants: Instant
    steps: Steps
    record: Record | None
    recorded: tuple[int, ...]
    final: PlatoonState


def _run(
    kernel: Callable[..., Any],
    static: Hashable,
    safety: SafetyParams | None,
    steps: int,
    plant: Plant,
    params: Any,
    initial: PlatoonState,
    obstacles: CircularObstacles,
    carry: Any,
    recorded: Any,
) -> tuple[Instant, Steps, Record, PlatoonState]:
    """A batch's run of ``steps`` steps (traced): the step of one platoon mapped over the
    platoons (``_mapped``: ``jax.vmap``, or the call itself for one) inside one scan over the
    steps, so that every step can keep the instants of the platoons ``recorded`` (R,) and a
    recording run shares its program with the runs of its batch. Outputs are time-major:
    instants (T + 1, B), records (T, B), the recorded instants (T + 1, R)."""
    dt, names = plant.dt, tuple(plant.task.names)

    def advance(state: PlatoonState, carried: Any, numbers: Any, around: CircularObstacles, k: Any) -> Any:
        t = k * dt
        desired, rate, target = plant.goal.at(t)
        problem = pose(
            state,
            plant.task,
            desired,
            rate,
            plant.gains,
            plant.limits,
            dt,
            avoidance=plant.avoidance,
            obstacles=around,
            t=t,
            safety=plant.safety,
        )
        velocity, carried, info = kernel(static, numbers, problem, carried)
        waiting = None
        if safety is not None:
            waiting, spilled = _standing_targets(problem, safety, velocity)
            info = info._replace(overflow=info.overflow | spilled)
        _, after = drive(state, velocity, plant.limits, dt, waiting)
        residual = problem.jacobian.apply(velocity) - problem.task_velocity
        gap = velocity - problem.nominal
        records = Steps(
            iterations=info.iterations,
            status=info.status,
            fell_back=info.fell_back,
            program_changed=info.program_changed,
            slack=jnp.asarray(info.slack),
            overflow=jnp.asarray(info.overflow),
            residual=jnp.sqrt(residual @ residual),
            deviation=jnp.sqrt(jnp.sum(gap * gap)),
            exempt=jnp.sum(problem.exempt),
            flips=jnp.sum(after.gear != state.gear),
        )
        measured = (problem.obstacle_distance, problem.unit_distance)
        sample = instant(state.positions, problem.task_value, desired, target, names, around, measured)
        return after, carried, sample, records, Record(state, problem.task_value, desired, target)

    def finish(state: PlatoonState, around: CircularObstacles) -> tuple[Instant, Record]:
        end = steps * dt
        desired, _, target = plant.goal.at(end)
        value = plant.task.value(state.positions, end)
        return instant(state.positions, value, desired, target, names, around), Record(
            state, value, desired, target
        )

    def pick(record: Record) -> Record:
        return jax.tree_util.tree_map(lambda leaf: leaf[recorded], record)

    def step(loop: tuple[PlatoonState, Any], k: Any) -> tuple[tuple[PlatoonState, Any], Any]:
        states, carried = loop
        after, carried, samples, records, record = _mapped(advance, initial.x.shape[0], (0, 0, 0, 0, None))(
            states, carried, params, obstacles, k
        )
        return (after, carried), (samples, records, pick(record))

    (final, _), (samples, records, kept) = jax.lax.scan(step, (initial, carry), jnp.arange(steps))
    last, last_record = _mapped(finish, initial.x.shape[0], (0, 0))(final, obstacles)

    def append(series: Any, item: Any) -> Any:
        return jax.tree_util.tree_map(lambda a, b: jnp.concatenate((a, b[None])), series, item)

    return append(samples, last), records, append(kept, pick(last_record)), final


def _standing_targets(problem: AllocationProblem, safety: SafetyParams, velocity: Any) -> tuple[Any, Any]:
    """``controller.standing_targets`` in the default ``Capacity``, searched only on a step where
    some unit of some platoon stands (``arrays.any_platoon``; the others keep their velocities)."""
    standing = any_platoon(jnp.any(jnp.hypot(velocity[:, 0], velocity[:, 1]) <= STANDING_SPEED))
    return jax.lax.cond(
        standing,
        lambda: standing_targets(problem, safety, velocity, capacity=Capacity()),
        lambda: (velocity, jnp.asarray(False)),
    )


def _mapped(
    function: Callable[..., Any], platoons: int, in_axes: tuple[int | None, ...]
) -> Callable[..., Any]:
    """``function`` of one platoon applied to each of ``platoons`` along the leading axis of the
    arguments whose ``in_axes`` is 0: ``jax.vmap``; for one platoon, the call itself with that axis
    taken off and put back, which compiles to fewer kernels than a batch of one under ``vmap``."""
    if platoons > 1:
        return jax.vmap(function, in_axes=in_axes, axis_name=BATCH_AXIS)

    def one(*args: Any) -> Any:
        inner = [
            jax.tree_util.tree_map(lambda leaf: leaf[0], arg) if axis == 0 else arg
            for arg, axis in zip(args, in_axes)
        ]
        return jax.tree_util.tree_map(lambda leaf: leaf[None], function(*inner))

    return one


# Platoons every batch of a study (and of ``simulation.simulate_batch``) is compiled for, the
# shorter padded: XLA rounds the same arithmetic differently in programs compiled for different
# batch sizes, so one size keeps a run's numbers independent of what runs beside it. Small,
# because under vmap the dual's Newton loop runs until the batch's slowest platoon has converged
# (measured: docs/engine.md, "Batches in a study"). A batch of 32 holds about 14 MB of records.
BATCH_SIZE = 32


# Compiled programs kept per process, the least recently used dropped first. Each holds about
# 350 (the iteration) to 650 (the dual) memory mappings of its machine code, and Linux allows a
# process 65,530 (vm.max_map_count): a test session that kept every program it compiled crashed
# inside XLA near that count.
PROGRAMS_KEPT = 32


@functools.lru_cache(maxsize=PROGRAMS_KEPT)
def _compiled(
    kernel: Callable[..., Any], static: Hashable, safety: SafetyParams | None, steps: int
) -> Callable[..., Any]:
    """``_run`` of one kernel, its static options, its barrier constraints and a run length,
    compiled (once per shape of the batch and number of recorded platoons)."""
    return jax.jit(functools.partial(_run, kernel, static, safety, steps))


def run_batch(
    step: CompiledStep,
    plant: Plant,
    initial: list[PlatoonState],
    obstacles: list[CircularObstacles],
    steps: int,
    *,
    params: list[Any] | None = None,
    record: Sequence[int] = (),
    size: int | None = None,
    record_size: int | None = None,
) -> Batch:
    """Run B platoons for ``steps`` steps in one compiled call.

    Args:
        step: the allocator's kernel, numbers and carry (``CompiledStep``).
        plant: what the runs share.
        initial, obstacles: each platoon's initial state and obstacles (B of each, of one n and
            one number of obstacles).
        params: each platoon's allocator numbers (B pytrees of one structure); None: ``step.params``
            for all.
        record: the platoons (indices) whose every instant is also returned (``Batch.record``;
            memory R (T + 1) (5 n + 2 m + 2) floats for R of them).
        size: compile for this many platoons (>= B; None: B), the rest copies of the last one
            whose results are dropped: calls of different B share one program.
        record_size: compile for this many recorded platoons (>= R; None: R), the rest copies of
            the last (or of platoon 0): calls that record different numbers share one program.
    """
    run, arguments = _prepare(step, plant, initial, obstacles, steps, params, record, size, record_size)
    instants, records, kept, final = jax.device_get(run(*arguments))

    def platoons_first(tree: Any, count: int) -> Any:
        return jax.tree_util.tree_map(lambda leaf: np.swapaxes(leaf, 0, 1)[:count], tree)

    count = len(initial)
    return Batch(
        instants=platoons_first(instants, count),
        steps=platoons_first(records, count),
        record=platoons_first(kept, len(record)) if len(record) else None,
        recorded=tuple(int(i) for i in record),
        final=jax.tree_util.tree_map(lambda leaf: leaf[:count], final),
    )


def batch_memory(
    step: CompiledStep,
    plant: Plant,
    initial: list[PlatoonState],
    obstacles: list[CircularObstacles],
    steps: int,
    *,
    params: list[Any] | None = None,
    record: Sequence[int] = (),
    size: int | None = None,
    record_size: int | None = None,
) -> int:
    """Bytes the compiled call of ``run_batch`` with these arguments holds at its peak (its
    arguments, outputs and temporary buffers, as XLA plans them), without running it."""
    run, arguments = _prepare(step, plant, initial, obstacles, steps, params, record, size, record_size)
    memory = run.lower(*arguments).compile().memory_analysis()
    return int(memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes)


def _prepare(
    step: CompiledStep,
    plant: Plant,
    initial: list[PlatoonState],
    obstacles: list[CircularObstacles],
    steps: int,
    params: list[Any] | None,
    record: Sequence[int],
    size: int | None = None,
    record_size: int | None = None,
) -> tuple[Any, tuple[Any, ...]]:
    """The compiled function of ``run_batch`` and its arguments, stacked along the batch axis
    (``size`` platoons: the last one repeated), and the recorded platoons (``record_size``)."""
    if not initial or len(initial) != len(obstacles):
        raise ValueError(
            f"run_batch: one obstacle set per initial state, got {len(initial)} and {len(obstacles)}"
        )
    if any(not 0 <= i < len(initial) for i in record):
        raise ValueError(f"run_batch: record {list(record)} names platoons outside 0..{len(initial) - 1}")
    rows = len(record) if record_size is None else record_size
    if rows < len(record):
        raise ValueError(f"run_batch: record_size {rows} is below the {len(record)} recorded platoons")
    recorded = np.array([*record, *[record[-1] if len(record) else 0] * (rows - len(record))], dtype=int)
    numbers = params if params is not None else [step.params] * len(initial)
    if size is not None:
        if size < len(initial):
            raise ValueError(f"run_batch: size {size} is below the {len(initial)} platoons")
        extra = size - len(initial)
        initial, obstacles, numbers = (
            [*items, *[items[-1]] * extra] for items in (initial, obstacles, numbers)
        )
    n, m = initial[0].n, len(plant.task.names)

    def stack(trees: list[Any]) -> Any:
        return jax.tree_util.tree_map(lambda *leaves: np.stack([np.asarray(leaf) for leaf in leaves]), *trees)

    carry = stack([step.carry(n, m)] * len(initial))
    run = _compiled(step.kernel, step.static, step.safety, int(steps))
    return run, (plant, stack(numbers), stack(initial), stack(obstacles), carry, recorded)
