"""The dual's form of the safe sets (docs/safety.md, section 4; docs/dual.md, section 5): each
unit's achievable set cut by its barrier rows, projected exactly by ``SafeSets``, with the
generalized Jacobian of the projection in the form ``alpha I + beta f f^T`` that the Newton
method takes (``sets.Projection``), in plane coordinates:

* inside the set: I (alpha 1);
* inside one row's line, normal n: I - n n^T (alpha 1, beta -1, f = n);
* on the disk's circle, at w / |w| times the radius R: (R / |w|) (I - f f^T), f = w / |w|;
* at a corner: 0.

Array-API style, as ``SafeSets``' projection: the compiled Newton method takes these sets as it
takes the sectors and polygons. The rows are padded to a multiple of ``ROW_BLOCK`` (zero rows,
which no candidate uses) so that a compiled solve serves every step whose row count falls in the
same block.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from platoon_opt.arrays import namespace, pytree
from platoon_opt.safe_sets import ARC, INTERIOR, LINE, SafeSets
from platoon_opt.solvers.dual.sets import TINY, Projection

# The safe sets' rows are padded to a multiple of this: one compiled solve per block, not per count.
ROW_BLOCK = 4


@pytree(data=("safe",))
@dataclass(frozen=True)
class SafeDualSets:
    """The safe sets of the units (``SafeSets``) with ``project`` and ``support`` as
    ``SectorSets`` has them."""

    safe: SafeSets

    @classmethod
    def of(cls, safe: SafeSets) -> SafeDualSets:
        """``safe`` with its rows padded to a multiple of ``ROW_BLOCK`` (numpy, on the host). The
        projection treats every row alike: the count of the set's own rows (``fixed``, static)
        is set to 0, so that it does not tell compiled programs apart."""
        n, rows = safe.offsets.shape
        extra = -rows % ROW_BLOCK
        normals = np.concatenate((safe.normals, np.zeros((n, extra, 2))), axis=1)
        offsets = np.concatenate((safe.offsets, np.zeros((n, extra))), axis=1)
        return cls(replace(safe, normals=normals, offsets=offsets, fixed=0))

    @property
    def radius(self) -> Any:
        """The speed disk's radius, m/s."""
        return self.safe.radius

    def project(self, wx: Any, wy: Any) -> Projection:
        """Project plane velocities (n,) x 2 onto the safe sets, with the Jacobian (see above)."""
        xp = namespace(wx, self.safe.normals)
        point, face, row = self.safe.project_onto_faces(xp.stack((wx, wy), axis=1))
        normal = xp.take_along_axis(self.safe.normals, row[:, None, None], axis=1)[:, 0]
        length = xp.maximum(xp.hypot(wx, wy), TINY)
        scale = self.safe.radius / length
        on_line, on_arc = face == LINE, face == ARC
        alpha = xp.where(face == INTERIOR, 1.0, xp.where(on_line, 1.0, xp.where(on_arc, scale, 0.0)))
        beta = xp.where(on_line, -1.0, xp.where(on_arc, -scale, 0.0))
        fx = xp.where(on_line, normal[:, 0], xp.where(on_arc, wx / length, 0.0))
        fy = xp.where(on_line, normal[:, 1], xp.where(on_arc, wy / length, 0.0))
        return Projection(point[:, 0], point[:, 1], alpha, beta, fx, fy)

    def support(self, gx: Any, gy: Any) -> tuple[Any, Any]:
        """A point of each set maximizing ``g_i . v`` (n,) x 2, m/s."""
        point = self.safe.support(namespace(gx).stack((gx, gy), axis=1))
        return point[:, 0], point[:, 1]
