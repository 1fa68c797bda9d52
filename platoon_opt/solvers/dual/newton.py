"""The semismooth Newton method on the dual of the standard form to which the dual allocator
brings every program (docs/dual.md, sections 2 to 4), as a JAX kernel.

``newton`` minimizes ``sum_i core_i w_i ||v_i - d_i||^2 + rho ||J v - u||^2`` over ``v_i in C_i``
(``Standard``: n units, m rows, static shapes; units outside the core have ``core_i = 0`` and zero
columns of J) by maximizing its dual over the m multipliers. Every iterate's
``v(lambda) = P_C(d - J^T lambda / (2 w))`` lies in C, and the duality gap ``rho ||grad g||^2``
certifies it (``Solution``).

The method is one ``lax.while_loop`` whose every pass is one evaluation (one projection pass
over the units): a trial point of the line search, which either is taken (then the stopping
tests run and the next Newton direction is computed there) or moves the step length. Under
``jax.vmap`` each platoon's loop state stops changing once it is done, and the batch loops until
every platoon is; with one evaluation per pass, platoons whose line searches differ in length
do not wait for each other's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from platoon_opt.arrays import pytree
from platoon_opt.solvers.dual.coupling import frobenius, solve_spd
from platoon_opt.solvers.dual.sets import Projection

# Line search: Armijo's constant (fraction of the predicted increase of g), the accepted
# size of the slope along the step relative to the initial one, and the evaluations at most.
ARMIJO = 1e-4
CURVATURE = 0.1
MAX_SEARCH = 30
# Up to this many units (8) is assembled as one fused sum over the (m, m, n) terms, which XLA
# runs fastest, also under ``vmap``; beyond, as three (m, n) x (n, m) products, which never hold
# that array (13 MB at n = 100,000). Measured in docs/dual.md, section 4.
SUMMED_UP_TO = 4096
# ``Solution.status``: what stopped the method (docs/dual.md, section 4); RUNNING while it runs.
STATUSES = ("optimal", "max_iterations", "singular", "stalled")
OPTIMAL, MAX_ITERATIONS, SINGULAR, STALLED, RUNNING = 0, 1, 2, 3, -1


@pytree(data=("dx", "dy", "weight", "core", "rows", "u", "rho", "sets", "radius"))
@dataclass(frozen=True)
class Standard:
    """``min sum_i core_i w_i ||v_i - d_i||^2 + rho ||J v - u||^2`` over ``v_i in C_i``.

    Attributes:
        dx, dy: d (n,) x 2, m/s.
        weight: w (n,) > 0 (1 outside the core).
        core: (n,) 1.0 for the units of the program, 0.0 for the others (their columns of
            ``rows`` are 0, so they take no part).
        rows: J (m, n, 2) (task-exact: K J, with zero rows for the directions left out).
        u: (m,); rho: > 0, the residual's weight.
        sets: the C_i (``sets.SectorSets``, ``sets.PolygonSets`` or ``safe.SafeDualSets``).
        radius: the speed disk's radius (m/s): the scale of |v_i| for the rounding level.
    """

    dx: Any
    dy: Any
    weight: Any
    core: Any
    rows: Any
    u: Any
    rho: Any
    sets: Any
    radius: Any


class Solution(NamedTuple):
    """Result of ``newton``.

    Attributes:
        vx, vy: the primal velocities v(lambda) (n,), m/s; always in C.
        lam: the multipliers (m,).
        primal: P(v), the objective at v (m^2/s^2); the optimum lies in [primal - gap, primal].
        gap: P(v(lambda)) - g(lambda) = rho ||grad g||^2 >= 0.
        iterations: Newton steps taken; evaluations: projection passes over the units.
        status: index into ``STATUSES``.
    """

    vx: Any
    vy: Any
    lam: Any
    primal: Any
    gap: Any
    iterations: Any
    evaluations: Any
    status: Any


class _Point(NamedTuple):
    """The program at one multiplier, as the loop carries it: v(lambda), J v - u, grad g and the
    weighted deviation sum core_i w_i ||v_i - d_i||^2. (The projection's Jacobian is used in the
    pass that evaluates the point, and not carried: every carried array costs the loop a kernel
    per pass, and a kernel costs more than a pass's arithmetic at n = 8.)"""

    lam: Any
    vx: Any
    vy: Any
    residual: Any
    grad: Any
    deviation: Any


class _Search(NamedTuple):
    """The Newton direction at the current point and the line search along it: the step length
    to evaluate next, the bracket [lo, hi], the last two moves, the evaluations so far, and the
    largest length with a rising slope (``best``) if any (``found``)."""

    step: Any
    length: Any
    lo: Any
    hi: Any
    moved: Any
    before: Any
    count: Any
    found: Any
    best: Any


class _State(NamedTuple):
    """The loop's state; ``first`` marks the pass that evaluates the starting multipliers,
    ``forced`` one that takes its trial point whatever its slope (the search's best, after
    ``MAX_SEARCH`` evaluations)."""

    point: _Point
    search: _Search
    iterations: Any
    evaluations: Any
    status: Any
    first: Any
    forced: Any


def _select(flag: Any, a: Any, b: Any) -> Any:
    """``a`` where ``flag``, else ``b``, leaf by leaf."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(flag, x, y), a, b)


def _evaluate(program: Standard, lam: Any) -> tuple[_Point, Projection]:
    """v(lambda) (equation (3)), J v - u, grad g (equation (5)) and the deviation: one pass; and
    the projection with its Jacobian."""
    tx, ty = _transpose_apply(program.rows, lam)
    half = 0.5 / program.weight
    p = program.sets.project(program.dx - half * tx, program.dy - half * ty)
    residual = _apply(program.rows, p.vx, p.vy) - program.u
    ex, ey = p.vx - program.dx, p.vy - program.dy
    deviation = jnp.sum(program.core * program.weight * (ex * ex + ey * ey))
    grad = residual - lam / (2 * program.rho)
    return _Point(lam, p.vx, p.vy, residual, grad, deviation), p


def _apply(rows: Any, vx: Any, vy: Any) -> Any:
    """J v (m,) for v (n,) x 2. Products and sums rather than ``einsum``: at m = 4 XLA fuses them
    with the arithmetic around them, where a (batched) dot is a call of its own."""
    return jnp.sum(rows[:, :, 0] * vx + rows[:, :, 1] * vy, axis=1)


def _transpose_apply(rows: Any, weights: Any) -> tuple[Any, Any]:
    """J^T w (n,) x 2 for w (m,)."""
    return jnp.sum(weights[:, None] * rows[:, :, 0], axis=0), jnp.sum(
        weights[:, None] * rows[:, :, 1], axis=0
    )


def _dual_value(point: _Point, rho: Any) -> Any:
    """g(lambda) = deviation + lambda . (J v - u) - ||lambda||^2 / (4 rho) (equation (4))."""
    return point.deviation + point.lam @ point.residual - point.lam @ point.lam / (4 * rho)


def _hessian(program: Standard, p: Projection) -> Any:
    """-grad^2 g = sum_i J_i D_i J_i^T / (2 w_i) + I / (2 rho) (equation (6)), D_i = alpha I + beta f f^T."""
    rows, inverse = program.rows, 1.0 / program.weight
    jx, jy = rows[:, :, 0], rows[:, :, 1]
    along = jx * p.fx + jy * p.fy  # J_i f_i, (m, n)
    if rows.shape[1] <= SUMMED_UP_TO:
        isotropic = (jx[:, None, :] * jx[None, :, :] + jy[:, None, :] * jy[None, :, :]) * (p.alpha * inverse)
        directed = along[:, None, :] * along[None, :, :] * (p.beta * inverse)
        h = jnp.sum(isotropic + directed, axis=2)
    else:
        a, b = p.alpha * inverse, p.beta * inverse
        h = (jx * a) @ jx.T + (jy * a) @ jy.T + (along * b) @ along.T
    return 0.5 * h + jnp.eye(rows.shape[0]) / (2 * program.rho)


def _curvature(program: Standard, p: Projection, step: Any) -> Any:
    """step^T J D J^T step / w at ``p`` (the line search's second derivative, equation (9))."""
    tx, ty = _transpose_apply(program.rows, step)
    along = p.fx * tx + p.fy * ty
    return jnp.sum((p.alpha * (tx * tx + ty * ty) + p.beta * along * along) / program.weight)


def _fresh_search(step: Any) -> _Search:
    """A line search along ``step`` from length 1."""
    zero, inf = jnp.asarray(0.0), jnp.asarray(jnp.inf)
    return _Search(step, jnp.asarray(1.0), zero, inf, inf, inf, jnp.asarray(0), jnp.asarray(False), zero)


def newton(program: Standard, lam: Any, tolerance: Any, max_iterations: Any, band: Any = -1.0) -> Solution:
    """Maximize the dual of ``program`` from the multipliers ``lam`` (m,) by semismooth Newton
    ascent with the line search of docs/dual.md, section 4.

    Args:
        program: the standard form (``Standard``).
        lam: starting multipliers (m,): a warm start, or zeros.
        tolerance: stop when the gap is within ``tolerance`` times the objective, or ``grad g``
            is at its rounding level ``1e-13 (||J||_F R sqrt(n_core) + ||u||)``.
        max_iterations: Newton steps at most.
        band: also stop ("optimal") at the first multipliers whose ``|J v - u|`` is within
            ``band`` in every row (strict priority's second stage); negative: never.

    A program without core units stops at once ("optimal", nothing to solve).
    """
    rho = program.rho
    count = jnp.sum(program.core)
    floor = 1e-13 * (
        frobenius(program.rows) * program.radius * jnp.sqrt(count) + jnp.sqrt(program.u @ program.u)
    )

    def direction(point: _Point, p: Projection, iterations: Any) -> tuple[Any, _Search]:
        """The stopping tests at ``point`` (a status, or RUNNING) and the Newton direction there
        (equation (8)) with a fresh line search."""
        gap = rho * point.grad @ point.grad
        primal = point.deviation + rho * point.residual @ point.residual
        in_band = (band >= 0) & (jnp.max(jnp.abs(point.residual)) <= band)
        optimal = (gap <= tolerance * primal) | in_band | (jnp.sqrt(gap / rho) <= floor) | (count == 0)
        step, positive = solve_spd(_hessian(program, p), point.grad)
        status = jnp.where(
            optimal,
            OPTIMAL,
            jnp.where(
                iterations >= max_iterations,
                MAX_ITERATIONS,
                jnp.where(~positive, SINGULAR, jnp.where(point.grad @ step > 0, RUNNING, STALLED)),
            ),
        )
        return status, _fresh_search(step)

    def running(state: _State) -> Any:
        return state.status == RUNNING

    def one_evaluation(state: _State) -> _State:
        s, point = state.search, state.point
        slope0 = point.grad @ s.step
        value0 = _dual_value(point, rho)
        slack = 1e-14 * (jnp.abs(value0) + point.deviation + jnp.abs(point.lam) @ jnp.abs(point.residual))
        # The sets enter each pass through a barrier with the pass's multipliers: what their
        # projection computes from them alone (a polygon's boundary, ~40 arrays of n) is then
        # computed in the pass, where XLA would otherwise hoist it out of the loop and hold it.
        sets, trial_lam = jax.lax.optimization_barrier((program.sets, point.lam + s.length * s.step))
        trial, p = _evaluate(dataclasses.replace(program, sets=sets), trial_lam)
        slope = trial.grad @ s.step
        rising = slope >= 0
        accept = (rising & ((s.length == 1.0) | (slope <= CURVATURE * slope0))) | (
            ~rising
            & (slope >= -CURVATURE * slope0)
            & (_dual_value(trial, rho) >= value0 + ARMIJO * s.length * slope0 - slack)
        )
        found, best = s.found | rising, jnp.where(rising, s.length, s.best)
        lo, hi = jnp.where(rising, s.length, s.lo), jnp.where(rising, s.hi, s.length)
        # 1-D Newton on the slope, exact within one smooth piece; bisection when it leaves the
        # bracket or stalls (a slope with many kinks).
        flat = s.step @ s.step / (2 * rho)
        guess = s.length + slope / (0.5 * _curvature(program, p, s.step) + flat)
        bisect = ~((lo < guess) & (guess < hi)) | (jnp.abs(guess - s.length) > 0.5 * s.before)
        guess = jnp.where(bisect, 0.5 * (lo + hi), guess)
        exhausted = ~accept & (s.count + 1 >= MAX_SEARCH)
        # The first pass takes the starting multipliers (a step of length 0); a forced pass the
        # search's best point, evaluated again after the search ran out of evaluations.
        take = accept | state.first | state.forced
        retry = exhausted & found & ~take
        moved = _Search(
            s.step,
            jnp.where(retry, best, guess),
            lo,
            hi,
            jnp.abs(guess - s.length),
            s.moved,
            s.count + 1,
            found,
            best,
        )
        iterations = state.iterations + (take & ~state.first)
        status, fresh = direction(trial, p, iterations)
        status = jnp.where(take, status, jnp.where(exhausted & ~found, STALLED, RUNNING))
        return _State(
            _select(take, trial, point),
            _select(take, fresh, moved),
            iterations,
            state.evaluations + 1,
            status,
            jnp.asarray(False),
            retry,
        )

    # Before the first pass: the starting multipliers, a step of length 0 (the rest unused).
    m, n = program.rows.shape[0], program.rows.shape[1]
    zeros = jnp.zeros(n)
    start = _Point(jnp.asarray(lam, dtype=float), zeros, zeros, jnp.zeros(m), jnp.zeros(m), jnp.asarray(0.0))
    search = _fresh_search(jnp.zeros(m))._replace(length=jnp.asarray(0.0))
    initial = _State(
        start,
        search,
        jnp.asarray(0),
        jnp.asarray(0),
        jnp.asarray(RUNNING),
        jnp.asarray(True),
        jnp.asarray(False),
    )
    state = jax.lax.while_loop(running, one_evaluation, initial)
    point = state.point
    gap = rho * point.grad @ point.grad
    primal = point.deviation + rho * point.residual @ point.residual
    return Solution(
        point.vx, point.vy, point.lam, primal, gap, state.iterations, state.evaluations, state.status
    )
