"""The paper's allocator (Sec. 3.2): iterative null-space projection of the velocity error.

Each sweep adds, for every unit not under the precedence rule, the gap between its
closest achievable velocity and its desired velocity to a correction ``v_corr``, and
recomputes ``q'_d = J^+ u + N (v_rep + v_corr)``. One sweep is the alternating projection
``a <- P_A(P_C(a))`` between the task set ``A = {a : J a = u}`` and the achievable set
(exempt units take ``P_C = identity``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from platoon_opt.limits import AchievableSets
from platoon_opt.problem import Allocation, AllocationProblem
from platoon_opt.solvers.options import Choice, Integer, Option, check_options
from platoon_opt.solvers.registry import register
from platoon_opt.solvers.safety import SafetyOptions, safety_filter

# A velocity this close to its achievable set (m/s) counts as achievable.
ACHIEVABLE_TOLERANCE = 1e-9


MAX_ITERATIONS = Option(
    "max_iterations", 4, "the paper's m: sweeps at most (0: Eq. 5 alone)", Integer(at_least=0)
)
GEARS = Option(
    "gears",
    "either",
    "the sets projected onto: either gear's sector (the paper's) or the model gear rule's",
    Choice(("either", "model")),
)


@dataclass(frozen=True)
class IterativeProjection(SafetyOptions):
    """The paper's iteration with at most ``max_iterations`` sweeps (0 = Eq. 5 alone).

    Attributes:
        max_iterations: the paper's m.
        gears: "either" projects each unit onto the nearer of its forward and backing
            sectors (the paper's achievable set, both gears being reachable); "model"
            onto the sector of the gear chosen by the model's gear rule.
        safety, ...: with barriers on, the answer goes through ``safety_filter`` (each unit's
            velocity projected onto its safe set; ``SafetyOptions``).
    """

    max_iterations: int = MAX_ITERATIONS.field()
    gears: str = GEARS.field()

    def __post_init__(self) -> None:
        check_options(self, "iterative")

    @property
    def name(self) -> str:
        return f"iterative({', '.join([f'm={self.max_iterations}', *self.safety_name()])})"

    def allocate(self, problem: AllocationProblem) -> Allocation:
        start = time.perf_counter()
        desired, status, sweeps = problem.nominal, "nominal", 0
        if self.max_iterations:
            desired, status, sweeps = self._sweeps(problem)
        allocation = Allocation.of(
            problem,
            desired,
            allocator=self.name,
            status=status,
            iterations=sweeps,
            solve_time=time.perf_counter() - start,
        )
        return safety_filter(problem, allocation, self.safety_for(problem))

    def _sweeps(self, problem: AllocationProblem) -> tuple[np.ndarray, str, int]:
        """The iteration from the nominal velocity: (velocities, status, sweeps run)."""
        jacobian = problem.jacobian
        if self.gears == "model":
            project = problem.achievable().project
        else:
            sets = AchievableSets.for_gear(problem.state, np.ones(problem.n), problem.limits)
            project = sets.project_either_gear
        corrected = ~problem.exempt[:, None]
        base = jacobian.pinv_apply(problem.task_velocity)
        correction = np.zeros_like(problem.nominal)
        desired = problem.nominal
        for sweep in range(self.max_iterations):
            gap = np.where(corrected, project(desired) - desired, 0.0)
            if np.max(np.abs(gap), initial=0.0) <= ACHIEVABLE_TOLERANCE:
                return desired, "converged", sweep
            correction += gap
            desired = base + jacobian.null_project(problem.secondary + correction)
        return desired, "max_iterations", self.max_iterations

    @property
    def promise(self) -> str:
        gears = "either gear's sector" if self.gears == "either" else "its gear's sector"
        return f"when converged, the units not under the precedence rule in {gears}; otherwise nothing"

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        """Only a converged allocation promises anything (the paper's m sweeps may end outside the
        sets), and only for the units not under the precedence rule (never corrected)."""
        if allocation.status != "converged":
            return None
        corrected = ~problem.exempt
        if not corrected.any():
            return 0.0
        if self.gears == "either":
            sets = AchievableSets.for_gear(problem.state, np.ones(problem.n), problem.limits)
            distance = sets.distance_either_gear(allocation.velocities)
        else:
            distance = problem.achievable().distance(allocation.velocities)
        return float(np.max(distance[corrected]))


register(
    "iterative",
    IterativeProjection,
    summary="the paper's iterative null-space projection of the velocity error (Sec. 3.2), m sweeps",
    use="the reference method; m = 0 is the base controller of Eq. 5",
)
