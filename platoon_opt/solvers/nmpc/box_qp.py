"""Box-constrained convex QPs: ``min 1/2 x^T H x + g^T x`` subject to ``lower <= x <= upper``.

Two solvers for the receding-horizon SQP's step (``platoon_opt.solvers.nmpc.solve``;
docs/nmpc.md, section 4.3), whose bounds hold ``0`` (``lower <= 0 <= upper``: the step from a
feasible point):

- ``active_set_newton`` for a Hessian that is block diagonal plus low rank (``BlockLowRank``),
  the Gauss-Newton Hessian of a platoon: rows that involve one unit (speed, steering, nominal
  velocity, obstacles) give that unit's block, rows that couple units (task, clearance) the
  low-rank part. Each linear solve costs O(n b^3 + n b c^2 + c^3) for n blocks of size b and
  c coupling rows, against O((n b)^3) dense; up to ``DENSE_UP_TO`` variables the dense form is
  faster all the same (call overhead), and is used.
- ``projected_newton`` on the same Hessian: globally convergent, slower.
"""

from __future__ import annotations

from dataclasses import dataclass, field
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

    def solve_free(self, free: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """y (n b,) with H[free, free] y[free] = rhs[free] and y = 0 elsewhere (free: (n b,) bool,
        rhs: (n b,)); raises LinAlgError if the system is singular.

        Up to ``DENSE_UP_TO`` variables: Cholesky of H_FF. Above, Woodbury over the free part of
        each block: y = D^-1 rhs - Y S^-1 C D^-1 rhs with Y = D^-1 C^T and S = I + C Y, the held
        variables' rows and columns of D replaced by the identity's and their columns of C by
        zeros, so that every block keeps its size and a block solve is one batched product with
        the blocks' inverses. Where the blocks are far weaker than the coupling (the smoothness
        rows against the task rows) that formula cancels digits, so the solution is refined
        against the exact product until its residual is below 1e-12 of the right-hand side's or
        stops falling (the rounding of the product: ||H|| ||y|| eps).
        """
        if (small := self._small) is not None:
            # Cholesky of H_FF: backward stable, no refinement needed.
            kept = np.flatnonzero(free)
            y = np.zeros_like(rhs)
            y[kept] = lapack.dpotrs(_cholesky(small[np.ix_(kept, kept)]), rhs[kept], lower=1)[0]
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
        iterations: active-set iterations.
        at_upper, at_lower: the variables held at each bound in the last iteration, (n b,) bool;
            a guess for the next, similar problem.
    """

    x: np.ndarray | None
    iterations: int
    at_upper: np.ndarray
    at_lower: np.ndarray


def active_set_newton(
    hessian: BlockLowRank,
    gradient: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    guess: BoxSolution | None = None,
    max_iterations: int = 30,
) -> BoxSolution:
    """min 1/2 x^T H x + g^T x subject to lower <= x <= upper (lower <= 0 <= upper).

    Primal-dual active set (Hintermueller, Ito and Kunisch, 2002; a semismooth Newton method on
    ``x = clip(x - grad / diag(H))``): each iteration holds at its bound every variable whose
    scaled gradient step leaves the box and solves for the others exactly. When two consecutive
    iterations pick the same sets the KKT conditions hold: the free variables have zero gradient
    and lie in the box, the held ones have gradients pushing outward. The first iteration holds
    ``guess``'s sets if given (a previous SQP iteration's: on the SQP's steps that takes 2.3
    solves on average instead of 3.9 from x = 0), else those of x = 0. It is not globally
    convergent: when the sets cycle (or a free set's system is singular) it returns x = None
    and the caller needs another solver (``projected_newton``, or DAQP).
    """
    diagonal = hessian.diagonal()
    x = np.clip(np.zeros_like(gradient), lower, upper)
    held = None
    for iteration in range(1, max_iterations + 1):
        if iteration == 1 and guess is not None:
            at_upper, at_lower = guess.at_upper, guess.at_lower
        else:
            trial = x - (hessian.matvec(x) + gradient) / diagonal
            at_upper, at_lower = trial > upper, trial < lower
        now = np.concatenate((at_upper, at_lower))
        if held is not None and np.array_equal(now, held):
            return BoxSolution(np.clip(x, lower, upper), iteration, at_upper, at_lower)
        held = now
        x = np.where(at_upper, upper, np.where(at_lower, lower, 0.0))
        free = ~(at_upper | at_lower)
        if free.any():
            try:
                x = x + hessian.solve_free(free, -(gradient + hessian.matvec(x)))
            except LinAlgError:
                break
    return BoxSolution(None, iteration, at_upper, at_lower)


def projected_newton(
    hessian: BlockLowRank,
    gradient: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    tolerance: float = 1e-9,
    max_iterations: int = 1000,
) -> np.ndarray | None:
    """min 1/2 x^T H x + g^T x subject to lower <= x <= upper (lower <= 0 <= upper), H positive
    definite; x (k,), or None if it does not converge.

    Projected Newton (Bertsekas, 1982): the bounds that are (nearly) active with the gradient
    pushing outward are held, a Newton step on the others (``BlockLowRank.solve_free``: Cholesky
    of their block up to ``DENSE_UP_TO`` variables, Woodbury on the split above) and a
    diagonally scaled gradient step on the held ones, projected onto the box with an Armijo
    backtracking along the projection arc. It identifies the active set in finitely many
    steps and then converges in one; it stops when the scaled projected gradient
    ``x - clip(x - grad / diag(H))`` is below ``tolerance`` (in the units of x). Finding the set
    can take hundreds of iterations on an ill-conditioned H (experiments/battery.md).
    """
    x = np.clip(np.zeros_like(gradient), lower, upper)
    diagonal = hessian.diagonal()

    def value(point: np.ndarray) -> float:
        return float(0.5 * point @ hessian.matvec(point) + gradient @ point)

    for _ in range(max_iterations):
        grad = hessian.matvec(x) + gradient
        projected = x - np.clip(x - grad / diagonal, lower, upper)
        stationarity = float(np.max(np.abs(projected), initial=0.0))
        if stationarity <= tolerance:
            return x
        margin = min(stationarity, 1e-6)
        held = ((x - lower <= margin) & (grad > 0)) | ((upper - x <= margin) & (grad < 0))
        free = ~held
        direction = -grad / diagonal
        if free.any():
            try:
                direction[free] = hessian.solve_free(free, -grad)[free]
            except LinAlgError:
                return None
        current = value(x)
        step = 1.0
        while step > 1e-12:
            trial = np.clip(x + step * direction, lower, upper)
            if value(trial) <= current + 1e-4 * grad @ (trial - x):
                break
            step *= 0.5
        else:
            return None
        x = trial
    return None
