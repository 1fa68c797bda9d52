"""The compiled closed loop: a whole run, and a batch of runs, in one call.

The closed loop of ``platoon_opt.simulation`` (pose the problem, allocate, run the unit
controllers, move the vehicles) as one ``jax.lax.scan`` over the steps, for an allocator whose
step is itself a JAX kernel (``CompiledStep``), batched over platoons with ``jax.vmap`` and
compiled with ``jax.jit``. The model's functions are the same ones the host loop calls; only the
driver differs. A batch shares the scenario (after its variant) and the allocator's kernel; each
platoon has its own initial state, obstacles, allocator numbers (``CompiledStep.params``: m, rho,
eps, ...) and carried state (warm starts).

What a run yields (``Batch``): the samples of every instant (``metrics.Instant``) and the records
of every step, from which ``metrics.score`` computes the run's scores exactly as
``metrics.integrated_errors`` does for a recorded trajectory; and, when asked (``record=True``),
the whole trajectory.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from platoon_opt.arrays import pytree
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.controller import drive
from platoon_opt.metrics import Instant, instant
from platoon_opt.problem import pose, traceable
from platoon_opt.safety import SafetyParams
from platoon_opt.scenarios import Goal, Scenario
from platoon_opt.tasks import Task
from platoon_opt.vehicle import PlatoonState, VehicleLimits


class StepInfo(NamedTuple):
    """What a compiled allocator reports for one step (each a scalar).

    Attributes:
        iterations: iterations it ran.
        status: index into ``CompiledStep.statuses``.
        fell_back: whether its own method failed and a fallback answered.
        program_changed: whether the answer is another program's (``Allocation.program_changed``).
    """

    iterations: Any
    status: Any
    fell_back: Any
    program_changed: Any


class CompiledStep(NamedTuple):
    """An allocator as the engine runs it.

    ``kernel(static, params, problem, carry) -> (velocities (n, 2), carry, StepInfo)`` is a
    module-level function (the engine compiles one program per kernel and ``static``), pure and
    traceable; ``params`` are its numbers (a pytree: configurations that differ only in them share
    the compiled program); ``carry(n, m)`` builds what it carries from step to step for n units
    and m task rows (a pytree; e.g. warm-start multipliers); ``statuses`` name its status codes.
    """

    kernel: Callable[..., tuple[Any, Any, StepInfo]]
    static: Hashable
    params: Any
    carry: Callable[[int, int], Any]
    statuses: tuple[str, ...]


@runtime_checkable
class Compilable(Protocol):
    """An allocator that can run inside the engine."""

    def compiled(self, safety: SafetyParams) -> CompiledStep | None:
        """Its step for a scenario whose ``[safety]`` table is ``safety``; None when its options
        need the host (a feature the kernel lacks, e.g. barrier constraints)."""
        ...


def compiled_step(allocator: Any, scenario: Scenario) -> CompiledStep | None:
    """``allocator``'s kernel for ``scenario``, or None if it runs on the host only (no kernel, a
    task written for a host library, or options the kernel lacks)."""
    if not isinstance(allocator, Compilable) or not traceable(scenario.task()):
        return None
    return allocator.compiled(scenario.safety)


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
    data=("iterations", "status", "fell_back", "program_changed", "residual", "deviation", "exempt", "flips")
)
@dataclass(frozen=True)
class Steps:
    """The records of every step (a leading axis of T; with a batch, (B, T)).

    Attributes:
        iterations, status, fell_back, program_changed: the allocator's ``StepInfo``.
        residual: ||J v - u|| of the handed velocities; deviation: ||v - q'_d|| (m/s).
        exempt: units under the precedence rule.
        flips: units whose gear changed in the step.
    """

    iterations: Any
    status: Any
    fell_back: Any
    program_changed: Any
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


@pytree(data=("instants", "steps", "record", "final"))
@dataclass(frozen=True)
class Batch:
    """What ``run_batch`` returns, numpy arrays with a leading batch axis B.

    Attributes:
        instants: the samples of every instant (B, T + 1, ...) (``metrics.Instant``).
        steps: the records of every step (B, T) (``Steps``).
        record: the trajectories (B, T + 1, ...) if asked for, else None.
        final: the platoons' last states.
    """

    instants: Instant
    steps: Steps
    record: Record | None
    final: PlatoonState


def _run(
    kernel: Callable[..., Any],
    static: Hashable,
    steps: int,
    record: bool,
    plant: Plant,
    params: Any,
    initial: PlatoonState,
    obstacles: CircularObstacles,
    carry: Any,
) -> tuple[Instant, Steps, Record | None, PlatoonState]:
    """One platoon's run of ``steps`` steps (traced)."""
    dt, names = plant.dt, tuple(plant.task.names)

    def observe(
        state: PlatoonState, value: Any, desired: Any, target: Any, measured: tuple[Any, Any] | None
    ) -> tuple[Instant, Record | None]:
        sample = instant(state.positions, value, desired, target, names, obstacles, measured)
        return sample, (Record(state, value, desired, target) if record else None)

    def step(loop: tuple[PlatoonState, Any], k: Any) -> tuple[tuple[PlatoonState, Any], Any]:
        state, carried = loop
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
            obstacles=obstacles,
            t=t,
            safety=plant.safety,
        )
        velocity, carried, info = kernel(static, params, problem, carried)
        _, after = drive(state, velocity, plant.limits, dt)
        residual = problem.jacobian.apply(velocity) - problem.task_velocity
        gap = velocity - problem.nominal
        records = Steps(
            iterations=info.iterations,
            status=info.status,
            fell_back=info.fell_back,
            program_changed=info.program_changed,
            residual=jnp.sqrt(residual @ residual),
            deviation=jnp.sqrt(jnp.sum(gap * gap)),
            exempt=jnp.sum(problem.exempt),
            flips=jnp.sum(after.gear != state.gear),
        )
        measured = (problem.obstacle_distance, problem.unit_distance)
        return (after, carried), (observe(state, problem.task_value, desired, target, measured), records)

    (final, _), ((samples, recorded), records) = jax.lax.scan(step, (initial, carry), jnp.arange(steps))
    end = steps * dt
    desired, _, target = plant.goal.at(end)
    last, last_record = observe(final, plant.task.value(final.positions, end), desired, target, None)

    def append(series: Any, item: Any) -> Any:
        return jax.tree_util.tree_map(lambda a, b: jnp.concatenate((a, b[None])), series, item)

    return append(samples, last), records, (append(recorded, last_record) if record else None), final


# Compiled programs kept per process, the least recently used dropped first. Each holds about
# 350 (the iteration) to 650 (the dual) memory mappings of its machine code, and Linux allows a
# process 65,530 (vm.max_map_count): a test session that kept every program it compiled crashed
# inside XLA near that count.
PROGRAMS_KEPT = 32


@functools.lru_cache(maxsize=PROGRAMS_KEPT)
def _compiled(kernel: Callable[..., Any], static: Hashable, steps: int, record: bool) -> Callable[..., Any]:
    """``_run`` of one kernel, its static options, a run length and a record mode, batched and
    compiled (once per shape of the batch)."""

    def one(
        plant: Plant, params: Any, initial: PlatoonState, obstacles: CircularObstacles, carry: Any
    ) -> Any:
        return _run(kernel, static, steps, record, plant, params, initial, obstacles, carry)

    return jax.jit(jax.vmap(one, in_axes=(None, 0, 0, 0, 0)))


def run_batch(
    step: CompiledStep,
    plant: Plant,
    initial: list[PlatoonState],
    obstacles: list[CircularObstacles],
    steps: int,
    *,
    params: list[Any] | None = None,
    record: bool = False,
    size: int | None = None,
) -> Batch:
    """Run B platoons for ``steps`` steps in one compiled call.

    Args:
        step: the allocator's kernel, numbers and carry (``CompiledStep``).
        plant: what the runs share.
        initial, obstacles: each platoon's initial state and obstacles (B of each, of one n and
            one number of obstacles).
        params: each platoon's allocator numbers (B pytrees of one structure); None: ``step.params``
            for all.
        record: also return every instant's state (memory B (T + 1) (5 n + 2 m + 2) floats).
        size: compile for this many platoons (>= B; None: B), the rest copies of the last one
            whose results are dropped: calls of different B share one program.
    """
    run, arguments = _prepare(step, plant, initial, obstacles, steps, params, record, size)
    batch = jax.device_get(Batch(*run(*arguments)))
    if size is None or size == len(initial):
        return batch
    return jax.tree_util.tree_map(lambda leaf: leaf[: len(initial)], batch)


def batch_memory(
    step: CompiledStep,
    plant: Plant,
    initial: list[PlatoonState],
    obstacles: list[CircularObstacles],
    steps: int,
    *,
    params: list[Any] | None = None,
    record: bool = False,
    size: int | None = None,
) -> int:
    """Bytes the compiled call of ``run_batch`` with these arguments holds at its peak (its
    arguments, outputs and temporary buffers, as XLA plans them), without running it."""
    run, arguments = _prepare(step, plant, initial, obstacles, steps, params, record, size)
    memory = run.lower(*arguments).compile().memory_analysis()
    return int(memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes)


def _prepare(
    step: CompiledStep,
    plant: Plant,
    initial: list[PlatoonState],
    obstacles: list[CircularObstacles],
    steps: int,
    params: list[Any] | None,
    record: bool,
    size: int | None = None,
) -> tuple[Any, tuple[Any, ...]]:
    """The compiled function of ``run_batch`` and its arguments, stacked along the batch axis
    (``size`` platoons: the last one repeated)."""
    if not initial or len(initial) != len(obstacles):
        raise ValueError(
            f"run_batch: one obstacle set per initial state, got {len(initial)} and {len(obstacles)}"
        )
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
    run = _compiled(step.kernel, step.static, int(steps), bool(record))
    return run, (plant, stack(numbers), stack(initial), stack(obstacles), carry)
