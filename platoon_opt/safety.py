"""Hard safety: discrete-time barrier constraints on each unit's velocity (docs/safety.md).

For an obstacle (centre c, radius r) and a unit at tip p, ``h(p) = ||p - c||^2 - R^2`` with
``R = r + obstacle_margin``; for two units, ``h = ||p_i - p_j||^2 - safety_distance^2``. A step
is safe when ``h(p + D) >= (1 - gamma) h(p)`` for the executed displacement D. ``h`` is convex,
so ``h(p + D) >= h(p) + 2 g . D`` with ``g = p - c`` (or ``p_i - p_j``); a unit pair's term is
split in halves between the two units. Each unit thus needs ``g_hat . D >= -b dt`` with
``b = gamma h / (w dt |g|)``, w = 2 for an obstacle and 4 for a neighbour.

The executed displacement is not ``v dt``: the steering lags the allocated direction and the tip
follows an arc. For this project's vehicle model D = rho R(e) v dt with 0 < rho <= 1 and
|e| <= delta_i (``direction_error``), so the half-plane is made robust: the velocity must meet
``g_hat . R(e) v >= -b`` for every |e| <= delta_i, of which three half-planes are an inner
approximation (``robust_rows``).

These rows keep every unit safe, but a car-like unit heading at an obstacle is stopped at its
margin with every forward velocity pointing in: it cannot turn without moving. With
``turning_room`` a unit whose travel axis points at an obstacle (or a neighbour) also keeps the
room it needs to turn away at its least turning radius ``rho_t = d / sin(alpha_max)``: the
barrier ``H = ||g||^2 - (R + rho_t (1 - sin|psi|))^2``, psi the angle between its axis and the
direction to the centre, depends on the heading, whose rate ``theta' = e_perp . v / d`` is linear
in the tip velocity, so its step condition is one more half-plane (``turning_rows``). It is a
liveness condition, not part of the guarantee: its rows are not made robust.

Shapes: n units, k rows per unit; velocities (n, 2) in m/s; normals are unit vectors and a row
reads ``normals @ v <= offsets``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.errors import ConfigurationError
from platoon_opt.limits import AchievableSets
from platoon_opt.neighbours import BRUTE_FORCE_UNITS
from platoon_opt.validation import positive
from platoon_opt.vehicle import PlatoonState, VehicleLimits, wrap_angle

MODES = ("none", "barrier")
# Below this distance (m) a barrier's gradient direction is taken as +x (a unit at an obstacle's
# centre, or on top of another unit: an unsafe state, answered with a slack).
MIN_GRADIENT = 1e-9
# Largest direction error (rad) for which the robust rows are an inner approximation.
MAX_DIRECTION_ERROR = math.radians(80.0)
# Barrier values h within this of 0 (m^2) are on the boundary: a step that keeps h >= 0 exactly
# ends up to rounding outside it (a pair at 0.3 - 4e-14 m: h = -2.4e-14), which is no unsafe
# state to relax.
ROUNDING = 1e-12


@dataclass(frozen=True)
class SafetyParams:
    """What the barrier constraints keep (the ``[safety]`` table of a scenario file).

    Attributes:
        mode: "none" or "barrier".
        barrier_rate: gamma in (0, 1]: how much of h a step may use up (1: down to the boundary).
        safety_distance: least distance between two unit tips (m), > 0.
        obstacle_margin: added to every obstacle's radius (m), >= 0.
        neighbour_cutoff: pairs of units closer than this (m) are constrained; it must exceed
            ``safety_distance`` by at least the two units' largest travel in one step,
            2 max_speed dt (``check``), so that an unconstrained pair cannot collide within a
            step. None: ``safety_distance + 4 max_speed dt``.
        turning_room: also keep each unit heading at an obstacle or a neighbour far enough to
            turn away (``turning_rows``), so that it is not pinned.
    """

    mode: str = "none"
    barrier_rate: float = 0.5
    safety_distance: float = 0.3
    obstacle_margin: float = 0.05
    neighbour_cutoff: float | None = None
    turning_room: bool = True

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"SafetyParams.mode must be one of {MODES}, got {self.mode!r}")
        rate = positive("SafetyParams.barrier_rate", self.barrier_rate)
        if rate > 1:
            raise ValueError(f"SafetyParams.barrier_rate must be in (0, 1], got {rate!r}")
        positive("SafetyParams.safety_distance", self.safety_distance)
        positive("SafetyParams.obstacle_margin", self.obstacle_margin, allow_zero=True)
        if self.neighbour_cutoff is not None:
            positive("SafetyParams.neighbour_cutoff", self.neighbour_cutoff)
        if not isinstance(self.turning_room, bool):
            raise ValueError(f"SafetyParams.turning_room must be True or False, got {self.turning_room!r}")

    @property
    def enabled(self) -> bool:
        """Whether barrier constraints apply."""
        return self.mode == "barrier"

    def reach(self, limits: VehicleLimits, dt: float) -> float:
        """How far beyond ``safety_distance`` (between tips) and beyond an inflated obstacle
        (from a tip) constraints are imposed (m)."""
        if self.neighbour_cutoff is None:
            return 4 * limits.max_speed * dt
        return self.neighbour_cutoff - self.safety_distance

    def check(self, limits: VehicleLimits, dt: float, *, where: str = "safety") -> None:
        """Raise ``ConfigurationError`` unless the cutoff leaves no pair unguarded (see
        ``neighbour_cutoff``) and the vehicle's gear rule keeps an allocated gear (a velocity
        within the steering limit of one gear's axis must be beyond pi/2 + hysteresis of the
        other's: ``max_steering + gear_hysteresis < pi/2``)."""
        least = self.safety_distance + 2 * limits.max_speed * dt
        if self.neighbour_cutoff is not None and self.neighbour_cutoff < least:
            raise ConfigurationError(
                f"{where}.neighbour_cutoff must be >= safety_distance + 2 max_speed dt = {least:.6g} m "
                f"(the closest two units can come within a step), got {self.neighbour_cutoff!r}"
            )
        if limits.max_steering + limits.gear_hysteresis >= math.pi / 2:
            raise ConfigurationError(
                f"{where}: barrier constraints need max_steering + gear_hysteresis < 90 degrees (the "
                "unit controller must keep the gear it is allocated), got "
                f"{math.degrees(limits.max_steering):.6g} + {math.degrees(limits.gear_hysteresis):.6g}"
            )


def direction_error(
    state: PlatoonState, sets: AchievableSets, limits: VehicleLimits, dt: float
) -> np.ndarray:
    """Bound (n,) rad on the angle between an allocated velocity in ``sets`` and the displacement
    the unit executes in the step (``unit_controller`` then ``step_vehicles``; docs/safety.md).

    The steering reaches ``alpha + clip(K (phi - alpha), lo, hi) dt`` for an allocated steering
    phi (relative to the gear's axis), a piecewise-linear function of phi, so its largest lag over
    ``[lower, upper]`` is at an end or a kink; the arc's chord then turns by half the step's
    heading change, at most ``v_max dt sin|alpha'| / (2 d)``.
    """
    alpha, reach = state.alpha, limits.max_steering_rate
    low = np.maximum(-reach, (-limits.max_steering - alpha) / dt)
    high = np.minimum(reach, (limits.max_steering - alpha) / dt)

    def steered(phi: np.ndarray) -> np.ndarray:
        return alpha + np.clip(limits.steering_gain * (phi - alpha), low, high) * dt

    kinks = [sets.lower, sets.upper]
    kinks += [np.clip(alpha + bound / limits.steering_gain, sets.lower, sets.upper) for bound in (low, high)]
    lag = np.max([np.abs(steered(phi) - phi) for phi in kinks], axis=0)
    steepest = np.maximum(np.abs(steered(sets.lower)), np.abs(steered(sets.upper)))
    turn = limits.max_speed * dt * np.sin(steepest) / (2 * limits.length)
    return lag + turn + 1e-12


def robust_rows(
    direction: np.ndarray, budget: np.ndarray, error: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rows (…, 3, 2), (…, 3) that imply ``direction . R(e) v >= -budget`` for all |e| <= error.

    ``direction`` (…, 2) unit vectors, ``budget`` (…) m/s, ``error`` (…) rad below pi/2. The two
    extreme rotations ``R(+-error) direction . v >= -budget`` cover every v whose worst rotation
    is an extreme one; a v within ``error`` of ``-direction`` has its worst at ``-|v|``, which
    ``direction . v >= -budget cos(error)`` bounds (docs/safety.md).
    """
    cos, sin = np.cos(error), np.sin(error)
    x, y = direction[..., 0], direction[..., 1]
    plus = np.stack((cos * x - sin * y, sin * x + cos * y), axis=-1)
    minus = np.stack((cos * x + sin * y, -sin * x + cos * y), axis=-1)
    normals = -np.stack((plus, minus, direction), axis=-2)
    offsets = np.stack((budget, budget, budget * cos), axis=-1)
    return normals, offsets


@dataclass(frozen=True)
class Barriers:
    """Each unit's barrier half-planes for one step: ``normals[i] @ v <= offsets[i]``.

    Attributes:
        normals: (n, k, 2) unit vectors (zero rows pad units with fewer constraints).
        offsets: (n, k) m/s (padding rows 0).
        worst: (n,) the least h over each unit's constraints (m^2; +inf with none): a negative
            value is an unsafe state.
    """

    normals: np.ndarray
    offsets: np.ndarray
    worst: np.ndarray


def barriers(
    state: PlatoonState,
    obstacles: CircularObstacles,
    limits: VehicleLimits,
    dt: float,
    sets: AchievableSets,
    params: SafetyParams,
) -> Barriers:
    """The robust barrier rows of every unit (see the module docstring) for velocities in
    ``sets`` (the gears and steering ranges the units are allocated in), and with
    ``params.turning_room`` its turning rows.

    Constrained are the obstacles whose inflated surface lies within ``params.reach`` of a tip and
    the neighbours within ``safety_distance + reach`` (for the turning rows, one turning radius
    further); memory is O(n) for a bounded density.
    """
    params.check(limits, dt)
    positions = state.positions
    n, reach = state.n, params.reach(limits, dt)
    turning = turning_radius(limits) if params.turning_room else 0.0
    owner: list[np.ndarray] = []
    centre: list[np.ndarray] = []
    radius: list[np.ndarray] = []
    share: list[np.ndarray] = []  # 1 for an obstacle, 2 for a pair: each unit takes half
    for i, point, inflated in _near_obstacles(positions, obstacles, params.obstacle_margin, reach + turning):
        owner.append(i)
        centre.append(np.broadcast_to(point, (i.size, 2)))
        radius.append(np.full(i.size, inflated))
        share.append(np.ones(i.size))
    pairs = _near_pairs(positions, params.safety_distance + reach + turning)
    if pairs.size:
        owner += [pairs[:, 0], pairs[:, 1]]
        centre += [positions[pairs[:, 1]], positions[pairs[:, 0]]]
        radius += [np.full(len(pairs), params.safety_distance)] * 2
        share += [np.full(len(pairs), 2.0)] * 2
    if not owner:
        return Barriers(np.zeros((n, 0, 2)), np.zeros((n, 0)), np.full(n, np.inf))
    who, c, rho, w = (np.concatenate(parts) for parts in (owner, centre, radius, share))
    g = positions[who] - c
    length = np.hypot(g[:, 0], g[:, 1])
    h = length**2 - rho**2
    h = np.where(np.abs(h) < ROUNDING, 0.0, h)
    # The guaranteed rows: every constraint within reach of its boundary.
    near = length < rho + reach
    direction = np.where(
        (length > MIN_GRADIENT)[:, None], g / np.maximum(length, MIN_GRADIENT)[:, None], [1.0, 0.0]
    )
    budget = params.barrier_rate * h / (2 * w * dt * np.maximum(length, MIN_GRADIENT))
    error = direction_error(state, sets, limits, dt)
    if np.max(error) > MAX_DIRECTION_ERROR:
        raise ConfigurationError(
            f"safety: the steering may miss an allocated direction by {math.degrees(np.max(error)):.3g} "
            f"degrees in a step (more than {math.degrees(MAX_DIRECTION_ERROR):.0f}): use rate_aware=True "
            "or a steering gain near 1/dt"
        )
    normals, offsets = robust_rows(direction[near], budget[near], error[who[near]])
    rows_owner = [np.repeat(who[near], 3)]
    rows_normal, rows_offset = [normals.reshape(-1, 2)], [offsets.reshape(-1)]
    if params.turning_room:
        ahead, normal, offset = turning_rows(state, sets, limits, dt, who, g, rho, w, params.barrier_rate)
        rows_owner.append(who[ahead])
        rows_normal.append(normal)
        rows_offset.append(offset)
    worst = np.full(n, np.inf)
    np.minimum.at(worst, who[near], h[near])
    all_normals, all_offsets = _pack(
        n, np.concatenate(rows_owner), np.concatenate(rows_normal), np.concatenate(rows_offset)
    )
    return Barriers(all_normals, all_offsets, worst)


def turning_radius(limits: VehicleLimits) -> float:
    """The least radius (m) a unit's tip turns on: ``length / sin(max_steering)``."""
    return limits.length / math.sin(limits.max_steering)


def turning_rows(
    state: PlatoonState,
    sets: AchievableSets,
    limits: VehicleLimits,
    dt: float,
    owner: np.ndarray,
    offset: np.ndarray,
    radius: np.ndarray,
    share: np.ndarray,
    gamma: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Turning rows of the constraints whose unit's travel axis points at the centre.

    Constraint c has unit ``owner[c]`` at ``offset[c]`` (m, (c, 2)) from a centre it must keep
    ``radius[c]`` (m) from, with the budget divided by ``share[c]``. With psi the angle from the
    direction to the centre to the unit's axis (``sets.axis``), ``|psi| < pi/2``, the barrier
    ``H = |g|^2 - (radius + rho_t (1 - sin|psi|))^2`` changes at ``a . v`` with
    ``a = 2 g + 2 (radius + mu) rho_t cos(psi) sign(psi) (e_perp / d + t_perp / |g|)``, e_perp the
    heading's normal and t_perp the normal of the direction to the centre; the row asks
    ``a . v dt >= -gamma max(H, 0) / share``, which v = 0 meets.

    Returns:
        Which constraints have a row (c,) bool, and their unit normals (r, 2) and offsets (r,)
        (m/s) in the form ``normal . v <= offset``.
    """
    length = np.hypot(offset[:, 0], offset[:, 1])
    toward = -offset / np.maximum(length, MIN_GRADIENT)[:, None]
    psi = wrap_angle(sets.axis[owner] - np.arctan2(toward[:, 1], toward[:, 0]))
    ahead = (np.abs(psi) < math.pi / 2) & (length > radius)
    turning = turning_radius(limits)
    psi, g, s, toward, rho = psi[ahead], offset[ahead], length[ahead], toward[ahead], radius[ahead]
    margin = turning * (1 - np.sin(np.abs(psi)))
    theta = state.theta[owner[ahead]]
    heading_normal = np.column_stack((-np.sin(theta), np.cos(theta)))
    toward_normal = np.column_stack((-toward[:, 1], toward[:, 0]))
    side = np.where(psi >= 0, 1.0, -1.0)
    gain = 2 * (rho + margin) * turning * np.cos(psi) * side
    a = 2 * g + gain[:, None] * (heading_normal / limits.length + toward_normal / s[:, None])
    size = np.hypot(a[:, 0], a[:, 1])
    value = np.maximum(s**2 - (rho + margin) ** 2, 0.0)
    return ahead, -a / size[:, None], gamma * value / (share[ahead] * dt * size)


def _pack(
    n: int, owner: np.ndarray, normals: np.ndarray, offsets: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rows (r, 2), (r,) of units ``owner`` (r,) placed in each unit's slots: (n, k, 2), (n, k),
    k the most rows of a unit, zero rows padding."""
    order = np.argsort(owner, kind="stable")
    owner, normals, offsets = owner[order], normals[order], offsets[order]
    counts = np.bincount(owner, minlength=n)
    slot = np.arange(owner.size) - np.repeat(np.cumsum(counts) - counts, counts)
    k = int(counts.max(initial=0))
    all_normals, all_offsets = np.zeros((n, k, 2)), np.zeros((n, k))
    all_normals[owner, slot], all_offsets[owner, slot] = normals, offsets
    return all_normals, all_offsets


def _near_obstacles(
    positions: np.ndarray, obstacles: CircularObstacles, margin: float, reach: float
) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Per obstacle: the units within ``reach`` of its inflated surface, its centre and the
    inflated radius (one obstacle at a time: memory O(n))."""
    near = []
    for centre, radius in zip(obstacles.centers, obstacles.radii):
        inflated = radius + margin
        distance = np.hypot(positions[:, 0] - centre[0], positions[:, 1] - centre[1])
        units = np.flatnonzero(distance < inflated + reach)
        if units.size:
            near.append((units, centre, inflated))
    return near


def _near_pairs(positions: np.ndarray, cutoff: float) -> np.ndarray:
    """Pairs (p, 2) of units closer than ``cutoff`` (m), i < j."""
    n = positions.shape[0]
    if n <= BRUTE_FORCE_UNITS:
        i, j = np.triu_indices(n, 1)
        gap = positions[i] - positions[j]
        close = np.einsum("ij,ij->i", gap, gap) < cutoff**2
        return np.column_stack((i[close], j[close]))
    return cKDTree(positions).query_pairs(cutoff, output_type="ndarray").reshape(-1, 2)
