"""The semismooth Newton method on the dual of the standard form to which the dual allocator
brings every program (docs/dual.md, sections 2 to 4).

``solve_dual`` minimizes ``sum_i w_i ||v_i - d_i||^2 + rho ||J v - u||^2`` over ``v_i in C_i`` by
maximizing its dual over the m multipliers: for n units, velocities (n,) x 2 in m/s, J as a
``Coupling`` (m rows), u (m,), and the sets of ``platoon_opt.solvers.dual.sets``. Every iterate's
``v(lambda)`` lies in C, and the duality gap ``rho ||grad g||^2`` certifies it (``DualSolution``).
One pass over the units is an evaluator's ``evaluate``: a Python loop for small platoons
(``_ScalarEvaluator``), numpy passes for larger ones (``_VectorEvaluator``); the same numbers up
to rounding.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.linalg import lapack

from platoon_opt.solvers.dual.coupling import Coupling
from platoon_opt.solvers.dual.safe import SafeDualSets
from platoon_opt.solvers.dual.sets import TINY, PolygonSets, Projection, SectorSets

# Line search: Armijo's constant (fraction of the predicted increase of g), the accepted
# size of the slope along the step relative to the initial one, and the evaluations at most.
ARMIJO = 1e-4
CURVATURE = 0.1
MAX_SEARCH = 30
# Platoons up to this size are evaluated by a Python loop over the units (see _ScalarEvaluator).
SMALL = 32


@dataclass(frozen=True)
class DualSolution:
    """Result of ``solve_dual``.

    Attributes:
        vx, vy: the primal velocities v(lambda) (n,), m/s; always in C.
        lam: the multipliers (m,).
        primal: P(v), the objective at v (m^2/s^2); the optimum lies in [primal - gap, primal].
        gap: P(v(lambda)) - g(lambda) = rho ||grad g||^2 >= 0.
        iterations: Newton steps taken; evaluations: projection passes over the units.
        status: "optimal" (gap within tolerance), "max_iterations" or "stalled" (the line
            search found no ascent above rounding).
    """

    vx: np.ndarray
    vy: np.ndarray
    lam: np.ndarray
    primal: float
    gap: float
    iterations: int
    evaluations: int
    status: str

    @property
    def relative_gap(self) -> float:
        """gap / primal (0 when both vanish)."""
        return self.gap / max(self.primal, TINY)


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b for long vectors, without BLAS: a threaded BLAS dot product stalls for
    milliseconds when the cores are busy with other work (15 ms at n = 32,768 on a loaded
    2-core machine, against 20 us for this loop)."""
    return float(np.einsum("i,i->", a, b))


@dataclass(frozen=True)
class _Point:
    """One multiplier and what it gives: the evaluator's state at it (the projection), J v - u,
    grad g, and the weighted deviation sum w_i ||v_i - d_i||^2."""

    lam: np.ndarray
    state: Any
    residual: np.ndarray
    grad: np.ndarray
    deviation: float

    def dual(self, rho: float) -> float:
        """g(lambda) = deviation + lambda . (J v - u) - ||lambda||^2 / (4 rho)."""
        return self.deviation + float(self.lam @ self.residual) - float(self.lam @ self.lam) / (4 * rho)


class _VectorEvaluator:
    """v(lambda), J v - u and J D J^T by vectorized passes over the units (numpy)."""

    def __init__(
        self,
        dx: np.ndarray,
        dy: np.ndarray,
        coupling: Coupling,
        u: np.ndarray,
        sets: SectorSets | PolygonSets | SafeDualSets,
        weight: np.ndarray | None,
    ) -> None:
        self.dx, self.dy, self.coupling, self.u, self.sets, self.weight = dx, dy, coupling, u, sets, weight
        self.inverse = None if weight is None else 1.0 / weight

    def evaluate(self, lam: np.ndarray) -> tuple[Projection, np.ndarray, float]:
        """The projection at lam, J v - u (m,), and the deviation."""
        dx, dy, inverse = self.dx, self.dy, self.inverse
        tx, ty = self.coupling.apply_transpose(lam)
        if inverse is None:
            p = self.sets.project(dx - 0.5 * tx, dy - 0.5 * ty)
        else:
            p = replace(
                self.sets.project(dx - (0.5 * inverse) * tx, dy - (0.5 * inverse) * ty), factor=inverse
            )
        ex, ey = p.vx - dx, p.vy - dy
        deviation = dot(ex, ex) + dot(ey, ey) if self.weight is None else dot(self.weight, ex * ex + ey * ey)
        return p, self.coupling.apply(p.vx, p.vy) - self.u, deviation

    def curvature(self, p: Projection) -> np.ndarray:
        """J D J^T (m, m)."""
        return self.coupling.curvature(p)

    def jacobian_norm(self) -> float:
        """||J|| (Frobenius)."""
        jx, jy = self.coupling.jx.ravel(), self.coupling.jy.ravel()
        return math.sqrt(dot(jx, jx) + dot(jy, jy))

    def along(self, p: Projection, step: np.ndarray) -> float:
        """step^T J D J^T step."""
        tx, ty = self.coupling.apply_transpose(step)
        dxx, dxy, dyy = p.jacobian
        return dot(dxx, tx * tx) + 2 * dot(dxy, tx * ty) + dot(dyy, ty * ty)

    @staticmethod
    def velocities(p: Projection) -> tuple[np.ndarray, np.ndarray]:
        return p.vx, p.vy


class _ScalarEvaluator:
    """The same as ``_VectorEvaluator`` by a plain Python loop over the units: for a few units
    a numpy call costs far more than the arithmetic it does (n = 8: ~1 us per call, ~0.05 us
    per float operation), so small platoons take this path (``SMALL``)."""

    def __init__(
        self,
        dx: np.ndarray,
        dy: np.ndarray,
        coupling: Coupling,
        u: np.ndarray,
        sets: SectorSets | PolygonSets,
        weight: np.ndarray | None,
    ) -> None:
        n, frame = dx.size, sets.frame
        self.u, self.m = u, coupling.m
        self.x_rows, self.y_rows = coupling.x_rows.tolist(), coupling.y_rows.tolist()
        # J's rows: J v is summed row by row after the pass over the units.
        self.jx_rows, self.jy_rows = coupling.jx.tolist(), coupling.jy.tolist()
        self.point = sets.unit_point
        shapes = sets.unit_shapes()
        self.units = list(
            zip(
                dx.tolist(),
                dy.tolist(),
                coupling.jx.T.tolist(),
                coupling.jy.T.tolist(),
                frame.cos.tolist(),
                frame.sin.tolist(),
                [1.0] * n if weight is None else weight.tolist(),
                shapes * n if len(shapes) == 1 else shapes,
            )
        )

    def evaluate(self, lam: np.ndarray) -> tuple[tuple[list, list, list], np.ndarray, float]:
        """(vx, vy, per unit D as alpha, beta, fx, fy and the J^T-columns), J v - u (m,),
        the deviation."""
        values = lam.tolist()
        x_rows, y_rows, point = self.x_rows, self.y_rows, self.point
        lx, ly = [values[k] for k in x_rows], [values[k] for k in y_rows]
        deviation, vxs, vys, state = 0.0, [], [], []
        for dx, dy, jx, jy, c, s, w, shape in self.units:
            half = 0.5 / w
            wx = dx - half * sum(map(operator.mul, lx, jx))
            wy = dy - half * sum(map(operator.mul, ly, jy))
            b = c * wy - s * wx
            pa, pb, alpha, beta, fa, fb = point(c * wx + s * wy, abs(b), *shape)
            if b < 0:
                pb, fb = -pb, -fb
            vx, vy = c * pa - s * pb, s * pa + c * pb
            ex, ey = vx - dx, vy - dy
            deviation += w * (ex * ex + ey * ey)
            vxs.append(vx)
            vys.append(vy)
            state.append((alpha / w, beta / w, c * fa - s * fb, s * fa + c * fb, jx, jy))
        residual = [0.0] * self.m
        for k, row in zip(x_rows, self.jx_rows):
            residual[k] += sum(map(operator.mul, row, vxs))
        for k, row in zip(y_rows, self.jy_rows):
            residual[k] += sum(map(operator.mul, row, vys))
        return (vxs, vys, state), np.subtract(residual, self.u), deviation

    def jacobian_norm(self) -> float:
        """||J|| (Frobenius)."""
        total = 0.0
        for row in self.jx_rows + self.jy_rows:
            total += sum(map(operator.mul, row, row))
        return math.sqrt(total)

    def curvature(self, state: tuple[list, list, list]) -> np.ndarray:
        """J D J^T (m, m): sum over units of alpha J_i J_i^T + beta (J_i f)(J_i f)^T."""
        m, x_rows, y_rows = self.m, self.x_rows, self.y_rows
        out = [[0.0] * m for _ in range(m)]
        for alpha, beta, fx, fy, jx, jy in state[2]:
            if alpha:
                for k, jk in zip(x_rows, jx):
                    row = out[k]
                    for j, jj in zip(x_rows, jx):
                        row[j] += alpha * jk * jj
                for k, jk in zip(y_rows, jy):
                    row = out[k]
                    for j, jj in zip(y_rows, jy):
                        row[j] += alpha * jk * jj
            if beta:
                g = [0.0] * m
                for k, jk in zip(x_rows, jx):
                    g[k] += fx * jk
                for k, jk in zip(y_rows, jy):
                    g[k] += fy * jk
                for k in range(m):
                    scaled, row = beta * g[k], out[k]
                    for j in range(m):
                        row[j] += scaled * g[j]
        return np.array(out)

    def along(self, state: tuple[list, list, list], step: np.ndarray) -> float:
        """step^T J D J^T step."""
        values = step.tolist()
        sx, sy = [values[k] for k in self.x_rows], [values[k] for k in self.y_rows]
        total = 0.0
        for alpha, beta, fx, fy, jx, jy in state[2]:
            if alpha or beta:
                tx = sum(map(operator.mul, sx, jx))
                ty = sum(map(operator.mul, sy, jy))
                total += alpha * (tx * tx + ty * ty) + beta * (fx * tx + fy * ty) ** 2
        return total

    @staticmethod
    def velocities(state: tuple[list, list, list]) -> tuple[np.ndarray, np.ndarray]:
        return np.array(state[0]), np.array(state[1])


def solve_dual(
    dx: np.ndarray,
    dy: np.ndarray,
    coupling: Coupling,
    u: np.ndarray,
    rho: float,
    sets: SectorSets | PolygonSets | SafeDualSets,
    lam: np.ndarray,
    *,
    tolerance: float,
    max_iterations: int,
    weight: np.ndarray | None = None,
    scalar: bool | None = None,
    band: float | None = None,
) -> DualSolution:
    """Minimize ``sum w_i ||v_i - d_i||^2 + rho ||J v - u||^2`` over ``v_i in C_i`` by semismooth
    Newton ascent on the dual: ``v_i(lambda) = P_{C_i}(d_i - J_i^T lambda / (2 w_i))``, and D_i
    enters the generalized Hessian divided by w_i (docs/dual.md, equations (3) to (6)).

    Args:
        dx, dy: d (n,) x 2, m/s.
        coupling: J; u: (m,); rho: weight of the task residual, > 0.
        sets: the C_i.
        lam: starting multipliers (m,): a warm start, or zeros.
        tolerance: stop when the gap is within ``tolerance`` times the objective, or ``grad g``
            is at its rounding level.
        max_iterations: Newton steps at most.
        weight: w (n,) > 0, or None for all 1.
        scalar: evaluate by a Python loop over the units (True), by numpy (False), or by
            size (None: n <= ``SMALL``). Both give the same numbers up to rounding.
        band: also stop ("optimal") at the first multipliers whose ``|J v - u|`` is within
            ``band`` in every row (strict priority's second stage), None: never.
    """
    if scalar is None:
        scalar = dx.size <= SMALL
    evaluator: _ScalarEvaluator | _VectorEvaluator
    # The Python loop needs sets symmetric about a centre direction (``unit_point``): not the safe ones.
    if scalar and not isinstance(sets, SafeDualSets):
        evaluator = _ScalarEvaluator(dx, dy, coupling, u, sets, weight)
    else:
        evaluator = _VectorEvaluator(dx, dy, coupling, u, sets, weight)
    half_over_rho = 0.5 / rho
    evaluations = 0

    def evaluate(lam: np.ndarray) -> _Point:
        nonlocal evaluations
        evaluations += 1
        state, residual, deviation = evaluator.evaluate(lam)
        return _Point(lam, state, residual, residual - half_over_rho * lam, deviation)

    def rounding() -> float:
        """Rounding level of grad g: J v sums n products, |v_i| <= radius."""
        jnorm = evaluator.jacobian_norm()
        return 1e-13 * (jnorm * sets.frame.radius * math.sqrt(dx.size) + math.sqrt(float(u @ u)))

    point = evaluate(np.asarray(lam, dtype=float))
    status, iterations, floor = "max_iterations", 0, None
    while True:
        gap = rho * float(point.grad @ point.grad)
        primal = point.deviation + rho * float(point.residual @ point.residual)
        if gap <= tolerance * primal or (
            band is not None and float(np.max(np.abs(point.residual), initial=0.0)) <= band
        ):
            status = "optimal"
            break
        floor = rounding() if floor is None else floor
        if math.sqrt(gap / rho) <= floor:
            status = "optimal"
            break
        if iterations >= max_iterations:
            break
        hessian = 0.5 * evaluator.curvature(point.state)
        hessian.flat[:: coupling.m + 1] += half_over_rho
        _, step, info = lapack.dposv(hessian, point.grad)
        if info != 0:
            status = "singular"
            break
        accepted = _line_search(point, step, evaluate, rho, evaluator)
        if accepted is None:
            status = "stalled"
            break
        point = accepted
        iterations += 1
    vx, vy = evaluator.velocities(point.state)
    return DualSolution(vx, vy, point.lam, primal, gap, iterations, evaluations, status)


def _line_search(
    point: _Point,
    step: np.ndarray,
    evaluate: Callable[[np.ndarray], _Point],
    rho: float,
    evaluator: _VectorEvaluator | _ScalarEvaluator,
) -> _Point | None:
    """A point ``lambda + s step`` with more g, near the maximum of g along the step.

    The slope ``phi'(s) = step . grad g(lambda + s step)`` decreases in s (g is concave), is
    piecewise smooth, and is computed without the cancellation that makes differences of g
    unreliable near the optimum; ``phi''(s) = -step^T J D J^T step / 2 - ||step||^2 / (2 rho)``
    comes from the projection's Jacobian at s. s = 1 is accepted when the slope there is above
    ``-CURVATURE`` times the initial slope and the increase of g passes Armijo's test (with
    rounding slack). Otherwise the root of the slope is bracketed and found by 1-D Newton
    steps (exact within one smooth piece), bisection when Newton leaves the bracket or
    stalls, until the slope is within ``CURVATURE`` times the initial one in size.
    """
    slope0 = float(point.grad @ step)
    if not slope0 > 0:
        return None
    g0 = point.dual(rho)
    slack = 1e-14 * (abs(g0) + point.deviation + float(np.abs(point.lam) @ np.abs(point.residual)))
    flat = float(step @ step) / (2 * rho)
    lo, hi = 0.0, math.inf
    length, best, moved, before = 1.0, None, math.inf, math.inf
    for _ in range(MAX_SEARCH):
        trial = evaluate(point.lam + length * step)
        slope = float(trial.grad @ step)
        if slope >= 0:
            best = trial
            if length == 1.0 or slope <= CURVATURE * slope0:
                return trial
            lo = length
        else:
            if slope >= -CURVATURE * slope0 and trial.dual(rho) >= g0 + ARMIJO * length * slope0 - slack:
                return trial
            hi = length
        guess = length + slope / (0.5 * evaluator.along(trial.state, step) + flat)
        if not lo < guess < hi or abs(guess - length) > 0.5 * before:
            # Newton leaves the bracket or stalls: bisect (a slope with many kinks).
            guess = 0.5 * (lo + hi)
        moved, before = abs(guess - length), moved
        length = guess
    return best
