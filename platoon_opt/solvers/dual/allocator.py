"""The exact O(n) allocator ``dual``: the allocation programs of the convex allocators ``qp``,
``cone``, ``qp-projection`` and ``cone-projection`` (``platoon_opt.solvers.convex.allocator``)
solved through their m-dimensional dual (docs/dual.md).

``DualAllocator.allocate`` takes one step's ``AllocationProblem`` (n units, m task rows) and
returns velocities (n, 2), m/s, with a certificate of their accuracy in ``Allocation.info``; it
never raises. The multipliers are carried from step to step (``WarmStart``). The parts live
beside this module: ``sets`` (the achievable sets), ``coupling`` (J), ``newton`` (the dual and
its Newton method), ``reduction`` (one step's program in the dual's standard form), ``strict``
(strict priority) and ``wolfe`` (its first stage).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from platoon_opt.problem import Allocation, AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.solvers.dual.newton import solve_dual
from platoon_opt.solvers.dual.reduction import handed_velocities, precedence_velocities, reduce_program
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
    name_parts,
    program_promise,
)
from platoon_opt.solvers.registry import register
from platoon_opt.solvers.safety import SafetyOptions, slack_info

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
class DualAllocator(SafetyOptions):
    """The allocation programs of the convex allocators solved exactly in O(n) through their
    m-dimensional dual (docs/dual.md).

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
        rate_aware: narrow each steering sector to what the steering reaches in one step (the
            safe sets of barriers are always narrowed: docs/safety.md, section 6).
        precedence: units under the paper's precedence rule: "pin" (fixed at p_i, their nominal
            velocity projected onto their set) or "anchor" (kept, drawn to p_i with
            ``anchor_weight``); None: "pin" for achievable-first, "anchor" for task-exact,
            as the convex allocators.
        anchor_weight: > 0, see ``precedence``.
        priority: "weighted" (the rho-weighted program) or "strict" (achievable-first with
            precedence "pin": the best achievable task velocity first, then the nearest
            velocity to q'_d that keeps it; docs/dual.md, section 7).
        tolerance: stop when the duality gap is within ``tolerance`` times the objective.
        max_iterations: Newton steps at most.
        warm_start: start from the previous step's multipliers (kept in the allocator, in task
            coordinates, so that a change of the pinned set or of the task basis keeps them
            meaningful).

    The program, its precedence rule and its degenerate-task directions are those of
    ``platoon_opt.solvers.convex.formulation``. ``allocate`` never raises: if the method fails,
    every unit gets its nominal velocity projected onto its set, status "fallback:<reason>"
    (docs/dual.md, section 8).

    ``info``:
        objective: the program's, as ``platoon_opt.solvers.convex.formulation.objective``
            (m^2/s^2); strict priority: the deviation ``sum_i ||v_i - q'_d,i||^2`` (the second
            stage's, as ``qp``).
        duality_gap, relative_gap: an upper bound on objective - optimum (m^2/s^2), and the same
            relative to max(|objective|, |objective - gap|, ``objective_unit``), a scale that
            cannot vanish: at a zero optimum the gap is relative to the cost of one unit off
            by v_max (docs/dual.md, section 8). Not for strict priority.
        multipliers: of ``J v = u + s``, in task coordinates (m,).
        achievable: the achievable parts c (n, 2), m/s (v itself for achievable-first).
        backend: "dual" ("pinned" when every unit is pinned, "projection" for a fallback).
        evaluations: passes over the units.
        build_time: s, the part of solve_time spent posing the dual's standard form.
    Strict priority adds (docs/dual.md, section 7) stage1_task_velocity (t*, (m,)), stage1_gap
    (Wolfe's gap, bounds ||t* - exact||^2 / 2), stage1_iterations, band (the allowed
    ``|E^T (J v - t*)|``), band_residual (the one met), penalty (the last rho) and, for Wolfe's
    stage-1 point, stage2_bound (a bound on its deviation's excess, relative). Its certificate is
    the band: v = P_C(q'_d - J^T lambda / 2) for the reported multipliers, so v has the least
    deviation for its own task velocity J v; or the bound stage2_bound.
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
    # ``precedence`` resolved (None stands for the reading's default): what the programs use.
    _rule: str = field(default="", init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_options(self, "dual")
        rule = self.precedence or default_precedence(self.reading)
        object.__setattr__(self, "precedence", rule)
        object.__setattr__(self, "_rule", rule)
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
        elif self.sides != SIDES.default:
            parts.append(f"sides={self.sides}")
        parts += name_parts(self.reading, self.rate_aware, self.precedence, self.anchor_weight)
        parts += self.safety_name()
        return f"dual({', '.join(parts)})"

    @property
    def promise(self) -> str:
        return program_promise(self.reading, self.rate_aware)

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        return achievable_part_excess(problem, allocation, self.rate_aware)

    def allocate(self, problem: AllocationProblem) -> Allocation:
        """Velocities (n, 2) for one step, with the duality gap in ``info``."""
        start = time.perf_counter()
        params = self.safety_for(problem)
        safe = None
        if params.enabled:
            safe = problem.safe_sets(params, speed=self.speed, sides=self.sides)
        try:
            allocation = self._allocate(problem, start, safe)
        except Exception as error:  # the contract: never raise, never NaN
            self._warm.clear()
            allocation = self._fallback(problem, start, f"error:{type(error).__name__}", safe)
        if safe is None:
            return allocation
        return dataclasses.replace(allocation, info={**allocation.info, **slack_info(safe)})

    def _allocate(self, problem: AllocationProblem, start: float, safe: SafeSets | None) -> Allocation:
        sets = problem.achievable(rate_aware=self.rate_aware)
        if self.precedence == "pin" and problem.exempt.all():
            everyone = np.arange(problem.n)
            velocities = precedence_velocities(problem, sets, everyone, self.speed, self.sides, safe)
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
            rule=self._rule,
            rho=self.rho,
            eps=self.eps,
            anchor_weight=self.anchor_weight,
            safe=safe,
        )
        built = time.perf_counter()
        m = problem.jacobian.rows.shape[0]
        warm = self._warm.multipliers if self.warm_start else None
        if warm is not None and warm.shape != (m,):
            warm = None
        strict: StrictSolution | None = None
        to_task: np.ndarray | None
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
            solution, to_task = strict.solution, strict.basis  # to_task: None is the identity
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
            return self._fallback(problem, start, f"non-finite:{solution.status}", safe)
        multipliers = solution.lam if to_task is None else to_task @ solution.lam
        self._warm.multipliers = multipliers
        velocities, achievable = handed_velocities(problem, reduced, solution, eps=self.eps)
        safety: dict[str, Any] = {}
        if safe is not None and self.reading == "task-exact":
            # With barriers the units get c (docs/safety.md, section 5).
            safety["task_exact_velocity"], velocities = velocities, achievable
        status, fell_back = solution.status, False
        if strict is not None:
            objective = float(np.sum((velocities - problem.nominal) ** 2))
            accuracy = strict.accuracy
            certificate = strict.info()
        else:
            objective = reduced.scale * solution.primal + reduced.constant
            gap = reduced.scale * max(solution.gap, 0.0)
            accuracy = gap / max(abs(objective), abs(objective - gap), self.objective_unit(problem))
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
            **safety,
        )

    def objective_unit(self, problem: AllocationProblem) -> float:
        """The objective's own unit (m^2/s^2): a deviation of v_max on one unit in the term
        weighted least, ``v_max^2`` times eps (task-exact) or 1, and anchor_weight if smaller
        (precedence "anchor")."""
        weight = self.eps if self.reading == "task-exact" else 1.0
        if self.precedence == "anchor":
            weight = min(weight, self.anchor_weight)
        return problem.limits.max_speed**2 * weight

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
        program_changed: bool = False,
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
            program_changed=program_changed,
            backend=backend,
            achievable=achievable,
            **info,
        )

    def _fallback(
        self, problem: AllocationProblem, start: float, reason: str, safe: SafeSets | None = None
    ) -> Allocation:
        sets = problem.achievable(rate_aware=self.rate_aware)
        velocities = precedence_velocities(problem, sets, np.arange(problem.n), self.speed, self.sides, safe)
        return self._result(
            problem,
            start,
            velocities,
            velocities,
            f"fallback:{reason}->projection",
            fell_back=True,
            backend="projection",
            program_changed=True,  # no program solved: the nominal velocity projected
            program="projection",
        )


register(
    "dual",
    DualAllocator,
    summary="the programs of qp, cone, qp-projection and cone-projection, solved exactly through the dual",
    use="the convex programs at any n (O(n) time and memory), with a duality-gap certificate",
)
