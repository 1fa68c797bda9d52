"""Each unit's safe achievable set: its achievable set cut by its barrier rows.

``SafeSets`` holds, per unit, the rows of its achievable set (``limits.unit_rows``: the steering
sector's two half-planes, and in polygon mode the inscribed polygon's edges), the speed disk and
its barrier half-planes (``safety.barriers``), the latter relaxed where a unit starts unsafe.
Projections onto these small convex sets are exact: a point outside projects onto the set's
boundary, made of the rows' lines clipped to the set and of arcs of the circle; the nearest point
of each clipped line (the clamp of the point's position along it) and the point pulled onto the
circle are the candidates, and the nearest feasible one is the projection (O(k^2) per unit).

The build and the projection (``project_onto_faces``, ``support``) are written once for numpy
and JAX (``platoon_opt.arrays.namespace``): the dual allocator's compiled Newton method takes the
safe sets as one more kind of set, and its kernel builds them in fixed shapes (``SafeSets.build``
with a ``capacity``); the host builds every constraint's rows.

Shapes: n units, k rows per unit; velocities (n, 2) in m/s.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from platoon_opt.arrays import namespace, pytree, while_loop
from platoon_opt.avoidance import CircularObstacles
from platoon_opt.barrier_constraints import Capacity, nearest_constraints
from platoon_opt.limits import AchievableSets, unit_rows
from platoon_opt.safety import SafetyParams, barrier_rows, barriers, search
from platoon_opt.vehicle import PlatoonState, VehicleLimits

# A candidate is feasible within this (m/s), relative to the radius.
TOLERANCE = 1e-12
# Units projected at once by numpy: the support's candidates of a chunk take about 25 k^2 floats per unit.
_CHUNK = 2048
# Rows whose normals' cross product is within this are parallel (no vertex between them).
_PARALLEL = 1e-12
# Bisection steps for the least relaxation of an unsafe unit's barrier rows.
_BISECTIONS = 60
# The faces a projection lies on (``SafeSets.project_onto_faces``).
INTERIOR, LINE, ARC, VERTEX = 0, 1, 2, 3


@pytree(data=("sets", "normals", "offsets", "radius", "slack", "worst", "overflow"), static=("fixed",))
@dataclass(frozen=True)
class SafeSets:
    """Safe achievable sets, one per unit: ``normals[i] @ v <= offsets[i]`` and ``|v| <= radius``.

    Numpy arrays; JAX ones inside a compiled solve (a pytree, ``fixed`` static).

    Attributes:
        sets: the achievable sectors (gear, steering range).
        normals: (n, f + k, 2): the f rows of the achievable set, then the k barrier rows (zero
            rows pad units with fewer).
        offsets: (n, f + k) m/s, barrier offsets after the relaxation ``slack``.
        fixed: f.
        radius: the speed disk (m/s).
        slack: (n,) m/s by which each unit's barrier rows were relaxed (0 where its safe set was
            not empty: always in a safe state).
        worst: (n,) least barrier value h of each unit (m^2; negative: unsafe).
        overflow: (n,) bool: units whose barrier rows a compiled build could not hold
            (``safety.Barriers``); never on the host.
    """

    sets: AchievableSets
    normals: np.ndarray
    offsets: np.ndarray
    fixed: int
    radius: float
    slack: np.ndarray
    worst: np.ndarray
    overflow: np.ndarray

    @classmethod
    def build(
        cls,
        state: PlatoonState,
        obstacles: CircularObstacles,
        limits: VehicleLimits,
        dt: Any,
        sets: AchievableSets,
        params: SafetyParams,
        *,
        speed: str = "cone",
        sides: int = 16,
        capacity: Capacity | None = None,
    ) -> SafeSets:
        """The safe sets of ``sets``'s units in a speed model (``speed``: "cone", the exact disk,
        or "polygon", the inscribed ``sides``-gon, as ``limits.unit_rows``). A unit whose set is
        empty (only from an unsafe state) gets the least uniform relaxation of its barrier rows
        that makes it non-empty.

        ``capacity`` None: on the host (numpy), every constraint (``safety.barriers``). Else a
        build of fixed shapes for compiled code (numpy or JAX; ``nearest_constraints``):
        ``capacity``'s slots and rows, ``overflow`` marking the units they did not hold;
        ``params`` is not checked (``SafetyParams.check``)."""
        if capacity is None:
            rows = barriers(state, obstacles, limits, dt, sets, params)
            overflow = rows.overflow
        else:
            table, overflow = nearest_constraints(
                state.positions,
                obstacles,
                params.obstacle_margin,
                params.safety_distance,
                search(params, limits, dt),
                capacity,
            )
            rows = barrier_rows(state, table, sets, limits, dt, params, rows=capacity.rows)
            overflow = overflow | rows.overflow
        xp = namespace(rows.normals, sets.axis)
        own, own_offsets = unit_rows(sets, speed, sides, limits.max_speed)
        normals = xp.concatenate((own, rows.normals), axis=1)
        offsets = xp.concatenate((own_offsets, rows.offsets), axis=1)
        fixed, radius = own.shape[1], limits.max_speed
        unsafe = xp.min(rows.offsets, axis=1, initial=0.0) < 0
        if xp is np:
            # Only the unsafe units (rare) on the host; compiled code relaxes every unit (0 where
            # the set is not empty) in a loop that ends at once when none is.
            slack = np.zeros(state.n)
            if np.any(unsafe):
                slack[unsafe] = _least_relaxation(normals[unsafe], offsets[unsafe], fixed, radius)
        else:
            slack = xp.where(unsafe, _least_relaxation(normals, offsets, fixed, radius), 0.0)
        offsets = xp.where(xp.arange(offsets.shape[1]) >= fixed, offsets + slack[:, None], offsets)
        return cls(sets, normals, offsets, fixed, radius, slack, rows.worst, overflow)

    @property
    def barrier_normals(self) -> np.ndarray:
        """The barrier rows (n, k, 2) alone."""
        return self.normals[:, self.fixed :]

    @property
    def barrier_offsets(self) -> np.ndarray:
        """Their offsets (n, k), m/s, relaxed."""
        return self.offsets[:, self.fixed :]

    def project(self, velocity: Any) -> Any:
        """Euclidean projection (n, 2) of each velocity onto its safe set, m/s."""
        return self.project_onto_faces(velocity)[0]

    def project_onto_faces(self, velocity: Any) -> tuple[Any, Any, Any]:
        """The projection (n, 2), the face it lies on (n,): ``INTERIOR`` (the velocity itself),
        ``LINE`` (inside one row's line), ``ARC`` (on the disk's circle) or ``VERTEX`` (a corner),
        and the row of a ``LINE`` face (n,), for the Jacobian of the projection."""
        xp = namespace(velocity, self.normals)

        def faces(velocity: Any, normals: Any, offsets: Any) -> tuple[Any, Any, Any]:
            point, _, face, row = _nearest(velocity, normals, offsets, self.radius)
            return point, face, row

        return _chunked(faces, xp.asarray(velocity, dtype=float), self.normals, self.offsets)

    def sliding(self, velocity: Any) -> Any:
        """The velocity (n, 2) nearest to ``velocity`` that the barrier rows and the speed disk
        allow, whatever the steering (the achievable set's rows dropped), m/s: a velocity pushing
        into an obstacle or a neighbour keeps the part that slides along its rows."""
        xp = namespace(velocity, self.normals)
        barrier = xp.arange(self.normals.shape[1]) >= self.fixed
        free = SafeSets(
            self.sets,
            xp.where(barrier[None, :, None], self.normals, 0.0),
            xp.where(barrier[None, :], self.offsets, 0.0),
            self.fixed,
            self.radius,
            self.slack,
            self.worst,
            self.overflow,
        )
        return free.project(velocity)

    def support(self, direction: Any) -> Any:
        """A point (n, 2) of each safe set maximizing ``direction[i] . v``, m/s: a corner, or the
        circle's point along the direction if it is in the set."""
        xp = namespace(direction, self.normals)

        def best(direction: Any, normals: Any, offsets: Any) -> tuple[Any]:
            return (_support(direction, normals, offsets, self.radius),)

        return _chunked(best, xp.asarray(direction, dtype=float), self.normals, self.offsets)[0]

    def take(self, index: Any) -> SafeSets:
        """The safe sets of the units ``index`` (indices, or a slice) alone."""
        return SafeSets(
            self.sets.take(index),
            self.normals[index],
            self.offsets[index],
            self.fixed,
            self.radius,
            self.slack[index],
            self.worst[index],
            self.overflow[index],
        )

    def violation(self, velocity: np.ndarray) -> np.ndarray:
        """Largest violation (n,) of each unit's rows and disk at ``velocity`` (n, 2), m/s (<= 0
        inside)."""
        rows = np.einsum("ikj,ij->ik", self.normals, velocity) - self.offsets
        return np.maximum(np.max(rows, axis=1), np.hypot(velocity[:, 0], velocity[:, 1]) - self.radius)


def _chunked(function: Any, velocity: Any, normals: Any, offsets: Any) -> tuple[Any, ...]:
    """``function(velocity, normals, offsets)`` (a tuple of per-unit arrays): in chunks of
    ``_CHUNK`` units with numpy (memory), at once when traced (static shapes)."""
    if namespace(velocity, normals) is not np or velocity.shape[0] <= _CHUNK:
        return function(velocity, normals, offsets)
    parts = [
        function(
            velocity[start : start + _CHUNK], normals[start : start + _CHUNK], offsets[start : start + _CHUNK]
        )
        for start in range(0, velocity.shape[0], _CHUNK)
    ]
    return tuple(np.concatenate(column) for column in zip(*parts))


@functools.cache
def _pairs(k: int) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (a, b), a < b, of k rows: built once per k (numpy's ``triu_indices`` took a
    seventh of a projection of 8 units)."""
    return np.triu_indices(k, 1)


def _lines(normals: Any, offsets: Any, radius: Any) -> tuple[Any, Any, Any, Any]:
    """Each row's line ``foot + t tangent``: whether the row is real (not padding) (n, k), its
    unit tangent and foot (n, k, 2), and half its chord of the disk (n, k; 0 where it misses)."""
    xp = namespace(normals, offsets)
    real = xp.any(normals != 0.0, axis=2)
    tangent = xp.stack((-normals[..., 1], normals[..., 0]), axis=-1)
    foot = offsets[..., None] * normals
    half_chord = xp.sqrt(xp.maximum(radius**2 - offsets**2, 0.0))
    return real, tangent, foot, half_chord


def _corners(normals: Any, offsets: Any, radius: Any) -> tuple[Any, Any]:
    """The corners (n, c, 2) of each set's boundary and whether each exists: each pair of lines'
    intersection, each line's intersections with the circle, and the origin."""
    xp = namespace(normals, offsets)
    n, k = offsets.shape
    real, tangent, foot, half_chord = _lines(normals, offsets, radius)
    a, b = _pairs(k)
    na, nb, oa, ob = normals[:, a], normals[:, b], offsets[:, a], offsets[:, b]
    det = na[..., 0] * nb[..., 1] - na[..., 1] * nb[..., 0]
    crossing = xp.abs(det) > _PARALLEL
    safe_det = xp.where(crossing, det, 1.0)
    vertex = xp.stack(
        ((oa * nb[..., 1] - ob * na[..., 1]) / safe_det, (na[..., 0] * ob - nb[..., 0] * oa) / safe_det),
        axis=-1,
    )
    meets = real & (xp.abs(offsets) <= radius)
    points = xp.concatenate(
        (
            vertex,
            foot + half_chord[..., None] * tangent,
            foot - half_chord[..., None] * tangent,
            xp.zeros((n, 1, 2)),
        ),
        axis=1,
    )
    exists = xp.concatenate(
        (crossing & real[:, a] & real[:, b], meets, meets, xp.ones((n, 1), dtype=bool)), axis=1
    )
    return points, exists


def _excess(points: Any, exists: Any, normals: Any, offsets: Any, radius: Any) -> Any:
    """Largest violation (n, c) of each candidate point (n, c, 2) of its unit's rows and disk;
    inf for candidates that do not exist."""
    xp = namespace(points, normals)
    rows = xp.einsum("icj,ikj->ick", points, normals)
    excess = xp.maximum(
        xp.max(rows - offsets[:, None, :], axis=2, initial=-np.inf),
        xp.hypot(points[..., 0], points[..., 1]) - radius,
    )
    return xp.where(exists, excess, np.inf)


def _pick(points: Any, best: Any) -> Any:
    """``points[i, best[i]]`` (n, 2) of candidates (n, c, 2)."""
    return namespace(points).take_along_axis(points, best[:, None, None], axis=1)[:, 0]


def _nearest(velocity: Any, normals: Any, offsets: Any, radius: Any) -> tuple[Any, Any, Any, Any]:
    """The projection (n, 2) of each velocity onto its set, whether the set is non-empty (n,), the
    face the projection lies on (n,: ``INTERIOR``, ``LINE``, ``ARC`` or ``VERTEX``) and the row of
    a ``LINE`` face (n,). An empty set (to the tolerance) answers its least violating candidate.

    Each row i's line is clipped to the set: along it (``foot + t tangent``) row j holds where
    ``t (n_j . tangent_i) <= o_j - n_j . foot_i``, the disk where ``|t| <= sqrt(R^2 - o_i^2)``.
    The clamp of the velocity's t to that interval is the line's nearest point of the set (a
    vertex at either end). Candidates are checked against every row to the tolerance, as the
    clipping's divisions round."""
    xp = namespace(velocity, normals)
    k = offsets.shape[1]
    real, tangent, foot, half_chord = _lines(normals, offsets, radius)
    # [unit, line i, row j]: row j along line i reads t along <= room.
    along = xp.einsum("ijc,ikc->ikj", normals, tangent)
    room = offsets[:, None, :] - xp.einsum("ijc,ikc->ikj", normals, foot)
    ahead, behind = along > _PARALLEL, along < -_PARALLEL
    upper = xp.min(xp.where(ahead, room / xp.where(ahead, along, 1.0), xp.inf), axis=2)
    lower = xp.max(xp.where(behind, room / xp.where(behind, along, 1.0), -xp.inf), axis=2)
    # A row parallel to the line either holds along all of it or excludes it.
    excluded = xp.any(~ahead & ~behind & (room < -TOLERANCE * xp.maximum(radius, 1.0)), axis=2)
    upper, lower = xp.minimum(upper, half_chord), xp.maximum(lower, -half_chord)
    position = xp.einsum("ikc,ic->ik", tangent, velocity)
    # The foot plus the tangential part, not velocity - (n . velocity - offset) n: for a velocity
    # far outside (the dual's iterates reach 1e5 m/s) that difference loses its last digits
    # across the line, and the point would fail its own row's tolerance.
    on_line = foot + xp.clip(position, lower, upper)[..., None] * tangent
    speed = xp.hypot(velocity[:, 0], velocity[:, 1])
    on_circle = velocity * xp.minimum(1.0, radius / xp.maximum(speed, 1e-300))[:, None]
    points = xp.concatenate((velocity[:, None, :], on_line, on_circle[:, None, :]), axis=1)
    always = xp.ones((velocity.shape[0], 1), dtype=bool)
    clipped = real & ~excluded & (xp.abs(offsets) <= radius) & (lower <= upper)
    exists = xp.concatenate((always, clipped, always), axis=1)
    excess = _excess(points, exists, normals, offsets, radius)
    feasible = excess <= TOLERANCE * xp.maximum(radius, 1.0)
    # |p - velocity|^2 less |velocity|^2: the same order, without rounding at the scale of
    # |velocity|^2 (far velocities made near ties of candidates 1e-3 m/s apart).
    distance = xp.sum(points * (points - 2 * velocity[:, None, :]), axis=2)
    found = xp.any(feasible, axis=1)
    best = xp.where(found, xp.argmin(xp.where(feasible, distance, np.inf), axis=1), xp.argmin(excess, axis=1))
    row = xp.clip(best - 1, 0, max(k - 1, 0))
    # On a line strictly inside its clipped interval: a LINE face; at either end: a vertex.
    inside = xp.take_along_axis((position > lower) & (position < upper), row[:, None], axis=1)[:, 0]
    face = xp.where(best == 0, INTERIOR, xp.where(best == k + 1, ARC, xp.where(inside, LINE, VERTEX)))
    return _pick(points, best), found, face, row


def _support(direction: Any, normals: Any, offsets: Any, radius: Any) -> Any:
    """``SafeSets.support`` of one chunk: the best feasible corner or circle point."""
    xp = namespace(direction, normals)
    points, exists = _corners(normals, offsets, radius)
    length = xp.hypot(direction[:, 0], direction[:, 1])
    along = direction * (radius / xp.maximum(length, 1e-300))[:, None]
    # The corners and the circle's point along the direction.
    points = xp.concatenate((points, along[:, None]), axis=1)
    exists = xp.concatenate((exists, (length > 0)[:, None]), axis=1)
    excess = _excess(points, exists, normals, offsets, radius)
    value = xp.where(
        excess <= TOLERANCE * xp.maximum(radius, 1.0), xp.einsum("icj,ij->ic", points, direction), -np.inf
    )
    return _pick(points, xp.argmax(value, axis=1))


def _least_relaxation(normals: Any, offsets: Any, fixed: int, radius: Any) -> Any:
    """Least s (u,) >= 0 such that relaxing the barrier rows (columns ``fixed:``) by s leaves each
    set non-empty, by bisection (slightly above the least, so that the set has a point to the
    tolerance): numpy, or a ``lax.while_loop`` that ends as soon as no unit's interval is open
    (at once if every set is non-empty)."""
    xp = namespace(normals, offsets)
    zero = xp.zeros((offsets.shape[0], 2))
    empty = ~_nearest(zero, normals, offsets, radius)[1]
    # The origin meets every row of the achievable set, and every barrier row relaxed this far.
    barrier = xp.arange(offsets.shape[1]) >= fixed
    least = xp.maximum(-xp.min(xp.where(barrier, offsets, xp.inf), axis=1), 0.0) + TOLERANCE * xp.maximum(
        radius, 1.0
    )
    state = (0, xp.zeros(offsets.shape[0]), xp.where(empty, least, 0.0))

    def halve(state: tuple[Any, Any, Any]) -> tuple[Any, Any, Any]:
        step, low, high = state
        middle = 0.5 * (low + high)
        nonempty = _nearest(zero, normals, xp.where(barrier, offsets + middle[:, None], offsets), radius)[1]
        return step + 1, xp.where(nonempty, low, middle), xp.where(nonempty, middle, high)

    def open_(state: tuple[Any, Any, Any]) -> Any:
        # Once high <= low (0 for a non-empty set) no bisection moves either end.
        return (state[0] < _BISECTIONS) & xp.any(state[2] > state[1])

    return while_loop(open_, halve, state)[2]
