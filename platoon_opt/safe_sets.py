"""Each unit's safe achievable set: its achievable set cut by its barrier rows.

``SafeSets`` holds, per unit, the rows of its achievable set (``limits.unit_rows``: the steering
sector's two half-planes, and in polygon mode the inscribed polygon's edges), the speed disk and
its barrier half-planes (``safety.barriers``), the latter relaxed where a unit starts unsafe.
Projections onto these small convex sets are exact: the nearest feasible point among the
candidates (the point itself, its projection onto each line and the circle, each pair's
intersection) is the projection, because the projection lies in the relative interior of a face
cut out by at most two active constraints.

Shapes: n units, k rows per unit; velocities (n, 2) in m/s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.limits import AchievableSets, unit_rows
from platoon_opt.safety import SafetyParams, barriers
from platoon_opt.vehicle import PlatoonState, VehicleLimits

# A candidate is feasible within this (m/s), relative to the radius.
TOLERANCE = 1e-12
# Units projected at once: the candidates of a chunk take about 25 k^2 floats per unit.
_CHUNK = 2048
# Bisection steps for the least relaxation of an unsafe unit's barrier rows.
_BISECTIONS = 60
# The faces a projection lies on (``SafeSets.project_onto_faces``).
INTERIOR, LINE, ARC, VERTEX = 0, 1, 2, 3


@dataclass(frozen=True)
class SafeSets:
    """Safe achievable sets, one per unit: ``normals[i] @ v <= offsets[i]`` and ``|v| <= radius``.

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
    """

    sets: AchievableSets
    normals: np.ndarray
    offsets: np.ndarray
    fixed: int
    radius: float
    slack: np.ndarray
    worst: np.ndarray

    @classmethod
    def build(
        cls,
        state: PlatoonState,
        obstacles: CircularObstacles,
        limits: VehicleLimits,
        dt: float,
        sets: AchievableSets,
        params: SafetyParams,
        *,
        speed: str = "cone",
        sides: int = 16,
    ) -> SafeSets:
        """The safe sets of ``sets``'s units in a speed model (``speed``: "cone", the exact disk,
        or "polygon", the inscribed ``sides``-gon, as ``limits.unit_rows``). A unit whose set is
        empty (only from an unsafe state) gets the least uniform relaxation of its barrier rows
        that makes it non-empty."""
        rows = barriers(state, obstacles, limits, dt, sets, params)
        own, own_offsets = unit_rows(sets, speed, sides, limits.max_speed)
        normals = np.concatenate((own, rows.normals), axis=1)
        offsets = np.concatenate((own_offsets, rows.offsets), axis=1)
        fixed, radius = own.shape[1], limits.max_speed
        slack = np.zeros(state.n)
        unsafe = np.flatnonzero(np.min(rows.offsets, axis=1, initial=0.0) < 0)
        if unsafe.size:
            slack[unsafe] = _least_relaxation(normals[unsafe], offsets[unsafe], fixed, radius)
            offsets[unsafe, fixed:] += slack[unsafe, None]
        return cls(sets, normals, offsets, fixed, radius, slack, rows.worst)

    @property
    def barrier_normals(self) -> np.ndarray:
        """The barrier rows (n, k, 2) alone."""
        return self.normals[:, self.fixed :]

    @property
    def barrier_offsets(self) -> np.ndarray:
        """Their offsets (n, k), m/s, relaxed."""
        return self.offsets[:, self.fixed :]

    def project(self, velocity: np.ndarray) -> np.ndarray:
        """Euclidean projection (n, 2) of each velocity onto its safe set, m/s."""
        return self.project_onto_faces(velocity)[0]

    def project_onto_faces(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The projection (n, 2), the face it lies on (n,): ``INTERIOR`` (the velocity itself),
        ``LINE`` (inside one row's line), ``ARC`` (on the disk's circle) or ``VERTEX`` (a corner),
        and the row of a ``LINE`` face (n,), for the Jacobian of the projection."""
        velocity = np.asarray(velocity, dtype=float)
        n, k = self.offsets.shape
        out, face, row = np.empty_like(velocity), np.empty(n, dtype=int), np.empty(n, dtype=int)
        for start in range(0, n, _CHUNK):
            part = slice(start, start + _CHUNK)
            out[part], _, chosen = _nearest(
                velocity[part], self.normals[part], self.offsets[part], self.radius
            )
            face[part] = np.select([chosen == 0, chosen <= k, chosen == k + 1], [INTERIOR, LINE, ARC], VERTEX)
            row[part] = np.clip(chosen - 1, 0, k - 1) if k else 0
        return out, face, row

    def support(self, direction: np.ndarray) -> np.ndarray:
        """A point (n, 2) of each safe set maximizing ``direction[i] . v``, m/s: a corner, or the
        circle's point along the direction if it is in the set."""
        direction = np.asarray(direction, dtype=float)
        out = np.empty_like(direction)
        for start in range(0, out.shape[0], _CHUNK):
            part = slice(start, start + _CHUNK)
            out[part] = _support(direction[part], self.normals[part], self.offsets[part], self.radius)
        return out

    def take(self, index: np.ndarray) -> SafeSets:
        """The safe sets of the units ``index`` (indices) alone."""
        return SafeSets(
            self.sets.take(index),
            self.normals[index],
            self.offsets[index],
            self.fixed,
            self.radius,
            self.slack[index],
            self.worst[index],
        )

    def violation(self, velocity: np.ndarray) -> np.ndarray:
        """Largest violation (n,) of each unit's rows and disk at ``velocity`` (n, 2), m/s (<= 0
        inside)."""
        rows = np.einsum("ikj,ij->ik", self.normals, velocity) - self.offsets
        return np.maximum(np.max(rows, axis=1), np.hypot(velocity[:, 0], velocity[:, 1]) - self.radius)


def _candidates(
    velocity: np.ndarray, normals: np.ndarray, offsets: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate points (n, c, 2) of the projection of ``velocity`` and whether each exists."""
    n, k = offsets.shape
    real = np.any(normals != 0.0, axis=2)
    tangent = np.stack((-normals[..., 1], normals[..., 0]), axis=-1)
    foot = offsets[..., None] * normals
    # The foot plus the tangential part, not velocity - (n . velocity - offset) n: for a velocity
    # far outside (the dual's iterates reach 1e5 m/s) that difference loses its last digits
    # across the line, and the point would fail its own row's tolerance.
    on_line = foot + np.einsum("ikj,ij->ik", tangent, velocity)[..., None] * tangent
    speed = np.hypot(velocity[:, 0], velocity[:, 1])
    on_circle = velocity * np.minimum(1.0, radius / np.maximum(speed, 1e-300))[:, None]
    a, b = np.triu_indices(k, 1)
    na, nb, oa, ob = normals[:, a], normals[:, b], offsets[:, a], offsets[:, b]
    det = na[..., 0] * nb[..., 1] - na[..., 1] * nb[..., 0]
    crossing = np.abs(det) > 1e-12
    safe_det = np.where(crossing, det, 1.0)
    vertex = np.stack(
        ((oa * nb[..., 1] - ob * na[..., 1]) / safe_det, (na[..., 0] * ob - nb[..., 0] * oa) / safe_det),
        axis=-1,
    )
    half_chord = np.sqrt(np.maximum(radius**2 - offsets**2, 0.0))
    meets = real & (np.abs(offsets) <= radius)
    points = np.concatenate(
        (
            velocity[:, None, :],
            on_line,
            on_circle[:, None, :],
            vertex,
            foot + half_chord[..., None] * tangent,
            foot - half_chord[..., None] * tangent,
            np.zeros((n, 1, 2)),
        ),
        axis=1,
    )
    exists = np.concatenate(
        (
            np.ones((n, 1), bool),
            real,
            np.ones((n, 1), bool),
            crossing & real[:, a] & real[:, b],
            meets,
            meets,
            np.ones((n, 1), bool),
        ),
        axis=1,
    )
    return points, exists


def _excess(points: np.ndarray, exists: np.ndarray, normals: np.ndarray, offsets: np.ndarray, radius: float):
    """Largest violation (n, c) of each candidate point (n, c, 2) of its unit's rows and disk;
    inf for candidates that do not exist."""
    rows = np.einsum("icj,ikj->ick", points, normals)
    excess = np.maximum(
        np.max(rows - offsets[:, None, :], axis=2, initial=-np.inf),
        np.hypot(points[..., 0], points[..., 1]) - radius,
    )
    return np.where(exists, excess, np.inf)


def _nearest(
    velocity: np.ndarray, normals: np.ndarray, offsets: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The projection (n, 2) of each velocity onto its set, whether the set is non-empty (n,) and
    the candidate chosen (n,, its index in ``_candidates``' order). An empty set (to the
    tolerance) answers its least violating candidate."""
    points, exists = _candidates(velocity, normals, offsets, radius)
    excess = _excess(points, exists, normals, offsets, radius)
    feasible = excess <= TOLERANCE * max(radius, 1.0)
    # |p - velocity|^2 less |velocity|^2: the same order, without rounding at the scale of
    # |velocity|^2 (far velocities made near ties of candidates 1e-3 m/s apart).
    distance = np.sum(points * (points - 2 * velocity[:, None, :]), axis=2)
    score = np.where(feasible, distance, np.inf)
    found = feasible.any(axis=1)
    best = np.where(found, np.argmin(score, axis=1), np.argmin(excess, axis=1))
    return points[np.arange(points.shape[0]), best], found, best


def _support(direction: np.ndarray, normals: np.ndarray, offsets: np.ndarray, radius: float) -> np.ndarray:
    """``SafeSets.support`` of one chunk: the best feasible corner or circle point."""
    points, exists = _candidates(direction, normals, offsets, radius)
    length = np.hypot(direction[:, 0], direction[:, 1])
    along = direction * (radius / np.maximum(length, 1e-300))[:, None]
    k = offsets.shape[1]
    # The corners (from the pairs of lines on) and the circle's point along the direction.
    points = np.concatenate((points[:, k + 2 :], along[:, None]), axis=1)
    exists = np.concatenate((exists[:, k + 2 :], (length > 0)[:, None]), axis=1)
    excess = _excess(points, exists, normals, offsets, radius)
    value = np.where(
        excess <= TOLERANCE * max(radius, 1.0), np.einsum("icj,ij->ic", points, direction), -np.inf
    )
    return points[np.arange(points.shape[0]), np.argmax(value, axis=1)]


def _least_relaxation(normals: np.ndarray, offsets: np.ndarray, fixed: int, radius: float) -> np.ndarray:
    """Least s (u,) >= 0 such that relaxing the barrier rows (columns ``fixed:``) by s leaves each
    set non-empty, by bisection (slightly above the least, so that the set has a point to the
    tolerance)."""
    zero = np.zeros((offsets.shape[0], 2))
    empty = ~_nearest(zero, normals, offsets, radius)[1]
    # The origin meets every row of the achievable set, and every barrier row relaxed this far.
    least = np.maximum(-np.min(offsets[:, fixed:], axis=1), 0.0) + TOLERANCE * max(radius, 1.0)
    high = np.where(empty, least, 0.0)
    low = np.zeros_like(high)
    for _ in range(_BISECTIONS):
        middle = 0.5 * (low + high)
        relaxed = offsets.copy()
        relaxed[:, fixed:] += middle[:, None]
        nonempty = _nearest(zero, normals, relaxed, radius)[1]
        high, low = np.where(nonempty, middle, high), np.where(nonempty, low, middle)
    return high
