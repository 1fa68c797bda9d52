"""Achievable tip velocities of each unit in one step, and projections onto them.

A unit in one gear can move its tip at ``s (cos phi, sin phi)`` with ``0 <= s <= v_max``
and ``phi`` in the steering sector ``axis + [lower, upper]`` (``axis`` = heading,
or heading + pi when backing). With ``|lower|, |upper| <= alpha_max < pi/2`` the sector
is convex, so its intersection with the speed disk (a circular sector, ``C_i``) is
convex. Forward and backing together form a double sector, which is not convex.

Shapes: ``n`` units; velocities (n, 2) in m/s; angles (n,) in rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from platoon_opt.vehicle import PlatoonState, VehicleLimits, gear_axis


@dataclass(frozen=True)
class AchievableSets:
    """Circular sectors C_i, one per unit.

    Attributes:
        axis: direction of zero steering for the chosen gear (n,), rad.
        lower, upper: steering range relative to ``axis`` (n,), rad, lower <= upper.
        max_speed: radius of the speed disk, m/s.
    """

    axis: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    max_speed: float

    @classmethod
    def for_gear(
        cls,
        state: PlatoonState,
        gear: np.ndarray,
        limits: VehicleLimits,
        *,
        rate_aware: bool = False,
        dt: float | None = None,
    ) -> AchievableSets:
        """The sectors of each unit in ``gear`` (n,). The steering of a backing unit maps
        the same way: its tip moves along ``theta + pi + alpha``.

        ``rate_aware`` narrows the range to what the steering reaches within ``dt``:
        ``[alpha - alpha_dot_max dt, alpha + alpha_dot_max dt]`` cut by the steering limit.
        """
        n = state.n
        lower = np.full(n, -limits.max_steering)
        upper = np.full(n, limits.max_steering)
        if rate_aware:
            if dt is None:
                raise ValueError("AchievableSets.for_gear: rate_aware=True needs dt, got None")
            reach = limits.max_steering_rate * dt
            lower = np.maximum(lower, state.alpha - reach)
            upper = np.minimum(upper, state.alpha + reach)
        return cls(gear_axis(state.theta, gear), lower, upper, limits.max_speed)

    def unit_vectors(self, relative: np.ndarray) -> np.ndarray:
        """Unit vectors (n, 2) at ``axis + relative``."""
        angle = self.axis + relative
        return np.column_stack((np.cos(angle), np.sin(angle)))

    def project(self, velocity: np.ndarray) -> np.ndarray:
        """Euclidean projection of each velocity (n, 2) onto its sector C_i, closed form.

        For a cone K and a disk B centred at its apex, P_{K cap B} = P_B o P_K: project onto
        the steering sector (the velocity itself, the nearer edge ray, or the apex), then
        shorten to the speed limit.
        """
        angle = np.arctan2(velocity[:, 1], velocity[:, 0]) - self.axis
        angle = np.mod(angle + np.pi, 2 * np.pi) - np.pi
        inside = (angle >= self.lower) & (angle <= self.upper)
        lower_ray = self.unit_vectors(self.lower)
        upper_ray = self.unit_vectors(self.upper)
        on_lower = np.maximum(np.einsum("ij,ij->i", velocity, lower_ray), 0.0)
        on_upper = np.maximum(np.einsum("ij,ij->i", velocity, upper_ray), 0.0)
        edge = np.where(
            (on_upper >= on_lower)[:, None], on_upper[:, None] * upper_ray, on_lower[:, None] * lower_ray
        )
        in_cone = np.where(inside[:, None], velocity, edge)
        length = np.hypot(in_cone[:, 0], in_cone[:, 1])
        scale = np.minimum(1.0, self.max_speed / np.maximum(length, 1e-300))
        return in_cone * scale[:, None]

    def distance(self, velocity: np.ndarray) -> np.ndarray:
        """Distance (n,) of each velocity from its sector, m/s."""
        return np.linalg.norm(velocity - self.project(velocity), axis=1)

    def contains(self, velocity: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether each velocity (n, 2) lies in its sector to within ``tol`` (m/s)."""
        return self.distance(velocity) <= tol

    def polygon(self, sides: int = 16) -> tuple[np.ndarray, np.ndarray]:
        """Linear inequalities ``A_i v <= b_i`` describing an inner approximation of C_i.

        The two edge half-planes of the sector, plus the edges of the regular ``sides``-gon
        inscribed in the speed disk (a vertex at the sector's axis) that meet the sector;
        the rows of units that need fewer are padded with ``0 <= 0``.

        Returns:
            normals (n, k, 2) and offsets (n, k), k = 2 + number of polygon edges kept.
        """
        if sides < 3:
            raise ValueError(f"polygon sides must be >= 3, got {sides!r}")
        n = self.axis.shape[0]
        step = 2 * np.pi / sides
        # Edge j of the polygon spans angles [j step, (j+1) step] around the sector centre;
        # its outward normal points at its middle and its offset is v_max cos(step / 2).
        centre = (self.lower + self.upper) / 2
        half_width = (self.upper - self.lower) / 2
        first = -int(np.ceil(np.max(half_width) / step)) - 1
        edges = np.arange(first, -first)
        mid = (edges + 0.5) * step  # relative to the sector centre
        meets = (mid[None, :] + step / 2 > -half_width[:, None]) & (
            mid[None, :] - step / 2 < half_width[:, None]
        )
        normal_angle = self.axis[:, None] + centre[:, None] + mid[None, :]
        edge_normals = np.stack((np.cos(normal_angle), np.sin(normal_angle)), axis=-1) * meets[..., None]
        edge_offsets = self.max_speed * np.cos(step / 2) * meets
        # Sector sides: v . n <= 0 with n the outward normal of each edge ray.
        lower_normal = self.unit_vectors(self.lower - np.pi / 2)
        upper_normal = self.unit_vectors(self.upper + np.pi / 2)
        normals = np.concatenate((lower_normal[:, None], upper_normal[:, None], edge_normals), axis=1)
        offsets = np.concatenate((np.zeros((n, 2)), edge_offsets), axis=1)
        return normals, offsets


def project_either_gear(velocity: np.ndarray, state: PlatoonState, limits: VehicleLimits) -> np.ndarray:
    """Closest achievable velocity over both gears (the paper's q^best): the nearer of the
    projections onto the forward and the backing sectors. Shape (n, 2), m/s."""
    forward = AchievableSets.for_gear(state, np.ones(state.n), limits).project(velocity)
    backward = AchievableSets.for_gear(state, -np.ones(state.n), limits).project(velocity)
    forward_nearer = np.linalg.norm(velocity - forward, axis=1) <= np.linalg.norm(velocity - backward, axis=1)
    return np.where(forward_nearer[:, None], forward, backward)
