"""Secondary task: obstacle repulsion (Eq. 6) and inter-unit repulsion (Eq. 7).

Memory is O(n): the nearest neighbour comes from a k-d tree query with a cutoff, and
obstacles are scanned one at a time (their number k is small), keeping a running nearest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from platoon_opt.validation import finite_array, positive

# Distances are floored here so that 1/d stays finite when a unit touches an obstacle
# or another unit (m).
MIN_DISTANCE = 1e-2
# Unit-obstacle pairs handled at once by CircularObstacles.nearest.
_CHUNK = 1 << 16
# Up to this many units the nearest neighbour comes from all pairs (a bounded n x n block,
# several times faster than building a k-d tree for the paper's 8 units).
BRUTE_FORCE_UNITS = 32


@dataclass(frozen=True)
class CircularObstacles:
    """k circular obstacles: centres (k, 2) in m, radii (k,) in m (> 0). k may be 0."""

    centers: np.ndarray
    radii: np.ndarray

    def __post_init__(self) -> None:
        centers = finite_array("obstacles.centers", np.reshape(self.centers, (-1, 2)), (None, 2))
        radii = finite_array("obstacles.radii", np.reshape(self.radii, (-1,)), (centers.shape[0],))
        if np.any(radii <= 0):
            raise ValueError(f"obstacles.radii must be > 0, got {radii!r}")
        object.__setattr__(self, "centers", centers)
        object.__setattr__(self, "radii", radii)

    @classmethod
    def none(cls) -> CircularObstacles:
        """No obstacles."""
        return cls(np.zeros((0, 2)), np.zeros(0))

    def __len__(self) -> int:
        return self.radii.shape[0]

    def nearest(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance to the nearest obstacle surface (n,), m (negative inside), and the
        unit vector from that obstacle's centre to each unit (n, 2); inf and zeros if k = 0.

        Units are taken in chunks of at most ``_CHUNK / k`` so that memory stays O(n).
        """
        n, k = positions.shape[0], len(self)
        distance, away = np.full(n, np.inf), np.zeros((n, 2))
        if k == 0:
            return distance, away
        step = max(1, _CHUNK // k)
        for start in range(0, n, step):
            chunk = slice(start, start + step)
            offset = positions[chunk, None, :] - self.centers[None, :, :]
            length = np.hypot(offset[..., 0], offset[..., 1])
            nearest = np.argmin(length - self.radii, axis=1)
            rows = np.arange(offset.shape[0])
            distance[chunk] = length[rows, nearest] - self.radii[nearest]
            # A unit exactly at a centre is pushed along +x.
            along = length[rows, nearest]
            away[chunk] = np.where(
                (along > 0)[:, None], offset[rows, nearest] / np.maximum(along, 1e-300)[:, None], [1.0, 0.0]
            )
        return distance, away


@dataclass(frozen=True)
class AvoidanceParams:
    """Parameters of Eqs. 6 and 7.

    Attributes:
        d_minr: inter-unit activation distance (m); precedence below d_minr / 8.
        d_mino: obstacle activation distance (m); precedence below d_mino / 4.
        ahead_reference: "heading" tests "obstacle ahead" (|theta_io| < pi/2) against the
            body heading, as the paper words it; "travel" against the direction of travel
            (heading + steering, reversed when backing).
    """

    d_minr: float = 1.0
    d_mino: float = 3.0
    ahead_reference: str = "heading"

    def __post_init__(self) -> None:
        positive("avoidance.d_minr", self.d_minr)
        positive("avoidance.d_mino", self.d_mino)
        if self.ahead_reference not in ("heading", "travel"):
            raise ValueError(
                f"avoidance.ahead_reference must be 'heading' or 'travel', got {self.ahead_reference!r}"
            )


@dataclass(frozen=True)
class Repulsion:
    """The secondary velocity and the paper's precedence flags for one step.

    Attributes:
        velocity: v_repo + v_repr, shape (n, 2), m/s.
        obstacle_distance: signed distance to the nearest obstacle surface (n,), m.
        unit_distance: distance to the nearest other unit within d_minr (n,), m (inf beyond).
        exempt: units whose avoidance takes precedence (n,) bool: within d_mino/4 of an
            obstacle or d_minr/8 of another unit.
    """

    velocity: np.ndarray
    obstacle_distance: np.ndarray
    unit_distance: np.ndarray
    exempt: np.ndarray


def obstacle_repulsion(
    positions: np.ndarray,
    reference_heading: np.ndarray,
    obstacles: CircularObstacles,
    d_mino: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 6: ``cos(theta_io) (1/d - 1/d_mino)`` away from the nearest obstacle, active when
    the obstacle is within d_mino and ahead (|theta_io| < pi/2).

    theta_io is the angle between the reference heading and the direction from the unit to
    the nearest obstacle point (for a circle, toward its centre): an obstacle straight ahead
    repels fully, one abeam not at all, one behind (already passed) not at all.

    Returns:
        velocity (n, 2) in m/s and the signed obstacle distance (n,) in m.
    """
    distance, away = obstacles.nearest(positions)
    # cos(theta_io) as the dot product of the heading with the direction toward the obstacle;
    # "ahead" (|theta_io| < pi/2) is cos(theta_io) > 0.
    cosine = -(away[:, 0] * np.cos(reference_heading) + away[:, 1] * np.sin(reference_heading))
    active = (distance < d_mino) & (cosine > 0)
    magnitude = np.where(active, cosine * (1.0 / np.maximum(distance, MIN_DISTANCE) - 1.0 / d_mino), 0.0)
    return magnitude[:, None] * away, distance


def nearest_unit(positions: np.ndarray, cutoff: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance (n,) to each unit's nearest other unit and its index (n,); inf and n beyond
    ``cutoff``. Ties go to the lower index."""
    n = positions.shape[0]
    if n <= BRUTE_FORCE_UNITS:
        offset = positions[:, None, :] - positions[None, :, :]
        length = np.hypot(offset[..., 0], offset[..., 1])
        np.fill_diagonal(length, np.inf)
        index = np.argmin(length, axis=1)
        distance = length[np.arange(n), index]
        beyond = distance >= cutoff
        return np.where(beyond, np.inf, distance), np.where(beyond, n, index)
    tree = cKDTree(positions)
    # Queries in the tree's own order (the answers do not depend on it) stay in cache: at
    # n = 100,000 about twice as fast as in the units' order.
    order = tree.indices
    found, nearest = tree.query(positions[order], k=2, distance_upper_bound=cutoff)
    distance, index = np.empty(n), np.empty(n, dtype=nearest.dtype)
    distance[order], index[order] = found[:, 1], nearest[:, 1]
    return distance, index


def unit_repulsion(positions: np.ndarray, d_minr: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 7: ``(1/d - 1/d_minr)`` away from the nearest other unit within d_minr.

    Coincident units (distance 0) are pushed apart along deterministic directions: unit i
    along the angle i * golden angle.

    Returns:
        velocity (n, 2) in m/s and the nearest-unit distance (n,) in m (inf beyond d_minr).
    """
    n = positions.shape[0]
    distance, index = nearest_unit(positions, d_minr)
    active = np.isfinite(distance)
    neighbour = positions[np.where(active, index, np.arange(n))]
    offset = positions - neighbour
    length = np.hypot(offset[:, 0], offset[:, 1])
    away = offset / np.maximum(length, 1e-300)[:, None]
    coincident = np.flatnonzero(active & (length == 0))
    if coincident.size:
        golden = coincident * np.pi * (3 - np.sqrt(5))
        away[coincident] = np.column_stack((np.cos(golden), np.sin(golden)))
    magnitude = 1.0 / np.maximum(np.where(active, distance, d_minr), MIN_DISTANCE) - 1.0 / d_minr
    return np.where(active[:, None], magnitude[:, None] * away, 0.0), distance


def repulsion(
    positions: np.ndarray,
    reference_heading: np.ndarray,
    obstacles: CircularObstacles,
    params: AvoidanceParams,
) -> Repulsion:
    """The secondary velocity v = v_repo + v_repr and the precedence flags."""
    from_obstacles, obstacle_distance = obstacle_repulsion(
        positions, reference_heading, obstacles, params.d_mino
    )
    from_units, unit_distance = unit_repulsion(positions, params.d_minr)
    exempt = (obstacle_distance <= params.d_mino / 4) | (unit_distance <= params.d_minr / 8)
    return Repulsion(from_obstacles + from_units, obstacle_distance, unit_distance, exempt)
