"""Secondary task: obstacle repulsion (Eq. 6) and inter-unit repulsion (Eq. 7).

Written once for numpy and ``jax.numpy`` (``platoon_opt.arrays.namespace``). Memory is O(n):
obstacles are scanned one at a time (their number k is small), keeping a running nearest, and the
nearest other unit comes from all pairs for a few units or from a cell list
(``platoon_opt.neighbours``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from platoon_opt.arrays import namespace, pytree
from platoon_opt.neighbours import nearest_unit
from platoon_opt.validation import finite_array, positive

# Distances are floored here so that 1/d stays finite when a unit touches an obstacle
# or another unit (m).
MIN_DISTANCE = 1e-2
# Unit-obstacle pairs taken at once by ``CircularObstacles.nearest`` (beyond, one obstacle at a time).
ALL_AT_ONCE = 1 << 16
# A unit exactly at coincident positions is pushed along i times this angle (rad).
GOLDEN_ANGLE = float(np.pi * (3 - np.sqrt(5)))


@pytree(data=("centers", "radii"))
@dataclass(frozen=True)
class CircularObstacles:
    """k circular obstacles: centres (k, 2) in m, radii (k,) in m (> 0). k may be 0."""

    centers: Any
    radii: Any

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

    def nearest(self, positions: Any) -> tuple[Any, Any]:
        """Signed distance to the nearest obstacle surface (n,), m (negative inside), and the
        unit vector from that obstacle's centre to each unit (n, 2); inf and zeros if k = 0.

        Of equally near obstacles the first. A unit exactly at a centre is pushed along +x. Up
        to ``ALL_AT_ONCE`` unit-obstacle pairs at once, beyond one obstacle at a time (memory
        O(n)).
        """
        xp = namespace(positions, self.centers)
        n, k = positions.shape[0], len(self)
        if k == 0:
            return xp.full(n, xp.inf), xp.zeros((n, 2))

        def away_from(offset: Any, length: Any) -> Any:
            along = offset / xp.maximum(length, 1e-300)[..., None]
            return xp.where((length > 0)[..., None], along, xp.asarray([1.0, 0.0]))

        if n * k <= ALL_AT_ONCE:
            offset = positions[:, None, :] - self.centers[None, :, :]
            length = xp.hypot(offset[..., 0], offset[..., 1])
            nearest = xp.argmin(length - self.radii, axis=1)[:, None]
            chosen = xp.take_along_axis(length, nearest, axis=1)[:, 0]
            reach = xp.take_along_axis(offset, nearest[..., None], axis=1)[:, 0]
            return chosen - self.radii[nearest[:, 0]], away_from(reach, chosen)

        def nearer(best: tuple[Any, Any], obstacle: tuple[Any, Any]) -> tuple[tuple[Any, Any], None]:
            centre, radius = obstacle
            offset = positions - centre
            length = xp.hypot(offset[:, 0], offset[:, 1])
            distance = length - radius
            closer = distance < best[0]
            return (
                xp.where(closer, distance, best[0]),
                xp.where(closer[:, None], away_from(offset, length), best[1]),
            ), None

        best = (xp.full(n, xp.inf), xp.zeros((n, 2)))
        if xp is jnp:
            return jax.lax.scan(nearer, best, (self.centers, self.radii))[0]
        for obstacle in zip(self.centers, self.radii):
            best = nearer(best, obstacle)[0]
        return best


@pytree(data=("d_minr", "d_mino"), static=("ahead_reference",))
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


@pytree(data=("velocity", "obstacle_distance", "unit_distance", "exempt"))
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

    velocity: Any
    obstacle_distance: Any
    unit_distance: Any
    exempt: Any


def obstacle_repulsion(
    positions: Any, reference_heading: Any, obstacles: CircularObstacles, d_mino: Any
) -> tuple[Any, Any]:
    """Eq. 6: ``cos(theta_io) (1/d - 1/d_mino)`` away from the nearest obstacle, active when
    the obstacle is within d_mino and ahead (|theta_io| < pi/2).

    theta_io is the angle between the reference heading and the direction from the unit to
    the nearest obstacle point (for a circle, toward its centre): an obstacle straight ahead
    repels fully, one abeam not at all, one behind (already passed) not at all.

    Returns:
        velocity (n, 2) in m/s and the signed obstacle distance (n,) in m.
    """
    xp = namespace(positions, reference_heading)
    distance, away = obstacles.nearest(positions)
    # cos(theta_io) as the dot product of the heading with the direction toward the obstacle;
    # "ahead" (|theta_io| < pi/2) is cos(theta_io) > 0.
    cosine = -(away[:, 0] * xp.cos(reference_heading) + away[:, 1] * xp.sin(reference_heading))
    active = (distance < d_mino) & (cosine > 0)
    magnitude = xp.where(active, cosine * (1.0 / xp.maximum(distance, MIN_DISTANCE) - 1.0 / d_mino), 0.0)
    return magnitude[:, None] * away, distance


def unit_repulsion(positions: Any, d_minr: Any) -> tuple[Any, Any]:
    """Eq. 7: ``(1/d - 1/d_minr)`` away from the nearest other unit within d_minr.

    Coincident units (distance 0) are pushed apart along deterministic directions: unit i
    along the angle i * golden angle.

    Returns:
        velocity (n, 2) in m/s and the nearest-unit distance (n,) in m (inf beyond d_minr).
    """
    xp = namespace(positions)
    n = positions.shape[0]
    distance, index = nearest_unit(positions, d_minr)
    active = xp.isfinite(distance)
    offset = positions - positions[xp.where(active, index, xp.arange(n))]
    length = xp.hypot(offset[:, 0], offset[:, 1])
    golden = xp.arange(n) * GOLDEN_ANGLE
    away = xp.where(
        (active & (length == 0))[:, None],
        xp.stack((xp.cos(golden), xp.sin(golden)), axis=1),
        offset / xp.maximum(length, 1e-300)[:, None],
    )
    magnitude = 1.0 / xp.maximum(xp.where(active, distance, d_minr), MIN_DISTANCE) - 1.0 / d_minr
    return xp.where(active[:, None], magnitude[:, None] * away, 0.0), distance


def repulsion(
    positions: Any,
    reference_heading: Any,
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
