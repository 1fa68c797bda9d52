"""The sparsity patterns of a convex program's shape: which entries of the Hessian and the
constraint matrix are nonzero, fixed per ``Program.key`` so that a backend keeps its
factorization across steps while the numbers change (docs/programs.md, section 2).

Shapes: nf free units, m task components; N variables.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class Pattern:
    """A fixed CSC pattern from COO coordinates ``rows``, ``cols``; data come in COO order."""

    shape: tuple[int, int]
    rows: np.ndarray
    cols: np.ndarray
    order: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray

    @classmethod
    def of(cls, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> Pattern:
        order = np.lexsort((rows, cols))
        indptr = np.zeros(shape[1] + 1, dtype=np.int64)
        np.cumsum(np.bincount(cols, minlength=shape[1]), out=indptr[1:])
        return cls(shape, rows, cols, order, rows[order].astype(np.int64), indptr)

    def values(self, data: np.ndarray) -> np.ndarray:
        """The CSC data array (what a backend's in-place update takes)."""
        return data[self.order]

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((self.values(data), self.indices, self.indptr), shape=self.shape)

    def apply(self, data: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The matrix times x (shape[1],), without building the matrix."""
        return np.bincount(self.rows, weights=data * x[self.cols], minlength=self.shape[0])


@dataclass(frozen=True)
class Structure:
    """Patterns of one program shape (see ``structure``)."""

    variables: int
    velocity_columns: np.ndarray  # (nf, 2): the velocity handed to each free unit
    achievable_columns: np.ndarray  # (nf, 2): its achievable part (the same for achievable-first)
    hessian: Pattern  # full symmetric
    hessian_upper: Pattern
    hessian_upper_entries: np.ndarray  # which COO entries of ``hessian`` are in the upper triangle
    constraints: Pattern


@lru_cache(maxsize=32)
def structure(reading: str, stage: str, free: int, per_unit: int, m: int, task_rows: int) -> Structure:
    """The sparsity patterns for ``free`` units with ``per_unit`` linear rows each, an m-row task
    and ``task_rows`` rows on the task (equalities, or the two sides of the stage-2 band). COO
    order (the order of the data built in ``build``):

    * Hessian: achievable-first, the diagonal; task-exact, per unit and coordinate
      (a, a), (c, c), (a, c), (c, a).
    * Constraints: the task rows (row-major over the block, then the -I of ``s``), then the
      linear rows of each unit (x entry, y entry of each row).
    """
    units = np.arange(free)
    if reading == "achievable-first":
        task_variables = m if stage != "deviation" else 0
        variables = 2 * free + task_variables
        velocity = np.column_stack((2 * units, 2 * units + 1))
        achievable = velocity
        h_rows = h_cols = np.arange(variables)
        eq_rows = np.repeat(np.arange(task_rows), 2 * free)
        eq_cols = np.tile(np.arange(2 * free), task_rows)
        if task_variables:
            eq_rows = np.concatenate((eq_rows, np.arange(m)))
            eq_cols = np.concatenate((eq_cols, 2 * free + np.arange(m)))
    else:
        variables = 4 * free
        velocity = np.column_stack((4 * units, 4 * units + 1))
        achievable = velocity + 2
        a, c = velocity.ravel(), achievable.ravel()
        h_rows = np.concatenate((a, c, a, c))
        h_cols = np.concatenate((a, c, c, a))
        eq_rows = np.repeat(np.arange(task_rows), 2 * free)
        eq_cols = np.tile(a, task_rows)
    lin_rows = task_rows + np.repeat(np.arange(free * per_unit), 2)
    lin_cols = np.repeat(achievable, per_unit, axis=0).ravel()
    upper = h_rows <= h_cols
    rows_total = task_rows + free * per_unit
    return Structure(
        variables=variables,
        velocity_columns=velocity,
        achievable_columns=achievable,
        hessian=Pattern.of(h_rows, h_cols, (variables, variables)),
        hessian_upper=Pattern.of(h_rows[upper], h_cols[upper], (variables, variables)),
        hessian_upper_entries=upper,
        constraints=Pattern.of(
            np.concatenate((eq_rows, lin_rows)), np.concatenate((eq_cols, lin_cols)), (rows_total, variables)
        ),
    )
