"""Interior points for the box QP on the split Hessian, where the active-set exchange is slow or
stalls (docs/nmpc.md, section 4.3).

``min 1/2 x^T (blockdiag(B) + C^T C) x + g^T x`` subject to ``lower <= x <= upper``:

- ``interior_point``: Mehrotra's predictor-corrector on the QP as it is, each Newton system
  ``(blockdiag(B) + D + C^T C) dx = r`` (D diagonal, from the bounds' barrier) solved by
  Woodbury over the blocks: one Cholesky per block and one of the (c, c) capacitance, O(n b^3 +
  n b c^2 + c^3) a step, never the dense (n b)^2 Hessian.
- ``lifted_clarabel``: Clarabel on the QP lifted to a sparse form, with the coupling rows' values
  w = C x as variables,

      minimize  1/2 x^T blockdiag(B) x + 1/2 w^T w + g^T x   s.t.  C x - w = 0,  box on x,

  whose KKT matrix holds the blocks and C once (O(n b^2 + c n b) nonzeros). Slower (its sparse
  LDL factors C's dense rows without BLAS); the last resort.

Either answer's active sets start the exchange (``box_qp.active_set_newton``), which ends at the
exact minimizer, in one to three exchanges.
"""

from __future__ import annotations

from collections.abc import Callable

import clarabel
import numpy as np
import scipy.sparse as sp
from scipy.linalg import LinAlgError, lapack

from platoon_opt.solvers.nmpc.box_qp import BlockLowRank, BoxSolution, active_set_newton, wanted_sets

# Mehrotra's steps stop at this scaled residual and mean complementarity: far below what the
# exchange needs to read the active sets off x (tested: the exchange then ends in 1-3 steps).
_TOLERANCE = 1e-9
_MAX_STEPS = 60
# Fraction of the step to the boundary of the positive orthant (keeps the iterate interior).
_TO_BOUNDARY = 0.99


def interior_point(
    hessian: BlockLowRank, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> BoxSolution | None:
    """The minimizer as ``active_set_newton``'s answer from the sets of Mehrotra's
    predictor-corrector (module docstring); None if a Newton system is singular, the steps do
    not converge, or the exchange from their sets does not end."""
    n, b, _ = hessian.blocks.shape
    size = n * b
    scale = max(1.0, float(np.max(np.abs(gradient))))
    exact = lower, upper
    # A variable whose bounds meet has no interior: the steps see it in a sliver around its
    # value, and the exchange, on the exact bounds, holds it there.
    sliver = 1e-8 * max(1.0, float(np.max(upper - lower)))
    closed = upper - lower < sliver
    lower, upper = np.where(closed, lower - sliver, lower), np.where(closed, upper + sliver, upper)
    x = 0.5 * (lower + upper)
    slack_low, slack_up = x - lower, upper - x
    dual_low = np.full(size, 1e-2 * scale)
    dual_up = dual_low.copy()
    for _ in range(_MAX_STEPS):
        residual = hessian.matvec(x) + gradient - dual_low + dual_up
        mu = float(slack_low @ dual_low + slack_up @ dual_up) / (2 * size)
        if np.max(np.abs(residual)) <= _TOLERANCE * scale and mu <= 1e-3 * _TOLERANCE * scale:
            break
        try:
            solve = _barrier_solver(hessian, dual_low / slack_low + dual_up / slack_up)
        except LinAlgError:
            return None
        slacks, duals = (slack_low, slack_up), (dual_low, dual_up)
        zero = np.zeros(size)
        dx, d_low, d_up = _direction(solve, residual, slacks, duals, 0.0, (zero, zero))
        primal = min(_to_boundary(slack_low, dx), _to_boundary(slack_up, -dx))
        dual = min(_to_boundary(dual_low, d_low), _to_boundary(dual_up, d_up))
        affine = float(
            (slack_low + primal * dx) @ (dual_low + dual * d_low)
            + (slack_up - primal * dx) @ (dual_up + dual * d_up)
        ) / (2 * size)
        # Mehrotra's centring (affine / mu)^3 and second-order correction.
        target = (affine / mu) ** 3 * mu
        dx, d_low, d_up = _direction(solve, residual, slacks, duals, target, (dx * d_low, -dx * d_up))
        primal = _TO_BOUNDARY * min(_to_boundary(slack_low, dx), _to_boundary(slack_up, -dx))
        dual = _TO_BOUNDARY * min(_to_boundary(dual_low, d_low), _to_boundary(dual_up, d_up))
        x = x + primal * dx
        slack_low, slack_up = x - lower, upper - x
        dual_low, dual_up = dual_low + dual * d_low, dual_up + dual * d_up
    else:
        return None
    return _exchange_from(hessian, gradient, *exact, np.clip(x, *exact))


def _direction(
    solve: Callable[[np.ndarray], np.ndarray],
    residual: np.ndarray,
    slacks: tuple[np.ndarray, np.ndarray],
    duals: tuple[np.ndarray, np.ndarray],
    target: float,
    corrections: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Newton step (dx, dz_low, dz_up) on H x + g - z_low + z_up = 0 (``residual`` its left
    side now), s_low z_low = target and s_up z_up = target, with s_low = x - lower, s_up = upper -
    x, and the products' second-order ``corrections`` (zero for the affine step)."""
    (slack_low, slack_up), (dual_low, dual_up) = slacks, duals
    low_rhs = target - slack_low * dual_low - corrections[0]
    up_rhs = target - slack_up * dual_up - corrections[1]
    dx = solve(-residual + low_rhs / slack_low - up_rhs / slack_up)
    return dx, (low_rhs - dual_low * dx) / slack_low, (up_rhs + dual_up * dx) / slack_up


def _to_boundary(value: np.ndarray, step: np.ndarray) -> float:
    """The largest t <= 1 with value + t step >= 0 (value > 0)."""
    falling = step < 0
    return min(1.0, float(np.min(-value[falling] / step[falling]))) if falling.any() else 1.0


def _barrier_solver(hessian: BlockLowRank, barrier: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A solve of (blockdiag(B) + D + C^T C) y = r, D = diag(barrier), by Woodbury: with L the
    Cholesky factor of blockdiag(B) + D (block by block) and W = L^-1 C^T, the matrix is
    L (I + W W^T) L^T, so y = L^-T (h - W S^-1 W^T h) with h = L^-1 r and the capacitance
    S = I + W^T W (c, c). Raises LinAlgError if a factor fails."""
    n, b, _ = hessian.blocks.shape
    coupling = hessian.coupling
    c = coupling.shape[0]
    diagonal = np.arange(b)
    blocks = hessian.blocks.copy()
    blocks[:, diagonal, diagonal] += barrier.reshape(n, b)
    inverse_factors = np.linalg.inv(np.linalg.cholesky(blocks))  # L_i^-1, (n, b, b)
    weighted = (inverse_factors @ coupling.reshape(c, n, b).transpose(1, 2, 0)).reshape(n * b, c)
    capacitance = weighted.T @ weighted
    capacitance[np.diag_indices(c)] += 1.0
    factor, info = lapack.dpotrf(capacitance, lower=1) if c else (capacitance, 0)
    if info != 0:
        raise LinAlgError(f"capacitance not positive definite (dpotrf info {info})")

    def solve(rhs: np.ndarray) -> np.ndarray:
        half = (inverse_factors @ rhs.reshape(n, b, 1)).reshape(-1)
        if c:
            half = half - weighted @ lapack.dpotrs(factor, weighted.T @ half, lower=1)[0]
        return (np.swapaxes(inverse_factors, 1, 2) @ half.reshape(n, b, 1)).reshape(-1)

    return solve


def lifted_clarabel(
    hessian: BlockLowRank, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> BoxSolution | None:
    """The minimizer as ``active_set_newton``'s answer from the sets of Clarabel's solution of
    the lifted QP (module docstring); None if Clarabel does not solve it or the exchange from
    its sets does not end."""
    n, b, _ = hessian.blocks.shape
    size, c = n * b, hessian.coupling.shape[0]
    blocks = sp.block_diag(list(hessian.blocks), format="csc")
    P = sp.triu(sp.block_diag((blocks, sp.identity(c)), format="csc"), format="csc")
    identity = sp.identity(size, format="csc")
    A = sp.vstack(
        (
            sp.hstack((sp.csc_matrix(hessian.coupling), -sp.identity(c))),
            sp.hstack((identity, sp.csc_matrix((size, c)))),
            sp.hstack((-identity, sp.csc_matrix((size, c)))),
        ),
        format="csc",
    )
    offsets = np.concatenate((np.zeros(c), upper, -lower))
    cones = [clarabel.ZeroConeT(c), clarabel.NonnegativeConeT(2 * size)]
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    q = np.concatenate((gradient, np.zeros(c)))
    result = clarabel.DefaultSolver(P, q, A, offsets, cones, settings).solve()
    if result.status != clarabel.SolverStatus.Solved:
        return None
    return _exchange_from(hessian, gradient, lower, upper, np.clip(np.asarray(result.x[:size]), lower, upper))


def _exchange_from(
    hessian: BlockLowRank, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray, x: np.ndarray
) -> BoxSolution | None:
    """The exchange of sets started from those x (near the minimizer, in the box) picks; None if
    it does not end."""
    at_upper, at_lower = wanted_sets(hessian, gradient, lower, upper, x)
    polished = active_set_newton(
        hessian, gradient, lower, upper, BoxSolution(None, 0, at_upper, at_lower), restarts=0
    )
    return polished if polished.x is not None else None
