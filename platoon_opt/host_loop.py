"""The host loop: a closed-loop run under an allocator that the compiled engine cannot run (one
that calls a host library, or needs the barrier rows), one step at a time on numpy arrays. Each
step hands the allocator its problem, then one compiled call moves the vehicles and poses the next
step's problem (docs/engine.md, "The host loop's step")."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from platoon_opt.allocation import Allocator, check_allocator
from platoon_opt.arrays import host
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.controller import PlatoonController, check_moved, drive, drive_compiled
from platoon_opt.problem import AllocationProblem, posed_fields, traceable
from platoon_opt.safety import SafetyParams
from platoon_opt.scenarios import Goal, Scenario
from platoon_opt.tasks import Task
from platoon_opt.trajectory import Trajectory
from platoon_opt.vehicle import PlatoonState, VehicleLimits


def scenario_controller(
    scenario: Scenario, allocator: Allocator, obstacles: CircularObstacles, *, strict: bool = False
) -> PlatoonController:
    """The host loop's controller of ``scenario`` under ``allocator``, with a seed's ``obstacles``
    (``Scenario.initial``): the scenario's task, gains, limits, avoidance and safety, and its
    target as the reference of an allocator that plans ahead."""
    task = scenario.task()
    goal = scenario.goal(task.names)
    return PlatoonController(
        task=task,
        gains=scenario.gains,
        limits=scenario.limits,
        allocator=allocator,
        avoidance=scenario.avoidance,
        obstacles=obstacles,
        strict=strict,
        safety=scenario.safety,
        reference=lambda time: goal.at(time)[0],
    )


def run_host_loop(
    scenario: Scenario,
    allocator: Allocator,
    seed: int,
    duration: float | None,
    strict: bool,
    progress: Callable[[int, int], None] | None,
) -> Trajectory:
    """``scenario`` run under ``allocator`` from ``seed`` in the host loop: ``simulation.simulate``
    with ``compiled=False``, whose arguments it takes as that function checked them."""
    state, obstacles = scenario.initial(seed)
    steps = scenario.run_steps(duration)
    controller = scenario_controller(scenario, allocator, obstacles, strict=strict)
    task = controller.task
    check_allocator(allocator, tuple(task.names))
    goal = scenario.goal(task.names)
    dt = scenario.dt
    n, m = scenario.n, len(task.names)
    t = np.arange(steps + 1) * dt
    try:
        log: dict[str, Any] = {key: np.empty((steps + 1, n)) for key in ("x", "y", "theta", "alpha", "gear")}
        task_value, desired = np.empty((steps + 1, m)), np.empty((steps + 1, m))
    except MemoryError:
        size = 8 * (steps + 1) * (5 * n + 2 * m) / 2**30
        raise ValueError(
            f"duration {duration if duration is not None else scenario.duration!r} s of {n:,} units needs "
            f"{size:.3g} GiB for the trajectory: too much memory"
        ) from None
    target = np.empty((steps + 1, 2))
    status = np.empty(steps, dtype=object)
    per_step: dict[str, Any] = {
        key: np.empty(steps) for key in ("iterations", "task_residual", "deviation", "solve_time")
    }
    fell_back, exempt = np.zeros(steps, dtype=bool), np.zeros(steps, dtype=int)
    solved = np.ones(steps, dtype=bool)
    program_changed = np.zeros(steps, dtype=bool)
    slack = np.zeros(steps, dtype=int)

    def record(k: int, state: PlatoonState, value: np.ndarray) -> None:
        for key in log:
            log[key][k] = getattr(state, key)
        task_value[k] = value

    stepper = _HostSteps(controller, goal, dt)
    problem, target[0] = stepper.posed(state, t[0])
    for k in range(steps):
        desired[k] = problem.desired
        allocation = controller.allocate(problem)
        record(k, state, problem.task_value)
        status[k] = allocation.status
        for key in per_step:
            per_step[key][k] = getattr(allocation, key)
        fell_back[k] = allocation.fell_back
        solved[k] = allocation.solved
        program_changed[k] = allocation.program_changed
        slack[k] = allocation.info.get("slack_units", 0)
        exempt[k] = int(np.count_nonzero(problem.exempt))
        waiting = controller.waiting(problem, allocation.velocities)
        state, problem, target[k + 1] = stepper.moved(state, allocation.velocities, waiting, t[k + 1])
        if progress is not None and (k + 1) % 100 == 0:
            progress(k + 1, steps)
    record(steps, state, problem.task_value)
    desired[steps] = problem.desired
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


def _drive_and_pose(
    state: PlatoonState,
    velocity: Any,
    waiting: Any,
    moving: Any,
    desired: Any,
    desired_rate: Any,
    t: Any,
    *,
    task: Task,
    gains: Any,
    limits: VehicleLimits,
    dt: Any,
    avoidance: AvoidanceParams,
    obstacles: CircularObstacles,
    safety: SafetyParams,
) -> Any:
    """The vehicles' step toward ``velocity`` (``controller.drive``; if ``moving`` is false the
    state stays), and what ``problem.pose`` computes for the new state at time ``t`` on f_d =
    ``desired``, f_d' = ``desired_rate`` (``problem.posed_fields``): the commands, the new state
    and those fields."""
    command, driven = drive(state, velocity, limits, dt, waiting)
    after = jax.tree_util.tree_map(lambda new, old: jnp.where(moving, new, old), driven, state)
    fields = posed_fields(
        after,
        task,
        desired,
        desired_rate,
        gains,
        limits,
        dt,
        avoidance=avoidance,
        obstacles=obstacles,
        t=t,
        safety=safety,
    )
    return command, after, fields


# Compiled, numpy out, with the numbers a run keeps static (as ``problem.AllocationProblem.build``):
# a call costs more than its arithmetic at small n, and one call per step that moves the vehicles
# and poses the next problem replaces a call to move and a call to pose.
_drive_and_pose_compiled = host(_drive_and_pose, static=("task", "safety", "limits", "avoidance", "dt"))


@dataclass(frozen=True)
class _HostSteps:
    """How the host loop poses each step's problem and moves the vehicles under ``controller``
    toward ``goal``, with steps of ``dt`` s: one compiled call per step (``_drive_and_pose``), or
    on the host for a task that a host library computes."""

    controller: PlatoonController
    goal: Goal
    dt: float

    @cached_property
    def _given(self) -> dict[str, Any] | None:
        """What every step's compiled call and problem take from the run (the task, gains, limits,
        dt, avoidance, obstacles and safety), built once; None for a task posed on the host."""
        controller = self.controller
        if not traceable(controller.task):
            return None
        return {
            "task": controller.task,
            "gains": np.asarray(controller.gains, dtype=float),
            "limits": controller.limits,
            "dt": self.dt,
            "avoidance": controller.avoidance,
            "obstacles": controller.obstacles,
            "safety": controller.safety,
        }

    def posed(self, state: PlatoonState, t: float) -> tuple[AllocationProblem, np.ndarray]:
        """The problem of ``state`` at time ``t`` (s), with f_d ahead for an allocator that plans
        ahead (``PlatoonController.previewed``), and the target's position (2,), m."""
        _, problem, target = self.moved(state, None, None, t)
        return problem, target

    def moved(
        self, state: PlatoonState, velocities: np.ndarray | None, waiting: np.ndarray | None, t: float
    ) -> tuple[PlatoonState, AllocationProblem, np.ndarray]:
        """The state after a step toward ``velocities`` (n, 2), m/s (None: no step; ``waiting``:
        see ``controller.drive``), and ``posed`` of it at time ``t``, the step's end.

        Raises:
            ValueError: a position that is not finite after the step (``controller.check_moved``).
        """
        controller, dt, given = self.controller, self.dt, self._given
        desired, rate, target = self.goal.at(t)
        if given is None:
            if velocities is not None:
                command, state = drive_compiled(state, velocities, controller.limits, dt, waiting)
                check_moved(command, state, dt)
            return state, controller.problem(state, desired, rate, dt, t), target
        moving = velocities is not None
        command, after, fields = _drive_and_pose_compiled(
            state,
            velocities if moving else np.zeros((state.n, 2)),
            waiting,
            moving,
            desired,
            rate,
            t,
            **given,
        )
        if moving:
            check_moved(command, after, dt)
        else:
            after = state
        problem = AllocationProblem(
            state=after, desired=desired, desired_rate=rate, t=float(t), **given, **fields
        )
        return after, controller.previewed(problem), target
