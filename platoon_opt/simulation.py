"""Fixed-step closed-loop simulation of a scenario under one allocator."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.controller import PlatoonController
from platoon_opt.problem import Allocator, check_allocator
from platoon_opt.scenarios import Scenario
from platoon_opt.vehicle import PlatoonState


@dataclass(frozen=True)
class Trajectory:
    """Time series of one run. T steps; states are sampled at the T + 1 instants ``t``.

    Attributes:
        t: (T + 1,) s.
        x, y, theta, alpha, gear: (T + 1, n) unit states (m, rad, +-1).
        task_value, desired: f(q(t)) and f_d(t), (T + 1, m).
        target: target position (T + 1, 2), m.
        task_names: the m component names.
        status: allocation status per step (T,).
        iterations, task_residual, deviation, solve_time: per step (T,).
        fell_back: per step (T,) bool.
        exempt: number of units under the precedence rule per step (T,).
        obstacles: the obstacles of this run (after the seed's jitter).
        scenario, allocator, seed: what was run.
        dt: the time step (s).
        solved: per step (T,) bool, whether the allocation ran a solve (``Allocation.solved``;
            False where ``nmpc`` handed its stored plan). None, as a trajectory built without it
            passes, is replaced by every step solving.
        program_changed: per step (T,) bool, whether the allocation answered another program
            than its allocator poses (``Allocation.program_changed``). None (a trajectory
            built without it) is replaced by no step changing it.
        slack: per step (T,) int, units whose barrier rows were relaxed (``info["slack_units"]``);
            None (a trajectory built without it) is replaced by zeros.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    gear: np.ndarray
    task_value: np.ndarray
    desired: np.ndarray
    target: np.ndarray
    task_names: tuple[str, ...]
    status: np.ndarray
    iterations: np.ndarray
    task_residual: np.ndarray
    deviation: np.ndarray
    solve_time: np.ndarray
    fell_back: np.ndarray
    exempt: np.ndarray
    obstacles: CircularObstacles
    scenario: str
    allocator: str
    seed: int
    dt: float
    solved: np.ndarray | None = None
    program_changed: np.ndarray | None = None
    slack: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.solved is None:
            object.__setattr__(self, "solved", np.ones(self.steps, dtype=bool))
        if self.program_changed is None:
            object.__setattr__(self, "program_changed", np.zeros(self.steps, dtype=bool))
        if self.slack is None:
            object.__setattr__(self, "slack", np.zeros(self.steps, dtype=int))

    @property
    def steps(self) -> int:
        """Number of steps T."""
        return self.t.shape[0] - 1

    def component(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """f and f_d of the task component ``name``, each (T + 1,)."""
        k = self.task_names.index(name)
        return self.task_value[:, k], self.desired[:, k]


def simulate(
    scenario: Scenario,
    allocator: Allocator,
    *,
    seed: int = 0,
    duration: float | None = None,
    strict: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Trajectory:
    """Run ``scenario`` for ``duration`` seconds (default: the scenario's) under ``allocator``.

    Args:
        seed: picks the initial state and obstacle jitter (``Scenario.initial``), an integer >= 0.
        duration: at least one step ``scenario.dt`` and at most ``MAX_STEPS`` steps (s).
        strict: let an allocator exception end the run instead of falling back.
        progress: called as ``progress(step, total)`` every 100 steps.

    Raises:
        ValueError: a bad ``seed`` or ``duration`` (naming it and the value), before any step.
        OptionError: the allocator's options do not fit the scenario's task
            (``problem.check_allocator``), before any step; or any ``ConfigurationError`` an
            allocator raises during the run, which no fallback answers.
        AllocationError: with ``strict``, the first step whose allocation failed or fell back.
    """
    # One BLAS thread: the step's matrices are tiny, and OpenBLAS's idle threads spinning beside
    # parallel runs made the receding-horizon allocator six times slower (measured).
    with threadpool_limits(limits=1, user_api="blas"):
        return _simulate(scenario, allocator, seed, duration, strict, progress)


def _simulate(
    scenario: Scenario,
    allocator: Allocator,
    seed: int,
    duration: float | None,
    strict: bool,
    progress: Callable[[int, int], None] | None,
) -> Trajectory:
    state, obstacles = scenario.initial(seed)
    steps = scenario.run_steps(duration)
    task = scenario.task()
    check_allocator(allocator, tuple(task.names))
    controller = PlatoonController(
        task=task,
        gains=scenario.gains,
        limits=scenario.limits,
        allocator=allocator,
        avoidance=scenario.avoidance,
        obstacles=obstacles,
        strict=strict,
        safety=scenario.safety,
    )
    dt = scenario.dt
    n, m = scenario.n, len(task.names)
    t = np.arange(steps + 1) * dt
    try:
        log = {key: np.empty((steps + 1, n)) for key in ("x", "y", "theta", "alpha", "gear")}
        task_value, desired = np.empty((steps + 1, m)), np.empty((steps + 1, m))
    except MemoryError:
        size = 8 * (steps + 1) * (5 * n + 2 * m) / 2**30
        raise ValueError(
            f"duration {duration if duration is not None else scenario.duration!r} s of {n:,} units needs "
            f"{size:.3g} GiB for the trajectory: too much memory"
        ) from None
    target = np.empty((steps + 1, 2))
    status = np.empty(steps, dtype=object)
    per_step = {key: np.empty(steps) for key in ("iterations", "task_residual", "deviation", "solve_time")}
    fell_back, exempt = np.zeros(steps, dtype=bool), np.zeros(steps, dtype=int)
    solved = np.ones(steps, dtype=bool)
    program_changed = np.zeros(steps, dtype=bool)
    slack = np.zeros(steps, dtype=int)

    def record(k: int, state: PlatoonState, value: np.ndarray) -> None:
        for key in log:
            log[key][k] = getattr(state, key)
        task_value[k] = value

    for k in range(steps):
        desired[k], rate, target[k] = scenario.desired_at(task.names, t[k])
        result = controller.step(state, desired[k], rate, dt, t[k])
        record(k, state, result.problem.task_value)
        allocation = result.allocation
        status[k] = allocation.status
        for key in per_step:
            per_step[key][k] = getattr(allocation, key)
        fell_back[k] = allocation.fell_back
        solved[k] = allocation.solved
        program_changed[k] = allocation.program_changed
        slack[k] = allocation.info.get("slack_units", 0)
        exempt[k] = int(np.count_nonzero(result.problem.exempt))
        state = result.state
        if progress is not None and (k + 1) % 100 == 0:
            progress(k + 1, steps)
    record(steps, state, task.value(state.positions, t[steps]))
    desired[steps], _, target[steps] = scenario.desired_at(task.names, t[steps])
    return Trajectory(
        t=t,
        **log,
        task_value=task_value,
        desired=desired,
        target=target,
        task_names=tuple(task.names),
        status=status,
        **per_step,
        fell_back=fell_back,
        exempt=exempt,
        obstacles=obstacles,
        scenario=scenario.name,
        allocator=allocator.name,
        seed=seed,
        dt=dt,
        solved=solved,
        program_changed=program_changed,
        slack=slack,
    )
