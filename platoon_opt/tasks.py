"""Platoon tasks f(q): value, Jacobian, and O(n) pseudoinverse and null-space projector.

A task maps the tip positions (n, 2) to m numbers. Its Jacobian is stored as ``rows``
of shape (m, n, 2) (row k, unit i, axis x/y), which is O(n) memory for a fixed m; the
m x m Gram matrix ``J J^T`` then costs O(m^2 n), and ``J^+ u = J^T (J J^T)^-1 u`` and
``N v = v - J^+ J v`` never form a 2n x 2n matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


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
    """

    rows: np.ndarray
    rcond: float = 1e-6
    orthogonal_gram: np.ndarray | None = None
    _flat: np.ndarray = field(init=False, repr=False)
    _gram_inverse: np.ndarray = field(init=False, repr=False)
    _vectors: np.ndarray | None = field(init=False, repr=False)
    _regular: np.ndarray = field(init=False, repr=False)
    degenerate: int = field(init=False)

    def __post_init__(self) -> None:
        # J as an m x 2n matrix over q = [x_1, y_1, x_2, ...]: products with it are single matmuls
        # (einsum's overhead dominated the step at small n).
        object.__setattr__(self, "_flat", np.ascontiguousarray(self.rows).reshape(self.rows.shape[0], -1))
        if self.orthogonal_gram is None:
            eigenvalues, vectors = np.linalg.eigh(np.einsum("kij,lij->kl", self.rows, self.rows))
        else:
            eigenvalues, vectors = self.orthogonal_gram, None
        floor = self.rcond * max(float(eigenvalues.max(initial=0.0)), np.finfo(float).tiny)
        regular = eigenvalues >= floor
        damped = np.maximum(eigenvalues, 0) / floor**2
        inverse = np.where(regular, 1.0 / np.maximum(eigenvalues, floor), damped)
        gram_inverse = np.diag(inverse) if vectors is None else (vectors * inverse) @ vectors.T
        object.__setattr__(self, "_gram_inverse", gram_inverse)
        object.__setattr__(self, "_vectors", vectors)
        object.__setattr__(self, "_regular", regular)
        object.__setattr__(self, "degenerate", int(np.count_nonzero(~regular)))

    def regular_directions(self) -> np.ndarray:
        """Orthonormal eigenvectors E (m, r) of J J^T that are not degenerate: ``E^T J`` has
        full row rank (what an equality ``J v = u`` can keep)."""
        if self._vectors is None:
            return np.eye(self._regular.shape[0])[:, self._regular]
        return self._vectors[:, self._regular]

    @property
    def shape(self) -> tuple[int, int]:
        """(m, 2n), the shape of J as a matrix over q = [x_1..x_n, y_1..y_n]."""
        m, n, _ = self.rows.shape
        return m, 2 * n

    @property
    def gram(self) -> np.ndarray:
        """J J^T, shape (m, m)."""
        return np.einsum("kij,lij->kl", self.rows, self.rows)

    @property
    def gram_inverse(self) -> np.ndarray:
        """(J J^T)^-1 with the degenerate directions damped, shape (m, m)."""
        return self._gram_inverse

    def apply(self, velocity: np.ndarray) -> np.ndarray:
        """J v for velocities (n, 2): shape (m,)."""
        return self._flat @ velocity.reshape(-1)

    def apply_transpose(self, weights: np.ndarray) -> np.ndarray:
        """J^T w for task weights (m,): velocities (n, 2)."""
        return (weights @ self._flat).reshape(-1, 2)

    def pinv_apply(self, task_velocity: np.ndarray) -> np.ndarray:
        """J^+ u for a task velocity (m,): velocities (n, 2)."""
        return self.apply_transpose(self._gram_inverse @ task_velocity)

    def null_project(self, velocity: np.ndarray) -> np.ndarray:
        """N v = v - J^+ J v for velocities (n, 2)."""
        return velocity - self.pinv_apply(self.apply(velocity))

    def to_dense(self) -> np.ndarray:
        """J as a dense (m, 2n) matrix over q = [x..., y...]; for tests and small n only."""
        return np.concatenate((self.rows[:, :, 0], self.rows[:, :, 1]), axis=1)


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

    Units: m, m^2, m, m^2. J J^T = diag(1/n, 4 var_x/(n-1), 1/n, 4 var_y/(n-1)).
    """

    rcond: float = 1e-6
    names: tuple[str, ...] = ("mean_x", "var_x", "mean_y", "var_y")

    def value(self, positions: np.ndarray, t: float = 0.0) -> np.ndarray:
        n = positions.shape[0]
        mean = positions.sum(axis=0) / n
        centred = positions - mean
        var = np.einsum("ij,ij->j", centred, centred) / (n - 1)
        return np.array([mean[0], var[0], mean[1], var[1]])

    def jacobian(self, positions: np.ndarray, t: float = 0.0) -> TaskJacobian:
        n = positions.shape[0]
        centred = positions - positions.sum(axis=0) / n
        rows = np.zeros((4, n, 2))
        rows[0, :, 0] = 1.0 / n
        rows[1, :, 0] = 2.0 * centred[:, 0] / (n - 1)
        rows[2, :, 1] = 1.0 / n
        rows[3, :, 1] = 2.0 * centred[:, 1] / (n - 1)
        # The mean and variance rows are orthogonal: sum_i (x_i - mean) = 0.
        squares = np.einsum("ij,ij->j", centred, centred)
        gram = np.array([1.0 / n, 4.0 * squares[0] / (n - 1) ** 2, 1.0 / n, 4.0 * squares[1] / (n - 1) ** 2])
        return TaskJacobian(rows, self.rcond, orthogonal_gram=gram)

    def time_derivative(self, positions: np.ndarray, t: float = 0.0) -> np.ndarray:
        return np.zeros(4)
