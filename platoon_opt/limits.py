"""Achievable tip velocities of each unit in one step, and projections onto them.

A unit in one gear can move its tip at ``s (cos phi, sin phi)`` with ``0 <= s <= v_max``
and ``phi`` in the steering sector ``axis + [lower, upper]`` (``axis`` = heading,
or heading + pi when backing). With ``|lower|, |upper| <= alpha_max < pi/2`` the sector
is convex, so its intersection with the speed disk (a circular sector, ``C_i``) is
convex. Forward and backing together form a double sector, which is not convex.

Shapes: ``n`` units; velocities (n, 2) in m/s; angles (n,) in rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from platoon_opt.arrays import namespace, pytree
from platoon_opt.vehicle import PlatoonState, VehicleLimits, gear_axis, wrap_angle

# A padded polygon row (``0 <= 0``, see ``AchievableSets.polygon``) is replaced by
# ``axis . v <= LOOSE * max_speed``, never active: the pattern stays fixed and interior-point
# backends keep a strictly feasible slack.
LOOSE = 2.0


@pytree(data=("axis", "lower", "upper", "max_speed"))
@dataclass(frozen=True)
class AchievableSets:
    """Circular sectors C_i, one per unit (numpy arrays, or JAX inside the engine).

    Attributes:
        axis: direction of zero steering for the chosen gear (n,), rad.
        lower, upper: steering range relative to ``axis`` (n,), rad, lower <= upper.
        max_speed: radius of the speed disk, m/s.
    """

    axis: Any
    lower: Any
    upper: Any
    max_speed: Any

    @classmethod
    def for_gear(
        cls,
        state: PlatoonState,
        gear: Any,
        limits: VehicleLimits,
        *,
        rate_aware: bool = False,
        dt: Any = None,
    ) -> AchievableSets:
        """The sectors of each unit in ``gear`` (n,). The steering of a backing unit maps
        the same way: its tip moves along ``theta + pi + alpha``.

        ``rate_aware`` narrows the range to what the steering reaches within ``dt``:
        ``[alpha - alpha_dot_max dt, alpha + alpha_dot_max dt]`` cut by the steering limit.
        """
        xp = namespace(state.theta, state.alpha, gear)
        n = state.n
        lower = xp.full(n, -limits.max_steering)
        upper = xp.full(n, limits.max_steering)
        if rate_aware:
            if dt is None:
                raise ValueError("AchievableSets.for_gear: rate_aware=True needs dt, got None")
            reach = limits.max_steering_rate * dt
            lower = xp.maximum(lower, state.alpha - reach)
            upper = xp.minimum(upper, state.alpha + reach)
        return cls(gear_axis(state.theta, gear), lower, upper, limits.max_speed)

    def take(self, index: Any) -> AchievableSets:
        """The sets of the units ``index`` (indices) alone."""
        return AchievableSets(self.axis[index], self.lower[index], self.upper[index], self.max_speed)

    def unit_vectors(self, relative: Any) -> Any:
        """Unit vectors (n, 2) at ``axis + relative``."""
        xp = namespace(self.axis, relative)
        angle = self.axis + relative
        return xp.stack((xp.cos(angle), xp.sin(angle)), axis=1)

    def frame(self) -> SectorFrame:
        """The sectors' directions as sines and cosines, for projecting many times (``SectorFrame``)."""
        xp = namespace(self.axis, self.lower)
        middle = (self.lower + self.upper) / 2
        return SectorFrame(
            xp.cos(self.axis),
            xp.sin(self.axis),
            xp.cos(self.lower),
            xp.sin(self.lower),
            xp.cos(self.upper),
            xp.sin(self.upper),
            xp.cos(middle),
            xp.sin(middle),
            self.lower,
            self.upper,
            self.max_speed,
        )

    def project(self, velocity: Any) -> Any:
        """Euclidean projection of each velocity (n, 2) onto its sector C_i, closed form."""
        return self.frame().project(velocity)

    def project_either_gear(self, velocity: Any) -> Any:
        """Projection onto the nearer of C_i and its reflection -C_i (``SectorFrame.project_either_gear``)."""
        return self.frame().project_either_gear(velocity)

    def steer(self, velocity: Any) -> Any:
        """Each velocity (n, 2) as the unit drives it when handed it (Eq. 2): its speed kept (capped
        at ``max_speed``), its direction turned as far toward the velocity's as the sector's steering
        range lets it. With the rate-aware range and the deadbeat steering (K_alpha dt = 1, the
        default) this is the velocity the unit drives within the step, in the velocity's gear; a
        velocity inside the sector is its own image. m/s."""
        xp = namespace(self.axis, velocity)
        speed = xp.minimum(xp.hypot(velocity[:, 0], velocity[:, 1]), self.max_speed)
        relative = wrap_angle(xp.arctan2(velocity[:, 1], velocity[:, 0]) - self.axis)
        return speed[:, None] * self.unit_vectors(xp.clip(relative, self.lower, self.upper))

    def distance(self, velocity: Any) -> Any:
        """Distance (n,) of each velocity from its sector, m/s."""
        gap = velocity - self.project(velocity)
        return namespace(gap).hypot(gap[:, 0], gap[:, 1])

    def distance_either_gear(self, velocity: Any) -> Any:
        """Distance (n,) of each velocity from the nearer of its sector and the other gear's, m/s."""
        gap = velocity - self.project_either_gear(velocity)
        return namespace(gap).hypot(gap[:, 0], gap[:, 1])

    def contains(self, velocity: Any, tol: float = 1e-9) -> Any:
        """Whether each velocity (n, 2) lies in its sector to within ``tol`` (m/s)."""
        return self.distance(velocity) <= tol

    def polygon(self, sides: int = 16) -> tuple[Any, Any]:
        """Linear inequalities ``A_i v <= b_i`` describing an inner approximation of C_i.

        The two edge half-planes of the sector, plus the edges of the regular ``sides``-gon
        inscribed in the speed disk (a vertex at the sector's axis) that meet the sector;
        every polygon edge that can meet a sector narrower than pi (a static count, so that
        compiled code has fixed shapes) is listed, and the rows of those that do not meet it
        are ``0 <= 0``.

        Returns:
            normals (n, k, 2) and offsets (n, k), k = 2 + 2 (ceil((pi/2) / step) + 1) with
            step = 2 pi / sides.
        """
        if sides < 3:
            raise ValueError(f"polygon sides must be >= 3, got {sides!r}")
        xp = namespace(self.axis, self.lower)
        n = self.axis.shape[0]
        step = 2 * math.pi / sides
        # Edge j of the polygon spans angles [j step, (j+1) step] around the sector centre;
        # its outward normal points at its middle and its offset is v_max cos(step / 2). A
        # half-width below pi/2 meets edges -count .. count - 1 at most.
        centre = (self.lower + self.upper) / 2
        half_width = (self.upper - self.lower) / 2
        count = math.ceil((math.pi / 2) / step) + 1
        mid = (xp.arange(-count, count) + 0.5) * step  # relative to the sector centre
        meets = (mid[None, :] + step / 2 > -half_width[:, None]) & (
            mid[None, :] - step / 2 < half_width[:, None]
        )
        normal_angle = self.axis[:, None] + centre[:, None] + mid[None, :]
        edge_normals = xp.stack((xp.cos(normal_angle), xp.sin(normal_angle)), axis=-1) * meets[..., None]
        edge_offsets = self.max_speed * math.cos(step / 2) * meets
        # Sector sides: v . n <= 0 with n the outward normal of each edge ray.
        lower_normal = self.unit_vectors(self.lower - math.pi / 2)
        upper_normal = self.unit_vectors(self.upper + math.pi / 2)
        normals = xp.concatenate((lower_normal[:, None], upper_normal[:, None], edge_normals), axis=1)
        offsets = xp.concatenate((xp.zeros((n, 2)), edge_offsets), axis=1)
        return normals, offsets


@pytree(
    data=(
        "cos_axis", "sin_axis", "cos_lower", "sin_lower", "cos_upper", "sin_upper",
        "cos_middle", "sin_middle", "lower", "upper", "max_speed",
    )
)  # fmt: skip
@dataclass(frozen=True)
class SectorFrame:
    """``AchievableSets`` with the cosines and sines of each sector's axis, edges (relative to the
    axis) and middle direction computed once (each (n,)): the projections onto the sectors, for
    loops that project many times (the paper's iteration, the dual)."""

    cos_axis: Any
    sin_axis: Any
    cos_lower: Any
    sin_lower: Any
    cos_upper: Any
    sin_upper: Any
    cos_middle: Any
    sin_middle: Any
    lower: Any
    upper: Any
    max_speed: Any

    def to_local(self, velocity: Any) -> tuple[Any, Any]:
        """Velocities (n, 2) in each sector's frame (axis along a): (a, b), each (n,)."""
        c, s = self.cos_axis, self.sin_axis
        return velocity[:, 0] * c + velocity[:, 1] * s, velocity[:, 1] * c - velocity[:, 0] * s

    def to_plane(self, a: Any, b: Any) -> Any:
        """Local velocities (a, b) back in the plane, (n, 2)."""
        c, s = self.cos_axis, self.sin_axis
        return namespace(a, c).stack((a * c - b * s, a * s + b * c), axis=1)

    def project_local(self, a: Any, b: Any) -> tuple[Any, Any]:
        """Projection of local velocities (a, b) (n,) x 2 onto the sectors {angle in [lower,
        upper], |.| <= max_speed}.

        For a cone K and a disk B centred at its apex, P_{K cap B} = P_B o P_K: project onto
        the steering sector (w itself, the nearer edge ray, or the apex), then shorten to
        the speed limit.
        """
        xp = namespace(a, self.lower)
        angle = xp.arctan2(b, a)
        on_lower = xp.maximum(a * self.cos_lower + b * self.sin_lower, 0.0)
        on_upper = xp.maximum(a * self.cos_upper + b * self.sin_upper, 0.0)
        upper_nearer = on_upper >= on_lower
        in_cone = (angle >= self.lower) & (angle <= self.upper)
        pa = xp.where(
            in_cone, a, xp.where(upper_nearer, on_upper * self.cos_upper, on_lower * self.cos_lower)
        )
        pb = xp.where(
            in_cone, b, xp.where(upper_nearer, on_upper * self.sin_upper, on_lower * self.sin_lower)
        )
        scale = xp.minimum(1.0, self.max_speed / xp.maximum(xp.hypot(pa, pb), 1e-300))
        return pa * scale, pb * scale

    def project(self, velocity: Any) -> Any:
        """Euclidean projection of each velocity (n, 2) onto its sector C_i, closed form."""
        return self.to_plane(*self.project_local(*self.to_local(velocity)))

    def project_either_gear(self, velocity: Any) -> Any:
        """Projection onto the nearer of C_i and its reflection -C_i (the other gear's sector:
        the same steering range about the reversed axis). Shape (n, 2), m/s.

        The line through the apex perpendicular to C_i's middle direction reflects C_i onto -C_i
        (the sector is symmetric about its middle), so the nearer one is the one on w's side
        of that line (C_i on the line itself, where both are as near).
        """
        a, b = self.to_local(velocity)
        side = namespace(a).where(a * self.cos_middle + b * self.sin_middle >= 0, 1.0, -1.0)
        pa, pb = self.project_local(side * a, side * b)
        return self.to_plane(side * pa, side * pb)


def project_either_gear(velocity: Any, state: PlatoonState, limits: VehicleLimits) -> Any:
    """Closest achievable velocity over both gears (the paper's q^best): the nearer of the
    projections onto the forward and the backing sectors. Shape (n, 2), m/s."""
    forward = namespace(state.theta).ones(state.n)
    return AchievableSets.for_gear(state, forward, limits).project_either_gear(velocity)


def unit_rows(sets: AchievableSets, speed: str, sides: int, max_speed: Any) -> tuple[Any, Any]:
    """Each unit's linear rows ``normals[i] @ v <= offsets[i]``: shapes (n, k, 2) and (n, k).

    Polygon mode: the two steering half-planes and the polygon edges that meet the sector
    (``AchievableSets.polygon``), padded rows made loose. On the host (numpy) the edges that no
    unit needs (e.g. the two beyond a full 90-degree sector) are dropped; compiled code keeps
    them, loose, for fixed shapes. Cone mode: the two half-planes.
    """
    xp = namespace(sets.axis)
    if speed == "cone":
        lower, upper = (
            sets.unit_vectors(sets.lower - math.pi / 2),
            sets.unit_vectors(sets.upper + math.pi / 2),
        )
        return xp.stack((lower, upper), axis=1), xp.zeros((lower.shape[0], 2))
    normals, offsets = sets.polygon(sides)
    padded = ~xp.any(normals != 0.0, axis=2) & (xp.arange(normals.shape[1]) >= 2)
    if xp is np:
        needed = ~np.all(padded, axis=0)
        normals, offsets, padded = normals[:, needed], offsets[:, needed], padded[:, needed]
    axis = sets.unit_vectors((sets.lower + sets.upper) / 2)
    normals = xp.where(padded[..., None], axis[:, None, :], normals)
    offsets = xp.where(padded, LOOSE * max_speed, offsets)
    return normals, offsets


def inner_projection(velocity: Any, sets: AchievableSets, speed: str, sides: int) -> Any:
    """Each velocity (n, 2) projected onto its exact sector, then (speed "polygon") shortened along
    its ray into the inscribed ``sides``-gon of ``AchievableSets.polygon``, so that it meets every
    row of ``unit_rows``: a pinned unit's or a fallback's velocity (n, 2), m/s.

    The ray from the apex leaves the polygon through the edge whose angular span holds its
    direction (the polygon is convex and holds the apex), so one edge per unit is checked: O(n)
    arithmetic, no rows built."""
    xp = namespace(velocity, sets.axis)
    frame = sets.frame()
    a, b = frame.project_local(*frame.to_local(velocity))
    if speed == "polygon":
        step = 2 * math.pi / sides
        centre = (sets.lower + sets.upper) / 2
        # The outward normal of that edge, at the middle of its span, relative to the axis.
        normal = centre + (xp.floor((xp.arctan2(b, a) - centre) / step) + 0.5) * step
        reach = a * xp.cos(normal) + b * xp.sin(normal)
        offset = sets.max_speed * math.cos(step / 2)
        shorten = reach > offset
        scale = xp.where(shorten, offset / xp.where(shorten, reach, 1.0), 1.0)
        a, b = a * scale, b * scale
    return frame.to_plane(a, b)
