"""The SQP's clearance rows (docs/nmpc.md, Eq. 2.7), for the pairs of units that can meet.

A clearance row is zero unless its two units are closer than ``unit_clearance``. A unit's tip
moves at most v_max h over an interval of h s, so two units farther apart now than
``unit_clearance + 2 v_max N h`` cannot come within it over the horizon: their rows are zero,
with a zero derivative, at every input within the bounds, and the SQP evaluates only the rows
of the other pairs (found by a k-d tree, O(n log n)). The rows are the same as the model's
(``residuals.residuals`` builds all n (n - 1) N / 2 of them for IPOPT); their number grows
with the neighbours a unit has, not with n^2 (docs/nmpc.md, section 9).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from platoon_opt.solvers.nmpc.residuals import DISTANCE_EPSILON, ERROR_SCALE


@dataclass(frozen=True)
class Clearance:
    """The clearance rows of one horizon.

    Attributes:
        distance: ``unit_clearance`` (m): rows are nonzero for tips closer than it.
        scale: sqrt(clearance_weight / N) / ERROR_SCALE, the factor of each row (1/m).
        duration: the horizon N h (s).
    """

    distance: float
    scale: float
    duration: float

    @classmethod
    def of(cls, unit_clearance: float, clearance_weight: float, intervals: int, interval: float) -> Clearance:
        """For ``intervals`` intervals of ``interval`` s."""
        scale = math.sqrt(clearance_weight / intervals) / ERROR_SCALE
        return cls(unit_clearance, scale, intervals * interval)

    def near(self, positions: np.ndarray, max_speed: float) -> PairRows:
        """The rows of the pairs of units at ``positions`` (n, 2), m, that can come closer than
        ``distance`` within the horizon at speeds of at most ``max_speed`` (m/s)."""
        reach = self.distance + 2 * max_speed * self.duration
        found = cKDTree(positions).query_pairs(reach, output_type="ndarray").astype(np.intp)
        found = np.sort(found.reshape(-1, 2), axis=1)
        return PairRows(self.distance, self.scale, found[np.lexsort((found[:, 1], found[:, 0]))])


@dataclass(frozen=True)
class PairRows:
    """The clearance rows of some pairs of units at every node of the horizon, node-major.

    Attributes:
        distance, scale: as ``Clearance``'s.
        pairs: (P, 2) the units (i, j), i < j, in lexicographic order.
    """

    distance: float
    scale: float
    pairs: np.ndarray

    def residual(self, states: np.ndarray) -> np.ndarray:
        """The rows (N P,) for node states (N, n, 4)."""
        return self._rows(states)[0].ravel()

    def linearization(self, states: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nonzero rows (c,) and their derivatives in the inputs (c, n 2N), columns
        unit-major as ``compiled.Chain``'s: d row / d U = d row / d p_i G[k, :, i] +
        d row / d p_j G[k, :, j] for node k (index k of ``states``) and the pair's tips p_i,
        p_j, with G (N, N, n, 4, 2) the states' sensitivities (docs/nmpc.md, Eq. 4.1)."""
        N, n = states.shape[:2]
        rows, offset, distance = self._rows(states)
        node, pair = np.nonzero(rows)
        first, second = self.pairs[pair, 0], self.pairs[pair, 1]
        # d row / d p_i = -scale (p_i - p_j) / |p_i - p_j| inside the clearance; d / d p_j its negative.
        gradient = -self.scale * offset[node, pair] / distance[node, pair, None]
        coupling = np.zeros((node.size, n, N, 2))
        live = np.arange(node.size)
        coupling[live, first] = np.einsum("rc,rlcs->rls", gradient, G[node, :, first, :2])
        coupling[live, second] = -np.einsum("rc,rlcs->rls", gradient, G[node, :, second, :2])
        return rows[node, pair], coupling.reshape(node.size, n * 2 * N)

    def _rows(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each node's rows (N, P), the tips' offsets p_i - p_j (N, P, 2) and distances (N, P)."""
        tips = states[:, :, :2]
        offset = tips[:, self.pairs[:, 0]] - tips[:, self.pairs[:, 1]]
        distance = np.sqrt(offset[..., 0] ** 2 + offset[..., 1] ** 2 + DISTANCE_EPSILON)
        return self.scale * np.maximum(0.0, self.distance - distance), offset, distance
