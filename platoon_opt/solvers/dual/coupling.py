"""The coupling of the units in the dual allocator: J (m x 2n, stored as rows (m, n, 2)) and the
small task-space algebra on it (docs/dual.md, sections 2 and 6), as JAX kernels.

* ``task_basis``: the regular directions E of J J^T, as all m eigenvectors and a mask (static
  shapes), decomposed per axis block when no row mixes the axes;
* ``cholesky``, ``solve_lower``, ``solve_upper``: the m x m factorizations of the Newton system
  and of the task-exact reduction, unrolled over the static m: m is a handful (4 for the
  mean/variance task), and written out they fuse with the arithmetic around them instead of
  calling LAPACK per step.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

# Cyclic Jacobi sweeps of ``task_basis``: each is quadratically convergent once the off-diagonal
# entries are small; 4 x 4 Gram matrices reach rounding within 5 or 6.
JACOBI_SWEEPS = 10


def gram(rows: Any, weight: Any = None) -> Any:
    """J W J^T (m, m) for rows (m, n, 2) and unit weights W = diag(weight) (n,) (None: J J^T)."""
    weighted = rows if weight is None else rows * weight[None, :, None]
    return jnp.einsum("kij,lij->kl", weighted, rows)


def _jacobi(matrix: Any) -> tuple[Any, Any]:
    """Eigenvalues (m,) and orthonormal eigenvectors (m, m, as columns) of a symmetric matrix by
    cyclic Jacobi rotations. A rotation acts on one pair of rows at a time and is the identity
    where their entry is 0: the blocks of a block-diagonal matrix (a task whose rows each keep
    to one axis) are decomposed separately, and every eigenvector keeps to one block."""
    m = matrix.shape[0]
    pairs = [(p, q) for p in range(m) for q in range(p + 1, m)]

    def sweep(_: Any, state: tuple[Any, Any]) -> tuple[Any, Any]:
        a, v = state
        for p, q in pairs:
            apq, app, aqq = a[p, q], a[p, p], a[q, q]
            rotate = apq != 0
            theta = (aqq - app) / (2.0 * jnp.where(rotate, apq, 1.0))
            tangent = jnp.where(
                rotate, jnp.sign(theta) / (jnp.abs(theta) + jnp.sqrt(theta * theta + 1.0)), 0.0
            )
            tangent = jnp.where(rotate & (theta == 0), 1.0, tangent)
            c = 1.0 / jnp.sqrt(tangent * tangent + 1.0)
            s = tangent * c
            rotation = jnp.eye(m).at[p, p].set(c).at[q, q].set(c).at[p, q].set(s).at[q, p].set(-s)
            a = rotation.T @ a @ rotation
            a = a.at[p, q].set(0.0).at[q, p].set(0.0)
            v = v @ rotation
        return a, v

    a, v = jax.lax.fori_loop(0, JACOBI_SWEEPS, sweep, (matrix, jnp.eye(m, dtype=matrix.dtype)))
    return jnp.diagonal(a), v


def task_basis(rows: Any, rcond: float) -> tuple[Any, Any]:
    """The eigenvectors E (m, m, columns) of J J^T for rows (m, n, 2) and which are regular (m,)
    bool: eigenvalue above ``rcond`` times the largest (none when J = 0), the directions
    ``platoon_opt.tasks.TaskJacobian.regular`` keeps for ``J a = u``, as
    ``platoon_opt.solvers.convex.formulation`` does (docs/dual.md, section 6). When no row has
    both axes (the mean/variance task) J J^T is block diagonal by axis and each direction keeps
    to one axis (``_jacobi``)."""
    values, vectors = _jacobi(gram(rows))
    top = jnp.max(values)
    return vectors, (values > rcond * top) & (top > 0)


def cholesky(matrix: Any) -> tuple[Any, Any]:
    """The lower Cholesky factor L (m, m) of a symmetric matrix and whether it is positive
    definite (every pivot positive and finite); where it is not, L is not a factor."""
    m = matrix.shape[0]
    factor: list[list[Any]] = [[jnp.zeros((), matrix.dtype)] * m for _ in range(m)]
    ok = jnp.asarray(True)
    for j in range(m):
        pivot = matrix[j, j] - sum((factor[j][k] * factor[j][k] for k in range(j)), jnp.zeros(()))
        ok = ok & (pivot > 0) & jnp.isfinite(pivot)
        root = jnp.sqrt(jnp.where(pivot > 0, pivot, 1.0))
        factor[j][j] = root
        for i in range(j + 1, m):
            rest = sum((factor[i][k] * factor[j][k] for k in range(j)), jnp.zeros(()))
            factor[i][j] = (matrix[i, j] - rest) / root
    return jnp.stack([jnp.stack(row) for row in factor]), ok


def solve_lower(factor: Any, b: Any) -> Any:
    """L^-1 b for a lower triangular L (m, m) and b (m,) or (m, k)."""
    out: list[Any] = []
    for i in range(factor.shape[0]):
        rest = sum((factor[i, k] * out[k] for k in range(i)), jnp.zeros_like(b[0]))
        out.append((b[i] - rest) / factor[i, i])
    return jnp.stack(out)


def solve_upper(factor: Any, b: Any) -> Any:
    """L^-T b for a lower triangular L (m, m) and b (m,) or (m, k)."""
    m = factor.shape[0]
    out: list[Any] = [None] * m
    for i in reversed(range(m)):
        rest = sum((factor[k, i] * out[k] for k in range(i + 1, m)), jnp.zeros_like(b[0]))
        out[i] = (b[i] - rest) / factor[i, i]
    return jnp.stack(out)


def solve_spd(matrix: Any, b: Any) -> tuple[Any, Any]:
    """x = M^-1 b for a symmetric positive definite M (m, m) and b (m,), by Cholesky, and whether
    M was positive definite (the Newton system's "singular" test)."""
    factor, ok = cholesky(matrix)
    return solve_upper(factor, solve_lower(factor, b)), ok


def frobenius(rows: Any) -> Any:
    """||J||_F of rows (m, n, 2)."""
    return jnp.sqrt(jnp.sum(rows * rows))
