"""Random obstacle fields (``[obstacle_field]``, docs/scenarios.md), drawn per seed on the host.

A field is ``count`` circles, each radius uniform in ``radius_range`` and each centre uniform in
the part of ``region`` where the whole circle lies inside it, drawn one after another by rejection
from the seed's generator: a candidate is kept if its edge keeps ``path_gap`` from the target's
path (if given), ``start_gap`` from every unit's initial position and ``obstacle_gap`` from every
obstacle already there (the file's fixed ones, after their jitter, and the field's). The count is
the same for every seed (the engine batches seeds of one shape), so a seed whose obstacle finds no
place in ``TRIES`` candidates is refused, naming the keys.

The distance to the path is measured to its outline (``paths.Path.outline``), a polyline with a
margin that bounds how far the path strays from it; the margin is added to the gap, so the gap
holds to the path itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# Candidates per obstacle before the seed is refused, drawn and tested ``_BATCH`` at a time (the
# first that fits is kept).
TRIES = 1000
_BATCH = 50


def segment_distance(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance (B,) m from each of ``points`` (B, 2) to the polyline ``polyline`` (M, 2) m."""
    if polyline.shape[0] == 1:
        return np.linalg.norm(points - polyline[0], axis=1)
    a, d = polyline[:-1], np.diff(polyline, axis=0)
    length = np.maximum(np.sum(d * d, axis=1), 1e-300)
    along = np.clip(np.einsum("bmk,mk->bm", points[:, None, :] - a, d) / length, 0.0, 1.0)
    nearest = a + along[..., None] * d
    return np.min(np.linalg.norm(points[:, None, :] - nearest, axis=2), axis=1)


@dataclass(frozen=True)
class ObstacleField:
    """A field as read from the file (m throughout).

    Attributes:
        count: obstacles per seed.
        radius_range: (2,) least and largest radius.
        region: (4,) x_min, y_min, x_max, y_max of the rectangle the obstacles lie in.
        path_gap: least gap between an obstacle and the path, or None (obstacles may cross it).
        start_gap: least gap between an obstacle and a unit's initial position.
        obstacle_gap: least gap between two obstacles.
        outline, margin: the path's outline (M, 2) and its margin (``paths.Path.outline``).
    """

    count: int
    radius_range: np.ndarray
    region: np.ndarray
    path_gap: float | None
    start_gap: float
    obstacle_gap: float
    outline: np.ndarray
    margin: float

    def draw(
        self, rng: np.random.Generator, units: np.ndarray, centers: np.ndarray, radii: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | int:
        """The field's centres (count, 2) and radii (count,) drawn from ``rng``, clear of the units'
        initial positions ``units`` (n, 2) and of the obstacles ``centers`` (k, 2), ``radii``
        (k,) already placed; or the index of the first obstacle that found no place."""
        low, high = self.region[:2], self.region[2:]
        start = cKDTree(units)
        placed_c, placed_r = [*centers], [*radii]
        for i in range(self.count):
            for _ in range(TRIES // _BATCH):
                r = rng.uniform(self.radius_range[0], self.radius_range[1], _BATCH)
                c = rng.uniform(low + r[:, None], high - r[:, None])
                fits = start.query(c)[0] >= r + self.start_gap
                if placed_c:
                    gaps = np.linalg.norm(c[:, None, :] - np.array(placed_c)[None], axis=2) - np.array(
                        placed_r
                    )
                    fits &= np.min(gaps, axis=1) >= r + self.obstacle_gap
                if self.path_gap is not None and fits.any():
                    fits &= segment_distance(c, self.outline) - self.margin >= r + self.path_gap
                if fits.any():
                    first = int(np.argmax(fits))
                    placed_c.append(c[first])
                    placed_r.append(r[first])
                    break
            else:
                return i
        return np.array(placed_c[len(centers) :]).reshape(-1, 2), np.array(placed_r[len(radii) :])
