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
from platoon_opt.solvers.registry import register

# A velocity this close to its achievable set (m/s) counts as achievable.
ACHIEVABLE_TOLERANCE = 1e-9


@dataclass(frozen=True)
class IterativeProjection:
    """The paper's iteration with at most ``max_iterations`` sweeps (0 = Eq. 5 alone).

    Attributes:
        max_iterations: the paper's m, >= 0.
        gears: "either" projects each unit onto the nearer of its forward and backing
            sectors (the paper's achievable set, both gears being reachable); "model"
            onto the sector of the gear chosen by the model's gear rule.
    """

    max_iterations: int = 4
    gears: str = "either"

    def __post_init__(self) -> None:
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, (int, np.integer)):
            raise TypeError(f"max_iterations must be an integer, got {self.max_iterations!r}")
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, got {self.max_iterations!r}")
        if self.gears not in ("either", "model"):
            raise ValueError(f"gears must be 'either' or 'model', got {self.gears!r}")

    @property
    def name(self) -> str:
        return f"iterative(m={self.max_iterations})"

    def allocate(self, problem: AllocationProblem) -> Allocation:
        start = time.perf_counter()
        desired, status, sweeps = problem.nominal, "nominal", 0
        if self.max_iterations:
            desired, status, sweeps = self._sweeps(problem)
        return Allocation.of(
            problem,
            desired,
            allocator=self.name,
            status=status,
            iterations=sweeps,
            solve_time=time.perf_counter() - start,
        )

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


@register("iterative")
def make_iterative(max_iterations: int = 4, gears: str = "either") -> IterativeProjection:
    """The paper's iterative projection; see ``IterativeProjection``."""
    return IterativeProjection(max_iterations=max_iterations, gears=gears)
