"""The step part: the whole control step with the dual (posing the problem: nominal velocity and
repulsion; the allocation, warm-started from the previous step's; unit controllers and vehicles)
over consecutive steps of a platoon tracking its target, against the floor of one vectorised
pass over the state.

Contract: one record of kind "step" per n, with the medians of each part and of the whole step.
"""

from __future__ import annotations

import functools
import statistics
import time
from typing import Any

import numpy as np

from platoon_opt import AllocationProblem, PlatoonState
from platoon_opt.controller import PlatoonController
from platoon_opt.solvers import get_allocator
from platoon_opt.study.bench.cases import scale_problem
from platoon_opt.study.bench.timing import Records, peak_memory
from platoon_opt.vehicle import step_vehicles, unit_controller


def _control_step(
    controller: PlatoonController, state: PlatoonState, problem: AllocationProblem, step: int
) -> tuple[tuple[float, float, float], PlatoonState]:
    """Control step ``step`` of a platoon tracking ``problem``'s target from ``state``: times (s)
    of posing the problem (task, Jacobian, repulsion, nominal velocity), of the allocation
    (warm-started from the previous step's), and of the unit controllers and vehicles; and
    the state after the step."""
    limits, dt = problem.limits, problem.dt
    t = problem.t + step * dt
    start = time.perf_counter()
    desired = problem.desired + step * dt * problem.desired_rate
    posed = controller.problem(state, desired, problem.desired_rate, dt, t)
    posed_at = time.perf_counter()
    allocation = controller.allocate(posed)
    allocated_at = time.perf_counter()
    after = step_vehicles(state, unit_controller(state, allocation.velocities, limits, dt), limits, dt)
    return (posed_at - start, allocated_at - posed_at, time.perf_counter() - allocated_at), after


def run_step(records: Records, sizes: tuple[int, ...]) -> None:
    """The whole control step with the dual along a closed loop (consecutive steps of a
    platoon tracking its target, each allocation warm-started from the previous step's), and
    the floor, per n."""
    for n in sizes:
        reps = 15 if n <= 4096 else 5
        problem = scale_problem(n, 0)
        controller = PlatoonController(
            task=problem.task,
            gains=np.array([50.0, 10, 50, 10]),
            limits=problem.limits,
            allocator=get_allocator("dual"),
        )
        _, state = _control_step(controller, problem.state, problem, 0)  # cold start, not timed
        steps = []
        for step in range(1, reps + 1):
            times, state = _control_step(controller, state, problem, step)
            steps.append(times)
        parts = np.array(steps)  # (reps, 3): the times of each step's parts
        x, y, out = problem.state.x, problem.state.y, np.empty(n)
        floor = []
        for _ in range(reps):
            start = time.perf_counter()
            np.add(x, y, out=out)
            floor.append(time.perf_counter() - start)
        medians = np.median(parts, axis=0)
        record: dict[str, Any] = {
            "kind": "step",
            "allocator": "dual",
            "n": n,
            "repetitions": reps,
            "problem": float(medians[0]),
            "allocate": float(medians[1]),
            "vehicles": float(medians[2]),
            "time": float(np.median(parts.sum(axis=1))),
            "floor": statistics.median(floor),
            "peak_memory_mb": peak_memory(
                functools.partial(_control_step, controller, state, problem, reps + 1)
            ),
        }
        records.add(**record)
        records.log(
            f"  n={n:>6} control step {record['time'] * 1e3:9.3f} ms (problem {medians[0] * 1e3:.3f}, "
            f"allocation {medians[1] * 1e3:.3f}, vehicles {medians[2] * 1e3:.3f}), "
            f"floor {record['floor'] * 1e6:.1f} us, peak {record['peak_memory_mb']:.1f} MB"
        )
