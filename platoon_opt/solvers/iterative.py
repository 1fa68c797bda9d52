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
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from platoon_opt.allocation import Allocation
from platoon_opt.arrays import namespace
from platoon_opt.barrier_constraints import Capacity
from platoon_opt.engine import CompiledStep, StepInfo
from platoon_opt.limits import AchievableSets
from platoon_opt.problem import AllocationProblem
from platoon_opt.safety import SafetyParams
from platoon_opt.scenarios import Scenario
from platoon_opt.solvers.options import Choice, Integer, Option, check_options
from platoon_opt.solvers.registry import register
from platoon_opt.solvers.safety import SafetyOptions, filtered, safety_filter

# A velocity this close to its achievable set (m/s) counts as achievable.
ACHIEVABLE_TOLERANCE = 1e-9
# The statuses of ``sweeps`` (StepInfo.status indexes them).
STATUSES = ("nominal", "converged", "max_iterations")


MAX_ITERATIONS = Option(
    "max_iterations", 4, "the paper's m: sweeps at most (0: Eq. 5 alone)", Integer(at_least=0)
)
GEARS = Option(
    "gears",
    "either",
    "the sets projected onto: either gear's sector (the paper's) or the model gear rule's",
    Choice(("either", "model")),
)


def sweeps(
    gears: str, max_iterations: Any, problem: AllocationProblem, carry: Any
) -> tuple[Any, Any, StepInfo]:
    """The iteration from the nominal velocity, at most ``max_iterations`` sweeps, each stopping
    early when every corrected unit's velocity is achievable. Numpy, or traced: the step of
    ``engine.CompiledStep``. Returns the velocities (n, 2), ``carry`` (nothing) and the
    ``StepInfo`` (status "nominal" for m = 0, else "converged" or "max_iterations")."""
    xp = namespace(problem.nominal, problem.state.theta)
    jacobian = problem.jacobian
    if gears == "model":
        project = AchievableSets.for_gear(problem.state, problem.gear, problem.limits).frame().project
    else:
        sets = AchievableSets.for_gear(problem.state, xp.ones(problem.n), problem.limits)
        project = sets.frame().project_either_gear
    corrected = ~problem.exempt[:, None]
    base = jacobian.pinv_apply(problem.task_velocity)

    def unfinished(loop: tuple[Any, Any, Any, Any]) -> Any:
        sweep, _, _, converged = loop
        return (sweep < max_iterations) & ~converged

    def sweep_once(loop: tuple[Any, Any, Any, Any]) -> tuple[Any, Any, Any, Any]:
        sweep, desired, correction, _ = loop
        gap = xp.where(corrected, project(desired) - desired, 0.0)
        converged = xp.max(xp.abs(gap)) <= ACHIEVABLE_TOLERANCE
        correction = xp.where(converged, correction, correction + gap)
        desired = xp.where(converged, desired, base + jacobian.null_project(problem.secondary + correction))
        return sweep + xp.where(converged, 0, 1), desired, correction, converged

    loop = (xp.asarray(0), problem.nominal, xp.zeros_like(problem.nominal), xp.asarray(False))
    if xp is jnp:
        loop = jax.lax.while_loop(unfinished, sweep_once, loop)
    else:
        while unfinished(loop):
            loop = sweep_once(loop)
    sweep, desired, _, converged = loop
    status = xp.where(max_iterations == 0, 0, xp.where(converged, 1, 2))
    return desired, carry, StepInfo(sweep, status, xp.asarray(False), xp.asarray(False))


def filtered_sweeps(
    static: tuple[str, SafetyParams], max_iterations: Any, problem: AllocationProblem, carry: Any
) -> tuple[Any, Any, StepInfo]:
    """The engine's step with barriers on: ``sweeps`` (``static``: its gears, and the barriers'
    parameters), its answer through the safety filter as on the host (``safety.filtered``), the
    safe sets built in the default ``Capacity`` (a unit beyond it overflows:
    ``engine.StepInfo.overflow``)."""
    gears, params = static
    velocities, carry, info = sweeps(gears, max_iterations, problem, carry)
    handout, safe = filtered(problem, params, velocities, capacity=Capacity())
    overflow = jnp.any(safe.overflow) | handout.overflow
    return handout.velocities, carry, info._replace(slack=jnp.sum(safe.slack > 0), overflow=overflow)


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

    def compiled(self, scenario: Scenario) -> CompiledStep | None:
        """The kernel ``sweeps`` with m as its number, with barriers on ``filtered_sweeps``; None
        where barriers need the host (``SafetyOptions.compiled_safety``)."""
        params = self.compiled_safety(scenario)
        m = np.asarray(self.max_iterations)
        if params is None:
            return None
        if not params.enabled:
            return CompiledStep(sweeps, self.gears, m, _no_carry, STATUSES)
        return CompiledStep(filtered_sweeps, (self.gears, params), m, _no_carry, STATUSES, safety=params)

    def allocate(self, problem: AllocationProblem) -> Allocation:
        start = time.perf_counter()
        velocities, _, info = sweeps(self.gears, self.max_iterations, problem, ())
        allocation = Allocation.of(
            problem,
            velocities,
            allocator=self.name,
            status=STATUSES[int(info.status)],
            iterations=int(info.iterations),
            solve_time=time.perf_counter() - start,
        )
        return safety_filter(problem, allocation, self.safety_for(problem))

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


def _no_carry(n: int, m: int) -> tuple[()]:
    return ()


register(
    "iterative",
    IterativeProjection,
    summary="the paper's iterative null-space projection of the velocity error (Sec. 3.2), m sweeps",
    use="the reference method; m = 0 is the base controller of Eq. 5",
)
