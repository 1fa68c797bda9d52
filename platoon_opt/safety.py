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
from typing import Any

import numpy as np

from platoon_opt.arrays import namespace, pytree, tree_slice
from platoon_opt.avoidance import CircularObstacles
from platoon_opt.barrier_constraints import Constraints, constraints_within
from platoon_opt.errors import ConfigurationError
from platoon_opt.limits import AchievableSets
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
# Units whose barrier rows are built at once on the host (memory).
_CHUNK = 4096


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


def direction_error(state: PlatoonState, sets: AchievableSets, limits: VehicleLimits, dt: Any) -> Any:
    """Bound (n,) rad on the angle between an allocated velocity in ``sets`` and the displacement
    the unit executes in the step (``unit_controller`` then ``step_vehicles``; docs/safety.md).

    The steering reaches ``alpha + clip(K (phi - alpha), lo, hi) dt`` for an allocated steering
    phi (relative to the gear's axis), a piecewise-linear function of phi, so its largest lag over
    ``[lower, upper]`` is at an end or a kink; the arc's chord then turns by half the step's
    heading change, at most ``v_max dt sin|alpha'| / (2 d)``.
    """
    xp = namespace(state.alpha, sets.lower)
    alpha, reach = state.alpha, limits.max_steering_rate
    low = xp.maximum(-reach, (-limits.max_steering - alpha) / dt)
    high = xp.minimum(reach, (limits.max_steering - alpha) / dt)

    def steered(phi: Any) -> Any:
        return alpha + xp.clip(limits.steering_gain * (phi - alpha), low, high) * dt

    kinks = [sets.lower, sets.upper]
    kinks += [xp.clip(alpha + bound / limits.steering_gain, sets.lower, sets.upper) for bound in (low, high)]
    lag = xp.max(xp.stack([xp.abs(steered(phi) - phi) for phi in kinks]), axis=0)
    steepest = xp.maximum(xp.abs(steered(sets.lower)), xp.abs(steered(sets.upper)))
    turn = limits.max_speed * dt * xp.sin(steepest) / (2 * limits.length)
    return lag + turn + 1e-12


def robust_rows(direction: Any, budget: Any, error: Any) -> tuple[Any, Any]:
    """Rows (…, 3, 2), (…, 3) that imply ``direction . R(e) v >= -budget`` for all |e| <= error.

    ``direction`` (…, 2) unit vectors, ``budget`` (…) m/s, ``error`` (…) rad below pi/2. The two
    extreme rotations ``R(+-error) direction . v >= -budget`` cover every v whose worst rotation
    is an extreme one; a v within ``error`` of ``-direction`` has its worst at ``-|v|``, which
    ``direction . v >= -budget cos(error)`` bounds (docs/safety.md).
    """
    xp = namespace(direction, budget, error)
    cos, sin = xp.cos(error), xp.sin(error)
    x, y = direction[..., 0], direction[..., 1]
    plus = xp.stack((cos * x - sin * y, sin * x + cos * y), axis=-1)
    minus = xp.stack((cos * x + sin * y, -sin * x + cos * y), axis=-1)
    normals = -xp.stack((plus, minus, direction), axis=-2)
    offsets = xp.stack((budget, budget, budget * cos), axis=-1)
    return normals, offsets


@pytree(data=("normals", "offsets", "worst", "overflow"))
@dataclass(frozen=True)
class Barriers:
    """Each unit's barrier half-planes for one step: ``normals[i] @ v <= offsets[i]``.

    Attributes:
        normals: (n, k, 2) unit vectors (zero rows pad units with fewer constraints).
        offsets: (n, k) m/s (padding rows 0).
        worst: (n,) the least h over each unit's constraints (m^2; +inf with none): a negative
            value is an unsafe state.
        overflow: (n,) bool: units whose rows are not all here (a compiled build's capacity was
            too small, or the steering may miss a direction by more than ``MAX_DIRECTION_ERROR``);
            their sets are not safe, and the step belongs on the host. Never on the host.
    """

    normals: Any
    offsets: Any
    worst: Any
    overflow: Any


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
    ``params.turning_room`` its turning rows, on the host: every constraint
    (``constraints_within``), as many rows as the most any unit has.

    Constrained are the obstacles whose inflated surface lies within ``params.reach`` of a tip and
    the neighbours within ``safety_distance + reach`` (for the turning rows, one turning radius
    further); memory is O(n) for a bounded density.

    Raises:
        ConfigurationError: the steering of a constrained unit may miss a direction by more than
            ``MAX_DIRECTION_ERROR``, or ``params.check`` fails.
    """
    params.check(limits, dt)
    table = constraints_within(
        state.positions, obstacles, params.obstacle_margin, params.safety_distance, search(params, limits, dt)
    )
    if table.present.shape[1] == 0:
        return Barriers(
            np.zeros((state.n, 0, 2)),
            np.zeros((state.n, 0)),
            np.full(state.n, np.inf),
            np.zeros(state.n, dtype=bool),
        )
    if state.n <= _CHUNK:
        rows = barrier_rows(state, table, sets, limits, dt, params)
    else:  # in chunks of units: a unit's candidate rows take about 40 floats per constraint
        chunks = [
            barrier_rows(*tree_slice((state, table), part), sets.take(part), limits, dt, params)
            for part in (slice(start, start + _CHUNK) for start in range(0, state.n, _CHUNK))
        ]
        kept = max(chunk.offsets.shape[1] for chunk in chunks)
        rows = Barriers(
            np.concatenate([_pad_rows(chunk.normals, kept) for chunk in chunks]),
            np.concatenate([_pad_rows(chunk.offsets, kept) for chunk in chunks]),
            np.concatenate([chunk.worst for chunk in chunks]),
            np.concatenate([chunk.overflow for chunk in chunks]),
        )
    # Every row is kept here: only a unit's steering error overflows.
    if np.any(rows.overflow):
        error = np.max(direction_error(state, sets, limits, dt)[rows.overflow])
        raise ConfigurationError(
            f"safety: the steering may miss an allocated direction by {math.degrees(error):.3g} "
            f"degrees in a step (more than {math.degrees(MAX_DIRECTION_ERROR):.0f}): use rate_aware=True "
            "or a steering gain near 1/dt"
        )
    return rows


def _pad_rows(rows: np.ndarray, kept: int) -> np.ndarray:
    """``rows`` (n, k, …) with zero rows appended up to ``kept``."""
    width = [(0, 0)] * rows.ndim
    width[1] = (0, kept - rows.shape[1])
    return np.pad(rows, width)


def search(params: SafetyParams, limits: VehicleLimits, dt: Any) -> Any:
    """How far beyond an inflated obstacle or the safety distance a constraint is kept (m): the
    step's reach, and with turning rows one turning radius more."""
    reach = params.reach(limits, dt)
    return reach + turning_radius(limits) if params.turning_room else reach


def barrier_rows(
    state: PlatoonState,
    table: Constraints,
    sets: AchievableSets,
    limits: VehicleLimits,
    dt: Any,
    params: SafetyParams,
    *,
    rows: int | None = None,
) -> Barriers:
    """The barrier rows of the constraints ``table`` (numpy or JAX): per constraint within reach
    of its boundary three robust rows, and with turning room a turning row when the unit's travel
    axis points at it; each unit's rows in ``table``'s order, the robust ones first. ``rows``:
    the rows kept per unit (units with more overflow), None for as many as the most any unit has
    (numpy only)."""
    xp = namespace(state.x, table.centre)
    g = state.positions[:, None, :] - table.centre
    length = xp.hypot(g[..., 0], g[..., 1])
    h = length**2 - table.radius**2
    h = xp.where(xp.abs(h) < ROUNDING, 0.0, h)
    near = table.present & (length < table.radius + params.reach(limits, dt))
    floored = xp.maximum(length, MIN_GRADIENT)
    direction = xp.where((length > MIN_GRADIENT)[..., None], g / floored[..., None], xp.asarray([1.0, 0.0]))
    share = xp.where(table.present, table.share, 1.0)
    budget = params.barrier_rate * h / (2 * share * dt * floored)
    error = direction_error(state, sets, limits, dt)
    normals, offsets = robust_rows(direction, budget, error[:, None])
    n, slots = near.shape
    normals, offsets = [normals.reshape(n, 3 * slots, 2)], [offsets.reshape(n, 3 * slots)]
    exists = [xp.repeat(near, 3, axis=1)]
    if params.turning_room:
        ahead, normal, offset = turning_rows(
            state.theta[:, None], sets.axis[:, None], g, table, limits, dt, params.barrier_rate
        )
        normals.append(normal)
        offsets.append(offset)
        exists.append(ahead)
    worst = xp.min(xp.where(near, h, xp.inf), axis=1, initial=xp.inf)
    present = xp.concatenate(exists, axis=1)
    count = xp.sum(present, axis=1)
    kept = int(np.max(count, initial=0)) if rows is None else rows
    overflow = (count > kept) | (xp.any(table.present, axis=1) & (error > MAX_DIRECTION_ERROR))
    all_normals, all_offsets = _compact(
        xp, present, xp.concatenate(normals, axis=1), xp.concatenate(offsets, axis=1), kept
    )
    return Barriers(all_normals, all_offsets, worst, overflow)


def _compact(xp: Any, present: Any, normals: Any, offsets: Any, kept: int) -> tuple[Any, Any]:
    """The first ``kept`` present rows (n, kept, 2), (n, kept) of each unit's ``normals`` (n, r, 2)
    and ``offsets`` (n, r), in order, zero rows after them."""
    n, total = present.shape
    column = xp.arange(total)
    # Unique keys, present rows first: a plain argsort keeps their order.
    order = xp.argsort(xp.where(present, column, column + total), axis=1)[:, :kept]
    picked = xp.take_along_axis(present, order, axis=1)
    normals = xp.where(picked[..., None], xp.take_along_axis(normals, order[..., None], axis=1), 0.0)
    offsets = xp.where(picked, xp.take_along_axis(offsets, order, axis=1), 0.0)
    short = kept - order.shape[1]
    if short > 0:
        normals = xp.concatenate((normals, xp.zeros((n, short, 2))), axis=1)
        offsets = xp.concatenate((offsets, xp.zeros((n, short))), axis=1)
    return normals, offsets


def turning_radius(limits: VehicleLimits) -> Any:
    """The least radius (m) a unit's tip turns on: ``length / sin(max_steering)``."""
    return limits.length / namespace(limits.max_steering).sin(limits.max_steering)


def turning_rows(
    theta: Any,
    axis: Any,
    offset: Any,
    table: Constraints,
    limits: VehicleLimits,
    dt: Any,
    gamma: float,
) -> tuple[Any, Any, Any]:
    """Turning rows of the constraints ``table`` (…) whose unit's travel axis points at the
    centre.

    A constraint's unit, with heading ``theta`` (…) rad and travel axis ``axis`` (…) rad (the
    sector's, ``sets.axis``), is at ``offset`` (…, 2) m from a centre it must keep ``radius`` (m)
    from, with the budget divided by ``share``. With psi the angle from the direction to the
    centre to the unit's axis, ``|psi| < pi/2``, the barrier
    ``H = |g|^2 - (radius + rho_t (1 - sin|psi|))^2`` changes at ``a . v`` with
    ``a = 2 g + 2 (radius + mu) rho_t cos(psi) sign(psi) (e_perp / d + t_perp / |g|)``, e_perp the
    heading's normal and t_perp the normal of the direction to the centre; the row asks
    ``a . v dt >= -gamma max(H, 0) / share``, which v = 0 meets.

    Returns:
        Which constraints have a row (…) bool, and their unit normals (…, 2) and offsets (…)
        (m/s) in the form ``normal . v <= offset`` (zeros where there is no row).
    """
    xp = namespace(offset, theta)
    length = xp.hypot(offset[..., 0], offset[..., 1])
    floored = xp.maximum(length, MIN_GRADIENT)
    toward = -offset / floored[..., None]
    psi = wrap_angle(axis - xp.arctan2(toward[..., 1], toward[..., 0]))
    ahead = table.present & (xp.abs(psi) < math.pi / 2) & (length > table.radius)
    turning = turning_radius(limits)
    margin = turning * (1 - xp.sin(xp.abs(psi)))
    heading_normal = xp.stack((-xp.sin(theta), xp.cos(theta)), axis=-1)
    toward_normal = xp.stack((-toward[..., 1], toward[..., 0]), axis=-1)
    side = xp.where(psi >= 0, 1.0, -1.0)
    gain = 2 * (table.radius + margin) * turning * xp.cos(psi) * side
    a = 2 * offset + gain[..., None] * (heading_normal / limits.length + toward_normal / floored[..., None])
    size = xp.where(ahead, xp.hypot(a[..., 0], a[..., 1]), 1.0)
    value = xp.maximum(length**2 - (table.radius + margin) ** 2, 0.0)
    share = xp.where(ahead, table.share, 1.0)
    normal = xp.where(ahead[..., None], -a / size[..., None], 0.0)
    return ahead, normal, xp.where(ahead, gamma * value / (share * dt * size), 0.0)
