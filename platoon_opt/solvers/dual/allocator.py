"""The exact O(n) allocator ``dual``: the allocation programs of the convex allocators ``qp``,
``cone``, ``qp-projection`` and ``cone-projection`` (``platoon_opt.solvers.convex.allocator``)
solved through their m-dimensional dual (docs/dual.md).

``DualAllocator.allocate`` takes one step's ``AllocationProblem`` (n units, m task rows) and
returns velocities (n, 2), m/s, with a certificate of their accuracy in ``Allocation.info``; it
never raises. Its step is the JAX kernel of ``kernel`` (``DualAllocator.compiled`` hands it to
the compiled engine; ``allocate`` calls it jitted on numpy arrays), the multipliers carried from
step to step. The parts live beside this module: ``sets`` and ``safe`` (the sets), ``coupling``
(the task-space algebra), ``newton`` (the dual and its Newton method), ``reduction`` (one step's
program in the dual's standard form), ``kernel`` (one step), ``strict`` (strict priority, on the
host) and ``wolfe`` (its first stage).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from platoon_opt.allocation import Allocation
from platoon_opt.arrays import host
from platoon_opt.engine import CompiledStep
from platoon_opt.limits import inner_projection
from platoon_opt.problem import AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.scenarios import Scenario
from platoon_opt.solvers.dual.kernel import (
    ACCEPTABLE_GAP,
    STATUSES,
    Params,
    Static,
    Warm,
    no_warm,
    objective_unit,
    solve,
    solve_step,
)
from platoon_opt.solvers.dual.padding import canonical, padded
from platoon_opt.solvers.dual.reduction import reduce_program
from platoon_opt.solvers.dual.safe import SafeDualSets
from platoon_opt.solvers.dual.sets import make_sets
from platoon_opt.solvers.dual.strict import solve_strict
from platoon_opt.solvers.options import Flag, Integer, Number, Option, check_options
from platoon_opt.solvers.programs import (
    ANCHOR_WEIGHT,
    EPS,
    GEARS,
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
    posed,
    program_promise,
)
from platoon_opt.solvers.registry import register
from platoon_opt.solvers.safety import SafetyOptions, safe_handout, slack_info

# One step on the host: the engine's kernel jitted (once per shape and static options), numpy out.
solve_host = host(solve, static=("static",))
# Strict priority's standard form (achievable-first, units under the precedence rule pinned).
reduce_host = host(reduce_program, static=("reading", "rule"))
# ``kernel.solve`` statuses after which every unit got p_i (a non-finite result).
_PROJECTED = frozenset(index for index, status in enumerate(STATUSES) if status.endswith("->projection"))

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
            safe sets of barriers are always narrowed: docs/safety.md, section 6) and pose the
            program on the nominal velocities as the units drive them (``programs.posed``).
        gears: "model" (each unit's sector in the gear its gear rule chose), "either" (in the
            gear whose sector lies nearer its nominal velocity) or "catching-up" (the nearer gear
            while the platoon catches up, the gear rule's otherwise): ``programs.posed``.
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
    (docs/dual.md, section 8). The weighted priority runs the JAX kernel ``kernel.solve``
    (``compiled`` hands ``kernel.solve_step`` to the compiled engine); strict priority runs on
    the host, calling the compiled Newton method for its penalized rounds.

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
        build_time: s, the part of solve_time spent on the host before the compiled solve (the
            safe sets with barriers; the program itself is posed inside the compiled kernel).
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
    gears: str = GEARS.field()
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
        parts += name_parts(self.reading, self.rate_aware, self.gears, self.precedence, self.anchor_weight)
        parts += self.safety_name()
        return f"dual({', '.join(parts)})"

    @property
    def promise(self) -> str:
        return program_promise(self.reading, self.rate_aware, self.gears)

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        return achievable_part_excess(problem, allocation, self.rate_aware, self.gears)

    @property
    def static(self) -> Static:
        """What shapes the compiled program (``kernel.Static``)."""
        return Static(self.reading, self.speed, self.sides, self.rate_aware, self.gears, self._rule)

    @property
    def params(self) -> Params:
        """The compiled program's numbers (``kernel.Params``), as arrays."""
        return Params(
            np.asarray(float(self.rho)),
            np.asarray(float(self.eps)),
            np.asarray(float(self.anchor_weight)),
            np.asarray(float(self.tolerance)),
            np.asarray(int(self.max_iterations)),
            np.asarray(bool(self.warm_start)),
        )

    def compiled(self, scenario: Scenario) -> CompiledStep | None:
        """The kernel ``kernel.solve_step`` with this allocator's numbers, carrying the multipliers
        and, with barriers on, building the safe sets in a fixed capacity (``kernel.solve_step``).
        None (the host runs it) for strict priority, and where barriers need the host
        (``SafetyOptions.compiled_safety``)."""
        if self.priority == "strict":
            return None
        params = self.compiled_safety(scenario)
        if params is None:
            return None
        if not params.enabled:
            return CompiledStep(solve_step, self.static, self.params, no_warm, STATUSES)
        static = self.static._replace(safety=params)
        return CompiledStep(solve_step, static, self.params, no_warm, STATUSES, safety=params)

    def allocate(self, problem: AllocationProblem) -> Allocation:
        """Velocities (n, 2) for one step, with the duality gap in ``info``."""
        start = time.perf_counter()
        problem = posed(problem, self.rate_aware, self.gears)
        params = self.safety_for(problem)
        safe = None
        if params.enabled:
            safe = problem.safe_sets(params, speed=self.speed, sides=self.sides)
        try:
            if self.priority == "strict":
                allocation = self._strict(problem, start, safe)
            else:
                allocation = self._weighted(problem, start, safe)
        except Exception as error:  # the contract: never raise, never NaN
            self._warm.clear()
            allocation = self._fallback(problem, start, f"error:{type(error).__name__}", safe)
        if safe is None:
            return allocation
        return dataclasses.replace(allocation, info={**allocation.info, **slack_info(safe)})

    def _carry(self, m: int) -> Warm:
        """The warm start as the kernel's carry (none if off, or of another task's size)."""
        warm = self._warm.multipliers
        if not self.warm_start or warm is None or warm.shape != (m,):
            return no_warm(0, m)
        return Warm(warm, np.asarray(True))

    def _pinned(self, problem: AllocationProblem) -> bool:
        """Whether every unit is pinned: nothing to solve."""
        return self._rule == "pin" and bool(problem.exempt.all())

    def _weighted(self, problem: AllocationProblem, start: float, safe: SafeSets | None) -> Allocation:
        """The rho-weighted or task-exact program, by the kernel (``kernel.solve``)."""
        grown, grown_safe = padded(problem, safe)
        dual_safe = None if grown_safe is None else SafeDualSets.of(grown_safe)
        built = time.perf_counter()
        result = solve_host(
            self.static, self.params, grown, self._carry(problem.jacobian.rows.shape[0]), dual_safe
        )
        n = problem.n
        result = result._replace(
            velocities=result.velocities[:n],
            achievable=result.achievable[:n],
            task_exact=result.task_exact[:n],
        )
        code = int(result.info.status)
        if code in _PROJECTED:
            self._warm.clear()
            return self._projection(problem, start, STATUSES[code], result.velocities)
        if bool(result.carry.valid):
            self._warm.multipliers = np.asarray(result.carry.multipliers)
        safety: dict[str, Any] = {}
        velocities = result.velocities
        if safe is not None and self.reading == "task-exact":
            params = self.safety_for(problem)
            handout = safe_handout(problem, params, safe, result.task_exact, result.achievable)
            velocities = handout.velocities
            safety.update(
                task_exact_velocity=result.task_exact,
                held_units=handout.held,
                escaping_units=handout.escaping,
            )
        return self._result(
            problem,
            start,
            velocities,
            result.achievable,
            STATUSES[code],
            iterations=int(result.info.iterations),
            fell_back=bool(result.info.fell_back),
            backend="pinned" if self._pinned(problem) else "dual",
            objective=float(result.objective),
            duality_gap=float(result.duality_gap),
            relative_gap=float(result.relative_gap),
            multipliers=np.asarray(result.multipliers).tolist(),
            evaluations=int(result.evaluations),
            build_time=built - start,
            **safety,
        )

    def _strict(self, problem: AllocationProblem, start: float, safe: SafeSets | None) -> Allocation:
        """Strict priority (docs/dual.md, section 7), on the host."""
        precedence = self._precedence(problem, safe)
        if safe is None:
            sets: Any = make_sets(problem.achievable(rate_aware=self.rate_aware), self.speed, self.sides)
        else:
            sets = SafeDualSets.of(safe)
        reduced = reduce_host(
            canonical(problem),
            sets,
            precedence,
            reading="achievable-first",
            rule="pin",
            rho=self.rho,
            eps=self.eps,
            anchor_weight=self.anchor_weight,
        )
        held = np.asarray(problem.exempt)
        if self._pinned(problem):
            deviation = float(np.sum((precedence - problem.nominal) ** 2))
            return self._result(
                problem, start, precedence, precedence, "optimal", backend="pinned", objective=deviation
            )
        built = time.perf_counter()
        m = problem.jacobian.rows.shape[0]
        warm = self._warm.multipliers if self.warm_start else None
        strict = solve_strict(
            reduced,
            warm if warm is not None and warm.shape == (m,) else None,
            problem.jacobian.rcond,
            rho=self.rho,
            previous_penalty=self._warm.penalty if self.warm_start else 0.0,
            tolerance=self.tolerance,
            max_iterations=self.max_iterations,
        )
        solution = strict.solution
        if not np.isfinite(solution.gap) or not np.all(np.isfinite(solution.vx)):
            self._warm.clear()
            return self._fallback(problem, start, f"non-finite:{strict.status}", safe)
        self._warm.penalty = strict.penalty
        multipliers = strict.basis @ solution.lam
        self._warm.multipliers = multipliers
        v = np.stack((solution.vx, solution.vy), axis=1)
        velocities = np.where(held[:, None], precedence, v)
        status, fell_back = strict.status, False
        if status != "optimal":
            # Every v(lambda) is achievable: keep the last one if J v's distance to t* is
            # acceptable (relative as the band).
            fell_back = strict.accuracy > ACCEPTABLE_GAP
            status = f"fallback:{status}->last-iterate" if fell_back else "inaccurate"
        # In the task coordinates of all units: what the pinned units serve added back.
        stage1 = strict._replace(
            stage1_task_velocity=strict.stage1_task_velocity + (problem.task_velocity - reduced.program.u)
        )
        return self._result(
            problem,
            start,
            velocities,
            velocities,
            status,
            iterations=solution.iterations,
            fell_back=fell_back,
            objective=float(np.sum((velocities - problem.nominal) ** 2)),
            multipliers=multipliers.tolist(),
            evaluations=solution.evaluations,
            build_time=built - start,
            **stage1.info(),
        )

    def objective_unit(self, problem: AllocationProblem) -> float:
        """The objective's own unit (m^2/s^2): a deviation of v_max on one unit in the term
        weighted least, ``v_max^2`` times eps (task-exact) or 1, and anchor_weight if smaller
        (precedence "anchor")."""
        return float(objective_unit(problem, self.static, self.params))

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
            np.asarray(velocities),
            allocator=self.name,
            status=status,
            iterations=iterations,
            solve_time=time.perf_counter() - start,
            fell_back=fell_back,
            program_changed=program_changed,
            backend=backend,
            achievable=np.asarray(achievable),
            **info,
        )

    def _projection(
        self, problem: AllocationProblem, start: float, status: str, velocities: np.ndarray
    ) -> Allocation:
        """The last resort: every unit's p_i (``velocities``), no program solved."""
        return self._result(
            problem,
            start,
            velocities,
            velocities,
            status,
            fell_back=True,
            backend="projection",
            program_changed=True,  # no program solved: the nominal velocity projected
            program="projection",
        )

    def _precedence(self, problem: AllocationProblem, safe: SafeSets | None) -> np.ndarray:
        """Every unit's p_i (n, 2) in numpy (``kernel.dual_sets`` computes the same traced)."""
        if safe is not None:
            return safe.project(problem.nominal)
        sets = problem.achievable(rate_aware=self.rate_aware)
        return inner_projection(problem.nominal, sets, self.speed, self.sides)

    def _fallback(
        self, problem: AllocationProblem, start: float, reason: str, safe: SafeSets | None = None
    ) -> Allocation:
        """After an exception or a non-finite strict result: every unit's p_i, computed on the host."""
        return self._projection(
            problem, start, f"fallback:{reason}->projection", self._precedence(problem, safe)
        )


register(
    "dual",
    DualAllocator,
    summary="the programs of qp, cone, qp-projection and cone-projection, solved exactly through the dual",
    use="the convex programs at any n (O(n) time and memory), with a duality-gap certificate",
)
