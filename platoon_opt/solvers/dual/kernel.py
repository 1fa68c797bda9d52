"""One step of the dual allocator as a JAX kernel (docs/dual.md, section 8): the engine's
``solve_step`` (``platoon_opt.engine.CompiledStep``) and, with the certificate and the safe sets
of barrier constraints, ``solve`` for the host.

``static`` (``Static``) holds what shapes the program: the reading, the speed model and sides,
``rate_aware`` and the precedence rule. ``params`` (``Params``) holds the numbers, arrays: rho,
eps, the anchor weight, the tolerance, the iteration cap and whether to warm start, so that
configurations that differ only in them share one compiled program (and a batch may give each
platoon its own). The carry (``Warm``) is the last step's multipliers in task coordinates (m,)
and whether they are valid.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from platoon_opt.barrier_constraints import Capacity
from platoon_opt.engine import StepInfo
from platoon_opt.limits import AchievableSets, inner_projection
from platoon_opt.problem import AllocationProblem
from platoon_opt.safety import SafetyParams
from platoon_opt.solvers.dual.newton import STATUSES as NEWTON_STATUSES
from platoon_opt.solvers.dual.newton import newton
from platoon_opt.solvers.dual.reduction import handed_velocities, reduce_program
from platoon_opt.solvers.dual.safe import SafeDualSets
from platoon_opt.solvers.dual.sets import make_sets
from platoon_opt.solvers.programs import posed
from platoon_opt.solvers.safety import safe_handout

# A result whose relative gap is within this after an early stop is still handed out
# (status "inaccurate"); beyond it the allocator falls back to the last iterate.
ACCEPTABLE_GAP = 1e-6
# ``StepInfo.status`` indexes these: the answer, an early stop within ACCEPTABLE_GAP, the last
# iterate beyond it (by what stopped Newton), and a non-finite result (every unit gets p_i).
STATUSES = (
    "optimal",
    "inaccurate",
    *(f"fallback:{name}->last-iterate" for name in NEWTON_STATUSES[1:]),
    *(f"fallback:non-finite:{name}->projection" for name in NEWTON_STATUSES),
)
_LAST_ITERATE, _NON_FINITE = 2, 1 + len(NEWTON_STATUSES)


class Static(NamedTuple):
    """What shapes the compiled program (hashable): ``reading``, ``speed``, ``sides``,
    ``rate_aware``, ``gears`` and ``rule`` (the precedence rule, resolved) as ``DualAllocator``'s options,
    and the barrier constraints ``solve_step`` builds (``safety``; None: none)."""

    reading: str
    speed: str
    sides: int
    rate_aware: bool
    gears: str
    rule: str
    safety: SafetyParams | None = None


class Params(NamedTuple):
    """The numbers of the compiled program (each a scalar array): ``rho``, ``eps``,
    ``anchor_weight``, ``tolerance``, ``max_iterations`` and ``warm_start`` as
    ``DualAllocator``'s options."""

    rho: Any
    eps: Any
    anchor_weight: Any
    tolerance: Any
    max_iterations: Any
    warm_start: Any


class Warm(NamedTuple):
    """The carry: the last step's multipliers in task coordinates (m,), and whether they are
    valid (False before the first step and after a non-finite result)."""

    multipliers: Any
    valid: Any


class Result(NamedTuple):
    """What ``solve`` returns: the handed velocities and their achievable parts (n, 2), m/s,
    the carry, the engine's ``StepInfo``, and the certificate: the program's objective and
    duality gap (m^2/s^2), the relative gap (docs/dual.md, section 8), the multipliers in task
    coordinates (m,), the passes over the units, and (task-exact) the velocities a before
    barriers made the units take c."""

    velocities: Any
    achievable: Any
    carry: Warm
    info: StepInfo
    objective: Any
    duality_gap: Any
    relative_gap: Any
    multipliers: Any
    evaluations: Any
    task_exact: Any


def no_warm(n: int, m: int) -> Warm:
    """The carry before the first step: no multipliers."""
    return Warm(np.zeros(m), np.asarray(False))


def dual_sets(static: Static, problem: AllocationProblem, safe: SafeDualSets | None) -> tuple[Any, Any]:
    """The dual's sets (the safe sets with barriers) and each unit's precedence velocity p_i
    (n, 2): its nominal velocity projected onto its exact sector and shortened along its ray into
    the polygon, as ``platoon_opt.solvers.convex.formulation`` takes it; with barriers, projected
    onto its safe set."""
    if safe is not None:
        return safe, safe.safe.project(problem.nominal)
    model = AchievableSets.for_gear(
        problem.state, problem.gear, problem.limits, rate_aware=static.rate_aware, dt=problem.dt
    )
    return make_sets(model, static.speed, static.sides), inner_projection(
        problem.nominal, model, static.speed, static.sides
    )


def objective_unit(problem: AllocationProblem, static: Static, params: Params) -> Any:
    """The objective's own unit (m^2/s^2): a deviation of v_max on one unit in the term weighted
    least, ``v_max^2`` times eps (task-exact) or 1, and anchor_weight if smaller (precedence
    "anchor")."""
    weight = params.eps if static.reading == "task-exact" else jnp.asarray(1.0)
    if static.rule == "anchor":
        weight = jnp.minimum(weight, params.anchor_weight)
    return problem.limits.max_speed**2 * weight


def solve(
    static: Static, params: Params, problem: AllocationProblem, carry: Warm, safe: SafeDualSets | None = None
) -> Result:
    """One step: the program posed (``reduction.reduce_program``), solved from the carried
    multipliers (``newton.newton``), its velocities handed out (``reduction.handed_velocities``)
    and certified, with the fallbacks of docs/dual.md, section 8. ``safe``: the safe sets of
    barrier constraints (the units then get c in the task-exact reading, and ``solve_step`` or
    the host hands out by ``safe_handout``)."""
    sets, precedence = dual_sets(static, problem, safe)
    reduced = reduce_program(
        problem,
        sets,
        precedence,
        reading=static.reading,
        rule=static.rule,
        rho=params.rho,
        eps=params.eps,
        anchor_weight=params.anchor_weight,
    )
    warm = carry.valid & params.warm_start
    start = jnp.where(warm, reduced.from_task @ carry.multipliers, 0.0)
    solution = newton(reduced.program, start, params.tolerance, params.max_iterations)
    velocities, achievable = handed_velocities(reduced, solution, params.eps)
    task_exact = velocities
    if safe is not None and static.reading == "task-exact":
        velocities = achievable  # with barriers the units get c (docs/safety.md, section 5)
    # Nothing to solve (every unit pinned): the objective is exact, and the carry stays as it was.
    solved = jnp.sum(reduced.program.core) > 0
    objective = reduced.scale * solution.primal + reduced.constant
    gap = jnp.where(solved, reduced.scale * jnp.maximum(solution.gap, 0.0), 0.0)
    unit = objective_unit(problem, static, params)
    relative = gap / jnp.maximum(jnp.maximum(jnp.abs(objective), jnp.abs(objective - gap)), unit)
    multipliers = reduced.to_task @ solution.lam
    # The gap is rho ||J v - u - lambda / (2 rho)||^2 at the returned lambda: finite only if lambda is.
    finite = jnp.isfinite(solution.gap) & jnp.all(jnp.isfinite(velocities))
    raw = solution.status
    early = (raw != 0) & (relative > ACCEPTABLE_GAP)
    status = jnp.where(
        ~finite, _NON_FINITE + raw, jnp.where(raw == 0, 0, jnp.where(early, _LAST_ITERATE + raw - 1, 1))
    )
    # A non-finite result: every unit gets p_i, and the warm start is dropped.
    velocities = jnp.where(finite, velocities, precedence)
    achievable = jnp.where(finite, achievable, precedence)
    kept = Warm(
        jnp.where(solved & finite, multipliers, carry.multipliers),
        jnp.where(solved, finite, carry.valid),
    )
    info = StepInfo(solution.iterations, status, (~finite) | early, ~finite)
    return Result(
        velocities,
        achievable,
        kept,
        info,
        objective,
        gap,
        relative,
        multipliers,
        solution.evaluations,
        task_exact,
    )


def solve_step(
    static: Static, params: Params, problem: AllocationProblem, carry: Warm
) -> tuple[Any, Warm, StepInfo]:
    """The engine's kernel (``platoon_opt.engine.CompiledStep``): ``solve``, returning the
    velocities (n, 2), the carry and the ``StepInfo``. With ``static.safety``, on the safe sets
    built in the default ``Capacity`` (``SafeSets.build``; a unit beyond it overflows:
    ``engine.StepInfo.overflow``), as the host builds them for ``DualAllocator``, and in the
    task-exact reading handed out as the host hands them (``safe_handout``)."""
    problem = posed(problem, static.rate_aware, static.gears)
    if static.safety is None:
        result = solve(static, params, problem, carry)
        return result.velocities, result.carry, result.info
    capacity = Capacity()
    safe = problem.safe_sets(static.safety, speed=static.speed, sides=static.sides, capacity=capacity)
    result = solve(static, params, problem, carry, SafeDualSets(dataclasses.replace(safe, fixed=0)))
    velocities, overflow = result.velocities, jnp.any(safe.overflow)
    if static.reading == "task-exact":
        handout = safe_handout(
            problem, static.safety, safe, result.task_exact, result.achievable, capacity=capacity
        )
        # A non-finite result hands every unit p_i, as on the host.
        velocities = jnp.where(result.info.program_changed, velocities, handout.velocities)
        overflow = overflow | handout.overflow
    info = result.info._replace(slack=jnp.sum(safe.slack > 0), overflow=overflow)
    return velocities, result.carry, info
