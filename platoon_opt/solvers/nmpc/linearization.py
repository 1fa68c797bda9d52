"""The SQP's linearized residuals, dr/dU, kept as the Gauss-Newton Hessian splits (docs/nmpc.md,
Eq. 4.4): rows that involve one unit hold that unit's 2N entries alone, rows that couple units
hold all n 2N. Memory O(n N) for the first and O(c n N) for the c coupling rows, where the
dense dr/dU would be O(n^2 N) (at n = 50: 17.6 MB, of which 16 MB the zeros off the units'
blocks).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Linearization(NamedTuple):
    """dr/dU at the kept residual rows (``compiled.Chain``); columns unit-major (column
    i 2N + 2k + side: unit i's input ``side`` of interval k).

    Attributes:
        own_residual: (a,) the residuals of the rows that involve one unit, ordered by unit.
        own: (a, 2N) their derivatives with respect to their unit's inputs.
        own_unit: (a,) their units, nondecreasing.
        coupled_residual: (c,) the residuals of the rows that couple units (task, clearance).
        coupling: (c, n 2N) their derivatives.
    """

    own_residual: np.ndarray
    own: np.ndarray
    own_unit: np.ndarray
    coupled_residual: np.ndarray
    coupling: np.ndarray

    def with_coupling(self, residual: np.ndarray, coupling: np.ndarray) -> Linearization:
        """These rows and more coupling rows after them: ``residual`` (c',) and their
        derivatives ``coupling`` (c', n 2N)."""
        return self._replace(
            coupled_residual=np.concatenate((self.coupled_residual, residual)),
            coupling=np.concatenate((self.coupling, coupling)),
        )

    @property
    def block(self) -> int:
        """2N, the inputs of one unit."""
        return self.own.shape[1]

    @property
    def units(self) -> int:
        """n."""
        return self.coupling.shape[1] // self.block

    def gradient(self) -> np.ndarray:
        """(dr/dU)^T r, (n 2N,)."""
        block = self.block
        own = np.bincount(
            (self.own_unit[:, None] * block + np.arange(block)).ravel(),
            weights=(self.own * self.own_residual[:, None]).ravel(),
            minlength=self.units * block,
        )
        return own + self.coupling.T @ self.coupled_residual

    def product(self, x: np.ndarray) -> np.ndarray:
        """(dr/dU) x for x (n 2N,): the own rows' then the coupling rows', (a + c,)."""
        per_unit = x.reshape(self.units, self.block)
        own = np.einsum("ij,ij->i", self.own, per_unit[self.own_unit])
        return np.concatenate((own, self.coupling @ x))

    def blocks(self) -> np.ndarray:
        """(n, 2N, 2N): unit i's block of the Gauss-Newton Hessian, the sum over its own rows of
        their outer products (the coupling rows' part is ``coupling``'s low rank)."""
        blocks = np.zeros((self.units, self.block, self.block))
        starts = np.searchsorted(self.own_unit, np.arange(self.units + 1))
        for i in np.flatnonzero(np.diff(starts)):
            rows = self.own[starts[i] : starts[i + 1]]
            blocks[i] = rows.T @ rows
        return blocks
