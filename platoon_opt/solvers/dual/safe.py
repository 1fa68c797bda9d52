"""The dual's form of the safe sets (docs/safety.md, section 4; docs/dual.md, section 5): each
unit's achievable set cut by its barrier rows, projected exactly by ``SafeSets``, with the
generalized Jacobian of the projection in the form ``alpha I + beta f f^T`` that the Newton
method takes (``sets.Projection``), in plane coordinates (an identity frame):

* inside the set: I (alpha 1);
* inside one row's line, normal n: I - n n^T (alpha 1, beta -1, f = n);
* on the disk's circle, at w / |w| times the radius R: (R / |w|) (I - f f^T), f = w / |w|;
* at a corner: 0.

These sets are not symmetric about a centre direction, so the Python loop over the units of
small platoons (``unit_point``) does not apply: ``newton.solve_dual`` evaluates them with numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from platoon_opt.safe_sets import ARC, INTERIOR, LINE, SafeSets
from platoon_opt.solvers.dual.sets import TINY, Frame, Projection


@dataclass(frozen=True)
class SafeDualSets:
    """The safe sets of the dual's core units (``SafeSets``) with ``project`` and ``support`` as
    ``SectorSets`` has them."""

    safe: SafeSets
    frame: Frame

    @classmethod
    def of(cls, safe: SafeSets) -> SafeDualSets:
        n = safe.offsets.shape[0]
        return cls(safe, Frame(np.ones(n), np.zeros(n), np.zeros(1), float(safe.radius)))

    def project(self, wx: np.ndarray, wy: np.ndarray) -> Projection:
        """Project plane velocities (n,) x 2 onto the safe sets, with the Jacobian (see above)."""
        w = np.column_stack((wx, wy))
        point, face, row = self.safe.project_onto_faces(w)
        units = np.arange(point.shape[0])
        normal = self.safe.normals[units, row] if self.safe.normals.shape[1] else np.zeros_like(point)
        length = np.maximum(np.hypot(wx, wy), TINY)
        scale = self.safe.radius / length
        on_line, on_arc = face == LINE, face == ARC
        alpha = np.select([face == INTERIOR, on_line, on_arc], [1.0, 1.0, scale], 0.0)
        beta = np.select([on_line, on_arc], [-1.0, -scale], 0.0)
        fx = np.select([on_line, on_arc], [normal[:, 0], wx / length], 0.0)
        fy = np.select([on_line, on_arc], [normal[:, 1], wy / length], 0.0)
        return Projection(
            np.ascontiguousarray(point[:, 0]),
            np.ascontiguousarray(point[:, 1]),
            self.frame,
            np.ones(point.shape[0]),
            alpha,
            beta,
            fx,
            fy,
        )

    def support(self, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A point of each set maximizing ``g_i . v`` (n,) x 2, m/s."""
        point = self.safe.support(np.column_stack((gx, gy)))
        return np.ascontiguousarray(point[:, 0]), np.ascontiguousarray(point[:, 1])
