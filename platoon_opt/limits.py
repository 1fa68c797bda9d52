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
from functools import cached_property

import numpy as np

from platoon_opt.vehicle import PlatoonState, VehicleLimits, gear_axis

# A padded polygon row (``0 <= 0``, see ``AchievableSets.polygon``) is replaced by
# ``axis . v <= LOOSE * max_speed``, never active: the pattern stays fixed and interior-point
# backends keep a strictly feasible slack.
LOOSE = 2.0


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

    def take(self, index: np.ndarray) -> AchievableSets:
        """The sets of the units ``index`` (indices) alone."""
        return AchievableSets(self.axis[index], self.lower[index], self.upper[index], self.max_speed)

    def unit_vectors(self, relative: np.ndarray) -> np.ndarray:
        """Unit vectors (n, 2) at ``axis + relative``."""
        angle = self.axis + relative
        return np.column_stack((np.cos(angle), np.sin(angle)))

    @cached_property
    def _rotation(self) -> np.ndarray:
        """exp(i axis): local sector coordinates (axis along +real) to the plane."""
        return np.exp(1j * self.axis)

    @cached_property
    def _edges(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit edge rays exp(i lower), exp(i upper) in local coordinates."""
        return np.exp(1j * self.lower), np.exp(1j * self.upper)

    @cached_property
    def _middle(self) -> np.ndarray:
        """exp(i (lower + upper) / 2): each sector's middle direction in local coordinates."""
        return np.exp(0.5j * (self.lower + self.upper))

    def _project_local(self, w: np.ndarray) -> np.ndarray:
        """Projection of local complex velocities w (n,) onto the local sectors."""
        return _project_sector(w, self.lower, self.upper, *self._edges, self.max_speed)

    def _to_local(self, velocity: np.ndarray) -> np.ndarray:
        # (n, 2) floats viewed as n complex numbers x + iy.
        plane = np.ascontiguousarray(velocity, dtype=float).view(np.complex128)[:, 0]
        return plane * self._inverse_rotation

    @cached_property
    def _inverse_rotation(self) -> np.ndarray:
        return self._rotation.conj()

    def _to_plane(self, w: np.ndarray) -> np.ndarray:
        return (w * self._rotation).view(np.float64).reshape(-1, 2)

    def project(self, velocity: np.ndarray) -> np.ndarray:
        """Euclidean projection of each velocity (n, 2) onto its sector C_i, closed form."""
        return self._to_plane(self._project_local(self._to_local(velocity)))

    def project_either_gear(self, velocity: np.ndarray) -> np.ndarray:
        """Projection onto the nearer of C_i and its reflection -C_i (the other gear's sector:
        the same steering range about the reversed axis). Shape (n, 2), m/s.

        The line through the apex perpendicular to C_i's middle direction reflects C_i onto -C_i
        (the sector is symmetric about its middle), so the nearer one is the one on w's side
        of that line (C_i on the line itself, where both are as near).
        """
        w = self._to_local(velocity)
        side = np.where((w * self._middle.conj()).real >= 0, 1.0, -1.0)
        return self._to_plane(side * self._project_local(side * w))

    def distance(self, velocity: np.ndarray) -> np.ndarray:
        """Distance (n,) of each velocity from its sector, m/s."""
        return np.linalg.norm(velocity - self.project(velocity), axis=1)

    def distance_either_gear(self, velocity: np.ndarray) -> np.ndarray:
        """Distance (n,) of each velocity from the nearer of its sector and the other gear's, m/s."""
        return np.linalg.norm(velocity - self.project_either_gear(velocity), axis=1)

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


def _project_sector(
    w: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    lower_ray: np.ndarray,
    upper_ray: np.ndarray,
    max_speed: float,
) -> np.ndarray:
    """Projection of local complex velocities w onto sectors {arg in [lower, upper], |.| <=
    max_speed}, each array of the same shape; ``*_ray`` = exp(i lower), exp(i upper).

    For a cone K and a disk B centred at its apex, P_{K cap B} = P_B o P_K: project onto
    the steering sector (w itself, the nearer edge ray, or the apex), then shorten to
    the speed limit.
    """
    angle = np.angle(w)
    on_lower = np.maximum((w * lower_ray.conj()).real, 0.0)
    on_upper = np.maximum((w * upper_ray.conj()).real, 0.0)
    edge = np.where(on_upper >= on_lower, on_upper * upper_ray, on_lower * lower_ray)
    in_cone = np.where((angle >= lower) & (angle <= upper), w, edge)
    return in_cone * np.minimum(1.0, max_speed / np.maximum(np.abs(in_cone), 1e-300))


def project_either_gear(velocity: np.ndarray, state: PlatoonState, limits: VehicleLimits) -> np.ndarray:
    """Closest achievable velocity over both gears (the paper's q^best): the nearer of the
    projections onto the forward and the backing sectors. Shape (n, 2), m/s."""
    return AchievableSets.for_gear(state, np.ones(state.n), limits).project_either_gear(velocity)


def unit_rows(
    sets: AchievableSets, speed: str, sides: int, max_speed: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each unit's linear rows ``normals[i] @ v <= offsets[i]``: shapes (n, k, 2) and (n, k).

    Polygon mode: the two steering half-planes and the polygon edges that meet the sector
    (``AchievableSets.polygon``), padded rows made loose. Cone mode: the two half-planes.
    """
    if speed == "cone":
        lower, upper = sets.unit_vectors(sets.lower - np.pi / 2), sets.unit_vectors(sets.upper + np.pi / 2)
        return np.stack((lower, upper), axis=1), np.zeros((lower.shape[0], 2))
    normals, offsets = sets.polygon(sides)
    padded = ~np.any(normals != 0.0, axis=2)
    padded[:, :2] = False
    # Edges no unit needs (e.g. the two beyond a full 90-degree sector) are dropped.
    needed = ~np.all(padded, axis=0)
    normals, offsets, padded = normals[:, needed], offsets[:, needed], padded[:, needed]
    axis = sets.unit_vectors((sets.lower + sets.upper) / 2)
    normals = np.where(padded[..., None], axis[:, None, :], normals)
    offsets = np.where(padded, LOOSE * max_speed, offsets)
    return normals, offsets


def inner_projection(
    velocity: np.ndarray, sets: AchievableSets, normals: np.ndarray, offsets: np.ndarray
) -> np.ndarray:
    """Each velocity (n, 2) projected onto its exact sector, then shortened along its ray until it
    meets every row ``normals @ v <= offsets`` (the polygon; nothing to do in cone mode, where the
    rows are homogeneous). The result satisfies the rows: a pinned unit's or a fallback's velocity
    (n, 2), m/s."""
    projected = sets.project(velocity)
    reach = np.einsum("ikj,ij->ik", normals, projected)
    # Only rows with a positive offset (polygon edges) can shorten; the homogeneous steering
    # rows already hold up to round-off after the exact projection.
    ratio = np.where((reach > offsets) & (offsets > 0), offsets / np.where(reach > 0, reach, 1.0), 1.0)
    return projected * np.minimum(1.0, np.min(ratio, axis=1, initial=1.0))[:, None]
