"""The coupling of the units in the dual allocator: J (m x 2n) as the m rows of each unit, split
by axis, and the task-space algebra on it (docs/dual.md, section 2).

A task whose rows each involve one axis (the mean/variance task: the means and variances of x
and of y) costs half: ``Coupling`` keeps the x parts of the rows that have one (``jx``, (mx, n))
and the y parts of the rows that have one (``jy``, (my, n)). Velocities are (n,) x 2 in m/s,
task vectors (m,).
``task_basis`` gives the regular directions E of J J^T, ``inverse_sqrt`` the matrix M^{-1/2}
of the task-exact reduction (docs/dual.md, section 6).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from platoon_opt.solvers.dual.sets import Projection


@lru_cache(maxsize=16)
def _blocks(x: tuple[int, ...], y: tuple[int, ...]) -> tuple[tuple[np.ndarray, ...], ...]:
    """Index grids of the (x, x), (y, y), (x, y), (y, x) blocks of an m x m matrix."""
    return np.ix_(x, x), np.ix_(y, y), np.ix_(x, y), np.ix_(y, x)


@dataclass(frozen=True)
class Coupling:
    """J (m x 2n) as the rows that have an x part (``jx``, (mx, n)) and the rows that have a y
    part (``jy``, (my, n)); ``x_rows``, ``y_rows`` are their indices among the m rows."""

    m: int
    x_rows: np.ndarray
    y_rows: np.ndarray
    jx: np.ndarray
    jy: np.ndarray

    @classmethod
    def of(cls, rows: np.ndarray) -> Coupling:
        """From Jacobian rows (m, n, 2)."""
        parts = np.asarray(rows.any(axis=1))  # (m, 2): whether each row has an x part, a y part
        x_rows, y_rows = parts[:, 0].nonzero()[0], parts[:, 1].nonzero()[0]
        return cls(
            rows.shape[0],
            x_rows,
            y_rows,
            np.ascontiguousarray(rows[x_rows, :, 0]),
            np.ascontiguousarray(rows[y_rows, :, 1]),
        )

    @cached_property
    def _blocks(self) -> tuple[tuple[np.ndarray, ...], ...]:
        return _blocks(tuple(self.x_rows.tolist()), tuple(self.y_rows.tolist()))

    def gram(self, weight: np.ndarray | None = None) -> np.ndarray:
        """J W J^T (m, m) for unit weights W = diag(weight) (None: J J^T)."""
        xx, yy, _, _ = self._blocks
        jx, jy = (self.jx, self.jy) if weight is None else (self.jx * weight, self.jy * weight)
        out = np.zeros((self.m, self.m))
        out[xx] = jx @ self.jx.T
        out[yy] += jy @ self.jy.T
        return out

    def transform(self, matrix: np.ndarray) -> Coupling:
        """The coupling of K J for K (r, m): its rows are combinations of these, so each keeps to
        the axes of the rows it combines."""
        kx, ky = matrix[:, self.x_rows], matrix[:, self.y_rows]
        x_rows, y_rows = kx.any(axis=1).nonzero()[0], ky.any(axis=1).nonzero()[0]
        return Coupling(matrix.shape[0], x_rows, y_rows, kx[x_rows] @ self.jx, ky[y_rows] @ self.jy)

    def take(self, units: np.ndarray) -> Coupling:
        """The coupling of the units ``units`` (indices) alone."""
        # np.take: fancy indexing along the second axis is ten times slower.
        return Coupling(
            self.m, self.x_rows, self.y_rows, np.take(self.jx, units, axis=1), np.take(self.jy, units, axis=1)
        )

    def apply(self, vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
        """J v for v (n,) x 2: shape (m,)."""
        out = np.zeros(self.m)
        out[self.x_rows] = self.jx @ vx
        out[self.y_rows] += self.jy @ vy
        return out

    def apply_transpose(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """J^T w for w (m,): velocities (n,) x 2."""
        return weights[self.x_rows] @ self.jx, weights[self.y_rows] @ self.jy

    def curvature(self, p: Projection) -> np.ndarray:
        """J D J^T, (m, m), for the block-diagonal D of a projection's Jacobian."""
        xx, yy, xy, yx = self._blocks
        dxx, dxy, dyy = p.jacobian
        out = np.zeros((self.m, self.m))
        out[xx] = (self.jx * dxx) @ self.jx.T
        out[yy] += (self.jy * dyy) @ self.jy.T
        cross = (self.jx * dxy) @ self.jy.T
        out[xy] += cross
        out[yx] += cross.T
        return out


def task_basis(coupling: Coupling, rcond: float) -> np.ndarray:
    """Orthonormal eigenvectors E (m, r) of J J^T with eigenvalues above ``rcond`` times the largest:
    the directions ``platoon_opt.tasks.TaskJacobian.regular_directions`` keeps for ``J a = u``, as
    ``platoon_opt.solvers.convex.formulation`` does (docs/dual.md, section 6). When no row has
    both axes (the mean/variance task) J J^T is block diagonal by axis and is decomposed per
    block, so that each direction keeps to one axis (``Coupling`` then skips the other)."""
    gram, m = coupling.gram(), coupling.m
    if np.intersect1d(coupling.x_rows, coupling.y_rows).size:
        blocks = [np.arange(m)]
    else:
        blocks = [coupling.x_rows, np.setdiff1d(np.arange(m), coupling.x_rows)]
    values, vectors = [], []
    for block in (block for block in blocks if block.size):
        block_values, block_vectors = np.linalg.eigh(gram[np.ix_(block, block)])
        embedded = np.zeros((m, block.size))
        embedded[block] = block_vectors
        values.append(block_values)
        vectors.append(embedded)
    values_all, vectors_all = np.concatenate(values), np.concatenate(vectors, axis=1)
    top = float(np.max(values_all))
    return vectors_all[:, values_all > rcond * top] if top > 0 else vectors_all[:, :0]


def inverse_sqrt(matrix: np.ndarray) -> np.ndarray:
    """M^{-1/2} of a symmetric positive definite matrix; entries at rounding level are zeroed so
    that a block-diagonal M (directions of one axis) keeps its blocks exactly."""
    values, vectors = np.linalg.eigh(matrix)
    root = (vectors / np.sqrt(values)) @ vectors.T
    root[np.abs(root) <= 1e-14 * np.max(np.abs(root), initial=0.0)] = 0.0
    return root
