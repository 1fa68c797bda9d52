"""Box-constrained convex QPs: ``min 1/2 x^T H x + g^T x`` subject to ``lower <= x <= upper``.

Two solvers for the receding-horizon SQP's step (``platoon_opt.solvers.nmpc.solve``;
docs/nmpc.md, section 4.3), whose bounds hold ``0`` (``lower <= 0 <= upper``: the step from a
feasible point):

- ``active_set_newton`` for a Hessian that is block diagonal plus low rank (``BlockLowRank``),
  the Gauss-Newton Hessian of a platoon: rows that involve one unit (speed, steering, nominal
  velocity, obstacles) give that unit's block, rows that couple units (task, clearance) the
  low-rank part. Each linear solve costs O(n b^3 + n b c^2 + c^3) for n blocks of size b and
  c coupling rows, against O((n b)^3) dense; up to ``DENSE_UP_TO`` variables the dense form is
  faster all the same (call overhead), and is used. Where its exchange of sets cycles it
  restarts from a few steps of projected Newton.
- ``projected_newton`` on the same Hessian: globally convergent, slower.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy.linalg import LinAlgError, lapack

# Up to this many variables ``BlockLowRank`` works on its dense form: below it the split's
# per-block calls cost more than the dense flops. Active-set solves of the SQP's QPs
# (experiments/nmpc_qp_timing.py, benchmarks/results/nmpc_timing.md): 160 variables, dense
# form faster; 320, split faster.
DENSE_UP_TO = 200
# Residual ||H_FF y - rhs|| / ||rhs|| at which a free-set solve stops refining.
_REFINE_TOLERANCE = 1e-12
_REFINE_STEPS = 3
# Projected Newton steps between two runs of the active-set exchange when its sets cycle.
RESTART_STEPS = 5


@dataclass(frozen=True)
class BlockLowRank:
    """H = blockdiag(blocks) + coupling^T coupling, positive definite.

    Up to ``DENSE_UP_TO`` variables the products and solves use H's dense form (formed once,
    O(n b^2 c)); above, the split (O(n b^2 + n b c) memory, no dense H).

    Attributes:
        blocks: (n, b, b), each symmetric positive definite; variable j belongs to block j // b.
        coupling: (c, n b).
    """

    blocks: np.ndarray
    coupling: np.ndarray
    # The inverses of the blocks' free parts by (block, free mask): an active-set iteration
    # changes the free sets of a few blocks only.
    _inverses: dict[tuple[int, bytes], np.ndarray] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @property
    def size(self) -> int:
        """Number of variables, n b."""
        return self.blocks.shape[0] * self.blocks.shape[1]

    @property
    def is_split(self) -> bool:
        """Whether products and solves work on the split (more than ``DENSE_UP_TO`` variables)."""
        return self._small is None

    @cached_property
    def _small(self) -> np.ndarray | None:
        """H dense (formed on first use) if there are at most ``DENSE_UP_TO`` variables."""
        return self.dense() if self.size <= DENSE_UP_TO else None

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """H x for x (n b,)."""
        if (small := self._small) is not None:
            return small @ x
        n, b, _ = self.blocks.shape
        local = np.einsum("ijk,ik->ij", self.blocks, x.reshape(n, b)).reshape(-1)
        return local + self.coupling.T @ (self.coupling @ x)

    def diagonal(self) -> np.ndarray:
        """diag(H), (n b,)."""
        return self._diagonal

    @cached_property
    def _diagonal(self) -> np.ndarray:
        return np.einsum("ijj->ij", self.blocks).reshape(-1) + np.einsum(
            "ij,ij->j", self.coupling, self.coupling
        )

    def dense(self) -> np.ndarray:
        """H as a dense (n b, n b) array."""
        n, b, _ = self.blocks.shape
        hessian = self.coupling.T @ self.coupling
        for i in range(n):
            hessian[i * b : (i + 1) * b, i * b : (i + 1) * b] += self.blocks[i]
        return hessian

    def _block_inverse(self, i: int, free: np.ndarray) -> np.ndarray:
        """The inverse (b, b) of block i with its held rows and columns replaced by the
        identity's (free: (b,) bool)."""
        key = (i, free.tobytes())
        if key not in self._inverses:
            diagonal = np.arange(free.size)
            block = np.where(free[:, None] & free[None, :], self.blocks[i], 0.0)
            block[diagonal, diagonal] += ~free
            # LAPACK directly: scipy's wrappers cost more than these small factorizations.
            lower, info = lapack.dpotri(_cholesky(block), lower=1)
            if info != 0:
                raise LinAlgError(f"block {i} is singular (dpotri info {info})")
            inverse = lower + lower.T  # dpotri fills the lower triangle, zeros above
            inverse[diagonal, diagonal] /= 2
            self._inverses[key] = inverse
        return self._inverses[key]

    def _free_part(self, kept: np.ndarray) -> np.ndarray:
        """H[kept, kept] (k, k) for the variable indices ``kept`` (k,)."""
        if (small := self._small) is not None:
            return small[np.ix_(kept, kept)]
        b = self.blocks.shape[1]
        block, local = np.divmod(kept, b)
        same = block[:, None] == block[None, :]
        part = np.where(same, self.blocks[block[:, None], local[:, None], local[None, :]], 0.0)
        columns = self.coupling[:, kept]
        return part + columns.T @ columns

    def solve_free(self, free: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """y (n b,) with H[free, free] y[free] = rhs[free] and y = 0 elsewhere (free: (n b,) bool,
        rhs: (n b,)); raises LinAlgError if the system is singular.

        Up to ``DENSE_UP_TO`` free variables: Cholesky of H_FF. Above, Woodbury over the free part of
        each block: y = D^-1 rhs - Y S^-1 C D^-1 rhs with Y = D^-1 C^T and S = I + C Y, the held
        variables' rows and columns of D replaced by the identity's and their columns of C by
        zeros, so that every block keeps its size and a block solve is one batched product with
        the blocks' inverses. Where the blocks are far weaker than the coupling (the smoothness
        rows against the task rows) that formula cancels digits, so the solution is refined
        against the exact product until its residual is below 1e-12 of the right-hand side's or
        stops falling (the rounding of the product: ||H|| ||y|| eps).
        """
        kept = np.flatnonzero(free)
        if kept.size <= DENSE_UP_TO:
            # Cholesky of H_FF: backward stable, no refinement needed. Above DENSE_UP_TO variables
            # a few free ones (most inputs at their bounds, as in a transient) are one small
            # system all the same: H_FF formed from the blocks and the coupling's free columns.
            y = np.zeros_like(rhs)
            y[kept] = lapack.dpotrs(_cholesky(self._free_part(kept)), rhs[kept], lower=1)[0]
            return y
        n, b, _ = self.blocks.shape
        mask = free.reshape(n, b)
        inverses = np.stack([self._block_inverse(i, mask[i]) for i in range(n)])
        coupling = np.where(free, self.coupling, 0.0)

        def block_solve(v: np.ndarray) -> np.ndarray:
            return np.matmul(inverses, v.reshape(n, b, -1)).reshape(v.shape)

        weighted = block_solve(coupling.T)  # Y, (n b, c)
        capacitance = _cholesky(np.identity(coupling.shape[0]) + coupling @ weighted)

        def solve(v: np.ndarray) -> np.ndarray:
            w = block_solve(v)
            if not coupling.shape[0]:
                return w
            return w - weighted @ lapack.dpotrs(capacitance, coupling @ w, lower=1)[0]

        target = np.where(free, rhs, 0.0)
        tolerance = _REFINE_TOLERANCE * float(np.linalg.norm(target))
        y, previous = solve(target), np.inf
        for _ in range(_REFINE_STEPS):
            residual = np.where(free, target - self.matvec(y), 0.0)
            error = float(np.linalg.norm(residual))
            # Stop at the tolerance or at the rounding floor of the product (no longer halving,
            # where a correction neither helps nor hurts).
            if error <= tolerance or error > previous / 2:
                break
            y, previous = y + solve(residual), error
        return y


def _cholesky(matrix: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor of a symmetric positive definite matrix; LinAlgError if not."""
    factor, info = lapack.dpotrf(matrix, lower=1)
    if info != 0:
        raise LinAlgError(f"not positive definite (dpotrf info {info})")
    return factor


@dataclass(frozen=True)
class BoxSolution:
    """A solution of ``active_set_newton``.

    Attributes:
        x: the minimizer (n b,), or None if the active sets cycled.
        iterations: active-set exchanges and projected Newton steps.
        at_upper, at_lower: the variables held at each bound in the last iteration, (n b,) bool;
            a guess for the next, similar problem.
        start: if x is None, the point of least objective reached, in the box (n b,): where
            another solver starts.
    """

    x: np.ndarray | None
    iterations: int
    at_upper: np.ndarray
    at_lower: np.ndarray
    start: np.ndarray | None = None


def active_set_newton(
    hessian: BlockLowRank,
    gradient: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    guess: BoxSolution | None = None,
    max_iterations: int = 30,
    restarts: int = 10,
) -> BoxSolution:
    """min 1/2 x^T H x + g^T x subject to lower <= x <= upper (lower <= 0 <= upper).

    Primal-dual active set (Hintermueller, Ito and Kunisch, 2002; a semismooth Newton method on
    ``x = clip(x - grad / diag(H))``): each iteration holds at its bound every variable whose
    scaled gradient step leaves the box and solves for the others exactly. When two consecutive
    iterations pick the same sets the KKT conditions hold: the free variables have zero gradient
    and lie in the box, the held ones have gradients pushing outward. The first iteration holds
    ``guess``'s sets if given (a previous SQP iteration's: on the SQP's steps that takes 2.3
    solves on average instead of 3.9 from x = 0), else those of x = 0.

    The exchange of sets is not globally convergent: where H is far from an M-matrix (units
    coupled by the task rows, most inputs at their bounds in a transient) the sets come back to
    earlier ones, and since the sets decide the next ones that is a cycle. Then it takes
    ``RESTART_STEPS`` steps of projected Newton (which lower the objective at every step) from
    the best iterate so far, and starts the exchange again from the sets that point picks; at
    most ``restarts`` times. If that does not end it (or a free set's system is singular) it
    returns x = None with the best point as ``start`` for another solver (``projected_newton``,
    or DAQP). ``iterations`` counts the exchanges and the Newton steps.
    """
    point = np.clip(np.zeros_like(gradient), lower, upper)
    if guess is not None:
        at_upper, at_lower = guess.at_upper, guess.at_lower
    else:
        at_upper, at_lower = wanted_sets(hessian, gradient, lower, upper, point)
    iterations = 0
    for _ in range(restarts + 1):
        exchanged = _exchange(hessian, gradient, lower, upper, at_upper, at_lower, max_iterations)
        iterations += exchanged.iterations
        if exchanged.x is not None:
            return replace(exchanged, iterations=iterations)
        start = exchanged.start
        if start is not None and _objective(hessian, gradient, start) < _objective(hessian, gradient, point):
            point = start
        stepped, converged = _newton_steps(hessian, gradient, lower, upper, point, RESTART_STEPS)
        iterations += RESTART_STEPS
        if stepped is None:
            break
        point = stepped
        at_upper, at_lower = wanted_sets(hessian, gradient, lower, upper, point)
        if converged:
            return BoxSolution(point, iterations, at_upper, at_lower)
    return BoxSolution(None, iterations, at_upper, at_lower, point)


def _exchange(
    hessian: BlockLowRank,
    gradient: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    at_upper: np.ndarray,
    at_lower: np.ndarray,
    max_iterations: int,
) -> BoxSolution:
    """The primal-dual active-set exchange from the sets held at the bounds (k,) bool: the
    minimizer with the sets it holds, or x = None (the sets cycled, ``max_iterations`` ran out,
    or a singular free set) with the iterate of least objective, projected onto the box, as
    ``start``."""
    best = np.clip(np.zeros_like(gradient), lower, upper)
    least = 0.0
    seen: set[bytes] = set()
    for iteration in range(1, max_iterations + 1):
        held = np.concatenate((at_upper, at_lower)).tobytes()
        if held in seen:
            break
        seen.add(held)
        x = np.where(at_upper, upper, np.where(at_lower, lower, 0.0))
        free = ~(at_upper | at_lower)
        if free.any():
            try:
                x = x + hessian.solve_free(free, -(gradient + hessian.matvec(x)))
            except LinAlgError:
                break
        projected = np.clip(x, lower, upper)
        if (value := _objective(hessian, gradient, projected)) < least:
            best, least = projected, value
        want_upper, want_lower = wanted_sets(hessian, gradient, lower, upper, x)
        if np.array_equal(want_upper, at_upper) and np.array_equal(want_lower, at_lower):
            return BoxSolution(projected, iteration, at_upper, at_lower)
        at_upper, at_lower = want_upper, want_lower
    return BoxSolution(None, iteration, at_upper, at_lower, best)


def wanted_sets(
    hessian: BlockLowRank, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray, x: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The variables whose scaled gradient step from x leaves the box above and below, (k,) bool
    each: the sets the exchange holds next."""
    trial = x - (hessian.matvec(x) + gradient) / hessian.diagonal()
    return trial > upper, trial < lower


def _objective(hessian: BlockLowRank, gradient: np.ndarray, x: np.ndarray) -> float:
    """1/2 x^T H x + g^T x."""
    return float(0.5 * x @ hessian.matvec(x) + gradient @ x)


def projected_newton(
    hessian: BlockLowRank,
    gradient: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    tolerance: float = 1e-9,
    max_iterations: int = 1000,
    start: np.ndarray | None = None,
) -> np.ndarray | None:
    """min 1/2 x^T H x + g^T x subject to lower <= x <= upper (lower <= 0 <= upper), H positive
    definite; x (k,), or None if it does not converge.

    Projected Newton (Bertsekas, 1982) from ``start`` (projected onto the box; default 0): the
    bounds that are (nearly) active with the gradient pushing outward are held, a Newton step on
    the others (``BlockLowRank.solve_free``) and a diagonally scaled gradient step on the held
    ones, projected onto the box with an Armijo backtracking along the projection arc. It
    identifies the active set in finitely many steps and then converges in one; it stops when
    the scaled projected gradient ``x - clip(x - grad / diag(H))`` is below ``tolerance`` (in
    the units of x). Finding the set can take hundreds of iterations on an ill-conditioned H
    (experiments/battery.md).
    """
    x = np.clip(np.zeros_like(gradient) if start is None else start, lower, upper)
    x, converged = _newton_steps(hessian, gradient, lower, upper, x, max_iterations, tolerance)
    return x if converged else None


def _newton_steps(
    hessian: BlockLowRank,
    gradient: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    x: np.ndarray,
    steps: int,
    tolerance: float = 1e-9,
) -> tuple[np.ndarray | None, bool]:
    """At most ``steps`` steps of projected Newton (``projected_newton``) from x in the box: the
    point reached (None if a step failed: a singular free set, or no decrease along the arc) and
    whether it is stationary to ``tolerance``."""
    diagonal = hessian.diagonal()
    for taken in range(steps + 1):
        grad = hessian.matvec(x) + gradient
        projected = x - np.clip(x - grad / diagonal, lower, upper)
        stationarity = float(np.max(np.abs(projected), initial=0.0))
        if stationarity <= tolerance:
            return x, True
        if taken == steps:
            return x, False
        margin = min(stationarity, 1e-6)
        held = ((x - lower <= margin) & (grad > 0)) | ((upper - x <= margin) & (grad < 0))
        free = ~held
        direction = -grad / diagonal
        if free.any():
            try:
                direction[free] = hessian.solve_free(free, -grad)[free]
            except LinAlgError:
                return None, False
        current = _objective(hessian, gradient, x)
        step = 1.0
        while step > 1e-12:
            trial = np.clip(x + step * direction, lower, upper)
            if _objective(hessian, gradient, trial) <= current + 1e-4 * grad @ (trial - x):
                break
            step *= 0.5
        else:
            return None, False
        x = trial
    return x, False
