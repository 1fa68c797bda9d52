"""The exact O(n) allocator ``dual``: the allocation programs of ``solvers.qp`` / ``solvers.cone``
solved through their m-dimensional dual.

The programs couple the units only through the m rows of J (m = 4 for the mean/variance
task). For the achievable-first reading

    P(v) = sum_i w_i ||v_i - d_i||^2 + rho ||J v - u||^2,   v_i in C_i

(w_i = 1, or the anchor weight of a unit under the precedence rule), dualizing
``s = J v - u`` gives, for multipliers ``lambda`` in R^m,

    v_i(lambda) = P_{C_i}(d_i - J_i^T lambda / (2 w_i))                (closed form per unit)
    g(lambda)   = sum_i w_i ||v_i - d_i||^2 + lambda^T (J v - u) - ||lambda||^2 / (4 rho)
    grad g      = J v(lambda) - u - lambda / (2 rho)                   (Danskin)
    -Hess g     = sum_i J_i D_i J_i^T / (2 w_i) + I / (2 rho),  D_i in dP_{C_i}  (generalized)

g is concave, continuously differentiable (projections are 1-Lipschitz), strongly concave
through the ``1/(2 rho)`` term, and its generalized Hessian is m x m, summed over the units.
A semismooth Newton method with a line search on the slope maximizes it in a handful of
vectorized passes over the units. Every ``v(lambda)`` is feasible, and the duality gap is
exactly ``P(v(lambda)) - g(lambda) = rho ||grad g||^2``: a certificate of accuracy.

The task-exact reading ``min sum_i ||a_i - c_i||^2 + eps ||a - d||^2``, ``J a = t``,
``c_i in C_i`` has the same shape once a is eliminated: for fixed c, ``a_i`` minimizes
``alpha_i ||a_i - m_i||^2`` with ``m_i = (c_i + eps d_i) / (1 + eps)``, ``alpha_i = 1 + eps``, over
``J a = t``, so ``a = m - A^-1 J^T (J A^-1 J^T)^-1 (J m - t)`` and what remains is

    eps/(1+eps) [ ||c - d||^2 + ||K (J c - u')||^2 / (eps (1 + eps)) ],
    K = (E^T J A^-1 J^T E)^{-1/2} E^T,   u' = (1 + eps) t - eps J d,

the form above with ``J -> K J``, ``u -> K u'``, ``rho -> 1 / (eps (1 + eps))``; E holds the
regular directions of J J^T, on which ``J a = t`` is imposed (as ``solvers.formulation``
does). Anchored units (the precedence rule) have c_i = p_i and ``alpha_i = anchor_weight + eps``;
pinned units leave the program with their task share.

**Strict priority** (achievable-first, as ``qp(priority="strict")``): first the best achievable
task velocity, the point t* of ``J(C) = sum_i J_i C_i`` nearest u, by Wolfe's minimum-norm-point
algorithm (``solvers.wolfe``; its linear oracle is each unit's support point, one pass); then
``min sum_i ||v_i - d_i||^2`` over ``v_i in C_i`` with J v at t*. The second stage is the form
above with u -> t* on the regular directions E of J J^T and a penalty rho raised until an
iterate has ``|E^T (J v - t*)|`` within the band of ``solvers.STRICT_BAND`` that the
QPs allow. Any ``v(lambda) = P_C(d - J^T lambda / 2)`` is the exact minimizer of the deviation
over ``{v in C : J v = J v(lambda)}`` (these are its optimality conditions), so the first iterate
in the band is an answer: the least deviation for a task velocity within the band of t*. When
t* lies on the boundary of J(C) (the task out of reach) the multipliers can grow like sqrt(rho),
which the band keeps moderate; where they grow without bound (t* at a corner of J(C)) the answer
is Wolfe's own stage-1 point if the penalized rounds certify its deviation (``DualAllocator._strict``).
The band matters where the task is out of reach: the least deviation is steep in J v near t*, and
on the benchmark's problems (n = 64) Clarabel's minimum over the band lies up to 0.2 % below the
dual's point of it, with both stage-1 task velocities within 1.2e-7 of each other.

Small platoons are evaluated by a Python loop over the units (``_ScalarEvaluator``), larger
ones by numpy passes (``_VectorEvaluator``); the Newton driver is shared.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from platoon_opt.problem import Allocation, AllocationProblem
from platoon_opt.solvers.dual.newton import solve_dual
from platoon_opt.solvers.dual.reduction import handed_velocities, precedence_velocities, reduce_program
from platoon_opt.solvers.dual.sets import TINY
from platoon_opt.solvers.dual.strict import StrictSolution, solve_strict
from platoon_opt.solvers.options import Flag, Integer, Number, Option, check_options
from platoon_opt.solvers.programs import (
    ANCHOR_WEIGHT,
    EPS,
    PRECEDENCE,
    PRIORITY,
    RATE_AWARE,
    READING,
    RHO,
    SIDES,
    SPEED,
    achievable_part_excess,
    default_precedence,
    program_promise,
)
from platoon_opt.solvers.registry import register

# A result whose relative gap is within this after ``max_iterations`` is still handed out
# (status "inaccurate"); beyond it the allocator falls back.
ACCEPTABLE_GAP = 1e-6

TOLERANCE = Option(
    "tolerance", 1e-10, "stop when the duality gap is within this times the objective", Number(above=0)
)
MAX_ITERATIONS = Option("max_iterations", 100, "Newton steps at most", Integer(at_least=0))
WARM_START = Option("warm_start", True, "start from the previous step's multipliers", Flag())


@dataclass
class WarmStart:
    """What a dual allocator carries from one step to the next: the multipliers (task
    coordinates, m) and the strict second stage's last penalty."""

    multipliers: np.ndarray | None = None
    penalty: float = 0.0

    def clear(self) -> None:
        self.multipliers, self.penalty = None, 0.0


@dataclass(frozen=True)
class DualAllocator:
    """The allocation programs of ``solvers.qp`` / ``solvers.cone`` solved exactly in O(n) through
    their m-dimensional dual (module docstring).

    Attributes:
        reading: "achievable-first", the ``qp`` / ``cone`` program
            ``min ||v - q'_d||^2 + rho ||J v - u||^2`` over achievable v (v handed out); or
            "task-exact", the ``qp-projection`` / ``cone-projection`` program
            ``min ||a - c||^2 + eps ||a - q'_d||^2``, ``J a = u``, c achievable (a handed out).
        speed: "polygon" (the inscribed ``sides``-gon) or "cone" (the exact speed disk).
        rho: task weight of the achievable-first reading, > 0 ((m/s)^2 per (task velocity)^2);
            with ``priority="strict"`` the first penalty of the second stage.
        eps: weight of the nominal velocity in the task-exact reading, > 0.
        sides: polygon sides (>= 3).
        rate_aware: narrow each steering sector to what the steering reaches in one step.
        precedence: units under the paper's precedence rule: "pin" (fixed at p_i, their nominal
            velocity projected onto their set) or "anchor" (kept, drawn to p_i with
            ``anchor_weight``); None: "pin" for achievable-first, "anchor" for task-exact,
            as ``solvers.qp``.
        anchor_weight: > 0, see ``precedence``.
        priority: "weighted" (the rho-weighted program) or "strict" (achievable-first with
            precedence "pin": the best achievable task velocity first, then the nearest
            velocity to q'_d that keeps it; module docstring).
        tolerance: stop when the duality gap is within ``tolerance`` times the objective.
        max_iterations: Newton steps at most.
        warm_start: start from the previous step's multipliers (kept in the allocator, in task
            coordinates, so that a change of the pinned set or of the task basis keeps them
            meaningful).

    The program, its precedence rule and its degenerate-task directions are those of
    ``solvers.formulation``. ``allocate`` never raises: if the method fails, the nominal
    velocity projected onto the sets is handed out, status "fallback:<reason>". ``info``:
    objective (the program's, as ``solvers.formulation.objective``, m^2/s^2), duality_gap (an
    upper bound on objective - optimum), relative_gap, multipliers (of ``J v = u + s``, task
    coordinates), achievable (c, (n, 2)), backend "dual", evaluations (passes over the units)
    and build_time (s, the part of solve_time spent posing the dual's standard form). Strict
    priority: objective is the deviation ``sum_i ||v_i - q'_d,i||^2`` (the second stage's, as
    ``qp``); no duality gap: the certificate is the band (v = P_C(q'_d - J^T lambda / 2) for the
    reported multipliers, so v has the least deviation for its own task velocity J v), or, for
    Wolfe's stage-1 point, stage2_bound (a bound on its deviation's excess, relative). Added:
    stage1_task_velocity (t*, (m,)), stage1_gap (Wolfe's gap, bounds ||t* - exact||^2 / 2),
    stage1_iterations, band (the allowed ``|E^T (J v - t*)|``), band_residual (the one met) and
    penalty (the last rho).
    """

    reading: str = READING.field()
    speed: str = SPEED.field()
    rho: float = RHO.field()
    eps: float = EPS.field()
    sides: int = SIDES.field()
    rate_aware: bool = RATE_AWARE.field()
    precedence: str | None = PRECEDENCE.field()
    anchor_weight: float = ANCHOR_WEIGHT.field()
    priority: str = PRIORITY.field()
    tolerance: float = TOLERANCE.field()
    max_iterations: int = MAX_ITERATIONS.field()
    warm_start: bool = WARM_START.field()
    _warm: WarmStart = field(default_factory=WarmStart, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_options(self, "dual")
        if self.precedence is None:
            object.__setattr__(self, "precedence", default_precedence(self.reading))
        if self.priority == "strict" and (self.reading, self.precedence) != ("achievable-first", "pin"):
            raise ValueError(
                "priority='strict' needs reading='achievable-first' and precedence='pin', got "
                f"reading={self.reading!r}, precedence={self.precedence!r}"
            )

    @cached_property
    def name(self) -> str:
        """E.g. "dual(rho=1000)", "dual(task-exact, eps=0.0001, cone)"."""
        if self.priority == "strict":
            parts = ["strict"]
        elif self.reading == "achievable-first":
            parts = [f"rho={self.rho:g}"]
        else:
            parts = ["task-exact", f"eps={self.eps:g}"]
        if self.speed == "cone":
            parts.append("cone")
        elif self.sides != 16:
            parts.append(f"sides={self.sides}")
        if self.rate_aware:
            parts.append("rate-aware")
        if self.precedence != default_precedence(self.reading) or self.anchor_weight != ANCHOR_WEIGHT.default:
            parts.append(f"anchor={self.anchor_weight:g}" if self.precedence == "anchor" else "pin")
        return f"dual({', '.join(parts)})"

    @property
    def promise(self) -> str:
        return program_promise(self.reading, self.rate_aware)

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        return achievable_part_excess(problem, allocation, self.rate_aware)

    def allocate(self, problem: AllocationProblem) -> Allocation:
        """Velocities (n, 2) for one step, with the duality gap in ``info``."""
        start = time.perf_counter()
        try:
            return self._allocate(problem, start)
        except Exception as error:  # the contract: never raise, never NaN
            self._warm.clear()
            return self._fallback(problem, start, f"error:{type(error).__name__}")

    def _allocate(self, problem: AllocationProblem, start: float) -> Allocation:
        sets = problem.achievable(rate_aware=self.rate_aware)
        if self.precedence == "pin" and problem.exempt.all():
            velocities = precedence_velocities(problem, sets, np.arange(problem.n), self.speed, self.sides)
            deviation = float(np.sum((velocities - problem.nominal) ** 2))
            residual = problem.jacobian.apply(velocities) - problem.task_velocity
            if self.reading == "task-exact":
                objective = self.eps * deviation
            elif self.priority == "strict":
                objective = deviation
            else:
                objective = deviation + self.rho * float(residual @ residual)
            return self._result(
                problem, start, velocities, velocities, "optimal", backend="pinned", objective=objective
            )
        reduced = reduce_program(
            problem,
            sets,
            reading=self.reading,
            speed=self.speed,
            sides=self.sides,
            rule=self.precedence,
            rho=self.rho,
            eps=self.eps,
            anchor_weight=self.anchor_weight,
        )
        built = time.perf_counter()
        m = problem.jacobian.rows.shape[0]
        warm = self._warm.multipliers if self.warm_start else None
        if warm is not None and warm.shape != (m,):
            warm = None
        strict: StrictSolution | None = None
        if self.priority == "strict":
            strict = solve_strict(
                reduced,
                warm,
                problem.jacobian.rcond,
                rho=self.rho,
                previous_penalty=self._warm.penalty if self.warm_start else 0.0,
                tolerance=self.tolerance,
                max_iterations=self.max_iterations,
            )
            self._warm.penalty = strict.penalty
            # In the task coordinates of all units: what the pinned units serve added back.
            strict = strict._replace(
                stage1_task_velocity=strict.stage1_task_velocity + (problem.task_velocity - reduced.u)
            )
            solution, to_task = strict.solution, strict.basis
        else:
            lam = np.zeros_like(reduced.u) if warm is None else warm
            if warm is not None and reduced.from_task is not None:
                lam = reduced.from_task @ warm
            solution = solve_dual(
                reduced.dx,
                reduced.dy,
                reduced.coupling,
                reduced.u,
                reduced.rho,
                reduced.sets,
                lam,
                tolerance=self.tolerance,
                max_iterations=self.max_iterations,
                weight=reduced.weight,
            )
            to_task = reduced.to_task
        # The gap is rho ||J v - u - lambda / (2 rho)||^2 at the returned lambda: finite only if lambda is.
        if not math.isfinite(solution.gap):
            self._warm.clear()
            return self._fallback(problem, start, f"non-finite:{solution.status}")
        multipliers = solution.lam if to_task is None else to_task @ solution.lam
        self._warm.multipliers = multipliers
        velocities, achievable = handed_velocities(
            problem, reduced, solution, reading=self.reading, eps=self.eps
        )
        status, fell_back = solution.status, False
        if strict is not None:
            objective = float(np.sum((velocities - problem.nominal) ** 2))
            accuracy = strict.accuracy
            certificate = strict.info()
        else:
            objective = reduced.scale * solution.primal + reduced.constant
            gap = reduced.scale * max(solution.gap, 0.0)
            accuracy = gap / max(objective, TINY)
            certificate = {"duality_gap": gap, "relative_gap": accuracy}
        if status != "optimal":
            # Every v(lambda) is achievable: keep the last one if its certified accuracy is
            # acceptable (the relative gap; strict: J v's distance to t*, relative as the band).
            fell_back = accuracy > ACCEPTABLE_GAP
            status = f"fallback:{status}->last-iterate" if fell_back else "inaccurate"
        return self._result(
            problem,
            start,
            velocities,
            achievable,
            status,
            iterations=solution.iterations,
            fell_back=fell_back,
            objective=objective,
            multipliers=multipliers.tolist(),
            evaluations=solution.evaluations,
            build_time=built - start,
            **certificate,
        )

    def _result(
        self,
        problem: AllocationProblem,
        start: float,
        velocities: np.ndarray,
        achievable: np.ndarray,
        status: str,
        *,
        iterations: int = 0,
        fell_back: bool = False,
        backend: str = "dual",
        **info: Any,
    ) -> Allocation:
        return Allocation.of(
            problem,
            velocities,
            allocator=self.name,
            status=status,
            iterations=iterations,
            solve_time=time.perf_counter() - start,
            fell_back=fell_back,
            backend=backend,
            achievable=achievable,
            **info,
        )

    def _fallback(self, problem: AllocationProblem, start: float, reason: str) -> Allocation:
        sets = problem.achievable(rate_aware=self.rate_aware)
        velocities = precedence_velocities(problem, sets, np.arange(problem.n), self.speed, self.sides)
        return self._result(
            problem,
            start,
            velocities,
            velocities,
            f"fallback:{reason}->projection",
            fell_back=True,
            backend="projection",
        )


register(
    "dual",
    DualAllocator,
    summary="the programs of qp, cone, qp-projection and cone-projection, solved exactly through the dual",
    use="the convex programs at any n (O(n) time and memory), with a duality-gap certificate",
)
