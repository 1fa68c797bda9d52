"""Platoon tasks f(q): value, Jacobian, and O(n) pseudoinverse and null-space projector.

A task maps the tip positions (n, 2) to m numbers. Its Jacobian is stored as ``rows``
of shape (m, n, 2) (row k, unit i, axis x/y), which is O(n) memory for a fixed m; the
m x m Gram matrix ``J J^T`` then costs O(m^2 n), and ``J^+ u = J^T (J J^T)^-1 u`` and
``N v = v - J^+ J v`` never form a 2n x 2n matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from platoon_opt.arrays import namespace, pytree


@pytree(data=("rows", "gram_inverse", "vectors", "regular", "orthogonal_gram"), static=("rcond",))
@dataclass(frozen=True)
class TaskJacobian:
    """J(q) as rows (m, n, 2), with a pseudoinverse that is safe when a row vanishes.

    Eigenvalues ``s`` of ``J J^T`` below ``rcond * max(s)`` are treated as degenerate: the
    inverse ``1/s`` is replaced by ``s / s_min^2``, continuous at ``s_min`` and going to
    zero with ``s``, so a vanishing row (a variance near 0) gives a bounded velocity
    instead of an unbounded one. ``degenerate`` counts such directions.

    A task whose rows are orthogonal passes ``orthogonal_gram``, the diagonal of ``J J^T``
    (m,) that it knows in closed form; the eigenvectors are then the axes and no
    eigendecomposition runs (at small n it would cost more than the rest of the step).

    Build it with ``TaskJacobian.of``. Its arrays are numpy or JAX (inside the engine); the
    products below work on either.

    Attributes:
        rows: J (m, n, 2).
        gram_inverse: (J J^T)^-1 with the degenerate directions damped (m, m).
        vectors: orthonormal eigenvectors of J J^T as columns (m, m) (the identity for an
            orthogonal task).
        regular: which eigenvectors are not degenerate (m,) bool.
        orthogonal_gram: the diagonal of J J^T (m,) of an orthogonal task, else None.
        rcond: the relative threshold of a degenerate direction.
    """

    rows: Any
    gram_inverse: Any
    vectors: Any
    regular: Any
    orthogonal_gram: Any
    rcond: float

    @classmethod
    def of(cls, rows: Any, rcond: float = 1e-6, orthogonal_gram: Any = None) -> TaskJacobian:
        """The Jacobian of rows (m, n, 2), numpy or JAX; ``orthogonal_gram`` (m,) when the rows
        are orthogonal and their Gram diagonal is known."""
        xp = namespace(rows, orthogonal_gram)
        m = rows.shape[0]
        if orthogonal_gram is None:
            eigenvalues, vectors = xp.linalg.eigh(xp.einsum("kij,lij->kl", rows, rows))
        else:
            eigenvalues, vectors = orthogonal_gram, xp.eye(m)
        floor = rcond * xp.maximum(xp.max(eigenvalues, initial=0.0), np.finfo(float).tiny)
        regular = eigenvalues >= floor
        damped = xp.maximum(eigenvalues, 0) / floor**2
        inverse = xp.where(regular, 1.0 / xp.maximum(eigenvalues, floor), damped)
        gram_inverse = xp.diag(inverse) if orthogonal_gram is not None else (vectors * inverse) @ vectors.T
        return cls(rows, gram_inverse, vectors, regular, orthogonal_gram, rcond)

    @property
    def degenerate(self) -> Any:
        """Directions of J J^T that were damped (a count; an int on the host)."""
        return namespace(self.regular).sum(~self.regular)

    def regular_directions(self) -> np.ndarray:
        """Orthonormal eigenvectors E (m, r) of J J^T that are not degenerate: ``E^T J`` has
        full row rank (what an equality ``J v = u`` can keep). Host only (r varies)."""
        return np.asarray(self.vectors)[:, np.asarray(self.regular)]

    @property
    def shape(self) -> tuple[int, int]:
        """(m, 2n), the shape of J as a matrix over q = [x_1..x_n, y_1..y_n]."""
        m, n, _ = self.rows.shape
        return m, 2 * n

    @property
    def gram(self) -> Any:
        """J J^T, shape (m, m)."""
        return namespace(self.rows).einsum("kij,lij->kl", self.rows, self.rows)

    def apply(self, velocity: Any) -> Any:
        """J v for velocities (n, 2): shape (m,)."""
        return self.rows.reshape(self.rows.shape[0], -1) @ velocity.reshape(-1)

    def apply_transpose(self, weights: Any) -> Any:
        """J^T w for task weights (m,): velocities (n, 2)."""
        return (weights @ self.rows.reshape(self.rows.shape[0], -1)).reshape(-1, 2)

    def pinv_apply(self, task_velocity: Any) -> Any:
        """J^+ u for a task velocity (m,): velocities (n, 2)."""
        return self.apply_transpose(self.gram_inverse @ task_velocity)

    def null_project(self, velocity: Any) -> Any:
        """N v = v - J^+ J v for velocities (n, 2)."""
        return velocity - self.pinv_apply(self.apply(velocity))

    def to_dense(self) -> np.ndarray:
        """J as a dense (m, 2n) matrix over q = [x..., y...]; for tests and small n only."""
        rows = np.asarray(self.rows)
        return np.concatenate((rows[:, :, 0], rows[:, :, 1]), axis=1)


def _mean_variance(positions: Any) -> tuple[Any, Any]:
    """Eq. 4's value (4,) at positions (n, 2), and the positions less their mean (n, 2)."""
    xp = namespace(positions)
    n = positions.shape[0]
    mean = positions.sum(axis=0) / n
    centred = positions - mean
    var = xp.einsum("ij,ij->j", centred, centred) / (n - 1)
    return xp.stack((mean[0], var[0], mean[1], var[1])), centred


def _mean_variance_rows(centred: Any) -> Any:
    """The rows (4, n, 2) of Eq. 4's Jacobian at positions whose mean is subtracted, (n, 2)."""
    xp = namespace(centred)
    n = centred.shape[0]
    zero, mean = xp.zeros(n), xp.full(n, 1.0 / n)
    return xp.stack(
        (
            xp.stack((mean, zero), axis=1),
            xp.stack((2.0 * centred[:, 0] / (n - 1), zero), axis=1),
            xp.stack((zero, mean), axis=1),
            xp.stack((zero, 2.0 * centred[:, 1] / (n - 1)), axis=1),
        )
    )


@runtime_checkable
class Task(Protocol):
    """A platoon-level function f(q, t) with m components."""

    @property
    def names(self) -> tuple[str, ...]:
        """The m component names, e.g. ("mean_x", "var_x", "mean_y", "var_y")."""
        ...

    def value(self, positions: np.ndarray, t: float = 0.0) -> np.ndarray:
        """f(q, t), shape (m,), for tip positions (n, 2)."""
        ...

    def jacobian(self, positions: np.ndarray, t: float = 0.0) -> TaskJacobian:
        """df/dq at (q, t)."""
        ...

    def time_derivative(self, positions: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Partial df/dt at (q, t), shape (m,); zero for a task without explicit time."""
        ...


@dataclass(frozen=True)
class MeanVarianceTask:
    """Eq. 4: f = [mu_x, var_x, mu_y, var_y] with the unbiased (n - 1) variance.

    Units: m, m^2, m, m^2. J J^T = diag(1/n, 4 var_x/(n-1), 1/n, 4 var_y/(n-1)). Its methods take
    numpy or JAX positions (inside the engine, traced ones).
    """

    rcond: float = 1e-6
    names: tuple[str, ...] = ("mean_x", "var_x", "mean_y", "var_y")
    # Its methods run on traced arrays: the compiled engine poses its problems (problem.traceable).
    traceable: ClassVar[bool] = True

    def value(self, positions: Any, t: Any = 0.0) -> Any:
        return _mean_variance(positions)[0]

    def jacobian(self, positions: Any, t: Any = 0.0) -> TaskJacobian:
        xp = namespace(positions)
        n = positions.shape[0]
        centred = positions - positions.sum(axis=0) / n
        rows = _mean_variance_rows(centred)
        # The mean and variance rows are orthogonal: sum_i (x_i - mean) = 0.
        squares = xp.einsum("ij,ij->j", centred, centred)
        gram = xp.stack(
            (
                xp.asarray(1.0 / n),
                4.0 * squares[0] / (n - 1) ** 2,
                xp.asarray(1.0 / n),
                4.0 * squares[1] / (n - 1) ** 2,
            )
        )
        return TaskJacobian.of(rows, self.rcond, orthogonal_gram=gram)

    def time_derivative(self, positions: Any, t: Any = 0.0) -> Any:
        return namespace(positions).zeros(4)


@dataclass(frozen=True)
class CovarianceTask:
    """Eq. 4 plus the sample covariance: f = [mu_x, var_x, mu_y, var_y, cov_xy], unbiased (n - 1).

    Units: m, m^2, m, m^2, m^2. The covariance matrix [[var_x, cov_xy], [cov_xy, var_y]] is the
    formation's spread ellipse, so commanding cov_xy with the variances commands its orientation,
    0.5 atan2(2 cov_xy, var_x - var_y). The cov_xy row, d cov_xy / d(x_i, y_i) =
    (y_i - mu_y, x_i - mu_x) / (n - 1), is not orthogonal to the variance rows, so ``J J^T`` (5 x 5)
    is decomposed in full. The allocators' floor builds the same task by CasADi's automatic
    differentiation (tested equal). Its methods take numpy or JAX positions.
    """

    rcond: float = 1e-6
    names: tuple[str, ...] = ("mean_x", "var_x", "mean_y", "var_y", "cov_xy")
    traceable: ClassVar[bool] = True

    def value(self, positions: Any, t: Any = 0.0) -> Any:
        values, centred = _mean_variance(positions)
        cov = centred[:, 0] @ centred[:, 1] / (positions.shape[0] - 1)
        return namespace(positions).concatenate((values, cov[None]))

    def jacobian(self, positions: Any, t: Any = 0.0) -> TaskJacobian:
        xp = namespace(positions)
        n = positions.shape[0]
        centred = positions - positions.sum(axis=0) / n
        rows = xp.concatenate((_mean_variance_rows(centred), centred[None, :, ::-1] / (n - 1)))
        return TaskJacobian.of(rows, self.rcond)

    def time_derivative(self, positions: Any, t: Any = 0.0) -> Any:
        return namespace(positions).zeros(5)
