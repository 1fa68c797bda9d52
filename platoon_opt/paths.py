"""The target's path: where the holonomic target is at time t, and its velocity, exactly.

A path is made of pieces (a straight leg, a circular arc, a spline segment), each travelled at its
own constant speed, and holds still at its last point once travelled. Position and velocity come
from one formula, so the velocity (f_d' of the means) is the exact time derivative of the position
(f_d): the unit tangent at the arc length travelled times the piece's speed.

One class per way of computing the geometry (the scenario file's ``target.kind``,
docs/scenarios.md):

* ``TargetPath``: straight legs through waypoints ("polyline"), the shape of the paper's path;
* ``ArcPath``: straight lines and circular arcs in closed form: a polyline whose corners are
  rounded with a turn radius ("rounded", ``rounded``) and a circle ("circle", ``circle``);
* ``CurvePath`` (``platoon_opt.curves``): smooth parametric curves whose arc length is tabulated
  on the host and inverted at run time ("figure_eight", "spline").

Each is a pytree (``arrays.pytree``) whose arrays are leaves of shapes the scenario fixes, so that
``at(t)`` runs inside the compiled loop with ``t`` traced: no Python branch on a traced value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from platoon_opt.arrays import namespace, pytree, searchsorted


class Path(Protocol):
    """What the goal (``scenarios.Goal``), the initial state and the reports need of a path."""

    def at(self, t: Any) -> tuple[Any, Any]:
        """Position (2,) m and velocity (2,) m/s at time ``t`` (s; a float, or traced)."""
        ...

    @property
    def length(self) -> float:
        """Path length (m)."""
        ...

    @property
    def speed(self) -> Any:
        """The speed (m/s); the fastest piece's where pieces differ (what reports show)."""
        ...

    @property
    def waypoints(self) -> Any:
        """(k, 2) m: the points where the pieces start and the last point (what reports show)."""
        ...

    def outline(self) -> tuple[np.ndarray, float]:
        """A polyline (M, 2) m and a margin (m) such that every point of the path lies within the
        margin of the polyline: what the obstacle field keeps its gap from (host only)."""
        ...


def travel(t: Any, starts: Any, speeds: Any, times: Any) -> tuple[Any, Any]:
    """Arc length travelled (m) at time ``t`` (s) and the index of the piece it lies on, for
    pieces starting at arc lengths ``starts`` (P + 1,) m, travelled at ``speeds`` (P,) m/s and
    entered at ``times`` (P + 1,) s. Before t = 0 the target is at the start; after the last
    piece the arc length keeps growing on it (the caller holds the target at its end)."""
    xp = namespace(t, starts, speeds, times)
    t = xp.maximum(t, 0.0)
    piece = xp.clip(searchsorted(times, t, side="right") - 1, 0, speeds.shape[0] - 1)
    return starts[piece] + speeds[piece] * (t - times[piece]), piece


def schedule(lengths: np.ndarray, speeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where (m) and when (s) each of the pieces of ``lengths`` (P,) m starts, travelled at
    ``speeds`` (P,) m/s, and where and when the last ends: two (P + 1,) arrays."""
    starts = np.concatenate((np.zeros(1), np.cumsum(lengths)))
    return starts, np.concatenate((np.zeros(1), np.cumsum(lengths / speeds)))


@pytree(data=("waypoints", "speed", "speeds"))
@dataclass(frozen=True)
class TargetPath:
    """A holonomic target moving through ``waypoints`` (k, 2) m on straight legs, at constant
    ``speed`` (m/s), or at ``speeds`` (k - 1,) m/s, one per leg (then ``speed`` is the fastest of
    them, for reports), then holding at the last waypoint."""

    waypoints: Any
    speed: Any
    speeds: Any = None

    # Computed at each call, not cached: a value cached inside a compiled loop would leak its
    # tracer out of it.
    @property
    def _cumulative(self) -> Any:
        """Arc length at each waypoint (k,), m."""
        xp = namespace(self.waypoints)
        legs = xp.linalg.norm(xp.diff(self.waypoints, axis=0), axis=1)
        return xp.concatenate((xp.zeros(1), xp.cumsum(legs)))

    @property
    def _directions(self) -> Any:
        """Unit direction of each leg (k - 1, 2)."""
        legs = namespace(self.waypoints).diff(self.waypoints, axis=0)
        return legs / namespace(legs).linalg.norm(legs, axis=1)[:, None]

    @property
    def length(self) -> float:
        """Path length (m)."""
        return float(self._cumulative[-1])

    def at(self, t: Any) -> tuple[Any, Any]:
        """Position (2,) m and velocity (2,) m/s at time ``t`` (s; a float, or traced)."""
        xp = namespace(t, self.waypoints, self.speeds)
        if self.waypoints.shape[0] == 1:
            return xp.asarray(self.waypoints[0]), xp.zeros(2)
        waypoints, cumulative = xp.asarray(self.waypoints), xp.asarray(self._cumulative)
        if self.speeds is None:
            # A constant speed: the arithmetic of the runs recorded before per-leg speeds (golden
            # tests), operation for operation.
            travelled = self.speed * xp.maximum(t, 0.0)
            leg = xp.clip(searchsorted(cumulative, travelled, side="right") - 1, 0, cumulative.shape[0] - 2)
            speed = self.speed
        else:
            speeds = xp.asarray(self.speeds)
            times = xp.concatenate((xp.zeros(1), xp.cumsum(xp.diff(cumulative) / speeds)))
            travelled, leg = travel(t, cumulative, speeds, times)
            speed = speeds[leg]
        direction = xp.asarray(self._directions)[leg]
        done = travelled >= cumulative[-1]
        along = waypoints[leg] + (travelled - cumulative[leg]) * direction
        return xp.where(done, waypoints[-1], along), xp.where(done, 0.0, speed * direction)

    def outline(self) -> tuple[np.ndarray, float]:
        """The waypoints themselves, margin 0."""
        return np.asarray(self.waypoints, dtype=float), 0.0


def arc_point(origin: Any, heading: Any, curvature: Any, sigma: Any) -> tuple[Any, Any]:
    """Position (..., 2) m and unit tangent (..., 2) at arc length ``sigma`` (...,) m along a line
    (``curvature`` 0) or a circular arc (signed curvature, 1/m, > 0 turning left) that starts at
    ``origin`` (..., 2) m with unit tangent ``heading`` (..., 2). The tangent is the exact
    derivative of the position in ``sigma``; 1 - cos is written 2 sin^2(x/2), exact for small x."""
    xp = namespace(origin, heading, curvature, sigma)
    normal = xp.stack((-heading[..., 1], heading[..., 0]), axis=-1)
    angle = curvature * sigma
    straight = curvature == 0
    bend = xp.where(straight, 1.0, curvature)
    along = xp.where(straight, sigma, xp.sin(angle) / bend)[..., None]
    across = xp.where(straight, 0.0, 2.0 * xp.sin(angle / 2) ** 2 / bend)[..., None]
    position = origin + along * heading + across * normal
    return position, xp.cos(angle)[..., None] * heading + xp.sin(angle)[..., None] * normal


# An arc of the outline spans at most this angle (rad): its chords stay within r (1 - cos 1 deg),
# 1.5e-4 of the radius, of the arc.
_OUTLINE_STEP = math.radians(2.0)


@pytree(data=("starts", "origins", "headings", "curvatures", "speeds", "times", "end"))
@dataclass(frozen=True)
class ArcPath:
    """Lines and circular arcs, each travelled at its own speed, in closed form.

    Attributes:
        starts: (P + 1,) arc length at each piece's start and at the end, m.
        origins: (P, 2) where each piece starts, m.
        headings: (P, 2) the unit tangent at each piece's start.
        curvatures: (P,) signed curvature, 1/m: 0 on a line, > 0 turning left.
        speeds: (P,) m/s.
        times: (P + 1,) when the target enters each piece, and reaches the end, s.
        end: (2,) the last point, where the target holds, m.
    """

    starts: Any
    origins: Any
    headings: Any
    curvatures: Any
    speeds: Any
    times: Any
    end: Any

    @classmethod
    def of(cls, pieces: list[tuple[Any, Any, float, float, float]]) -> ArcPath:
        """The path through ``pieces`` (origin (2,), heading (2,), curvature, length, speed), each
        starting where the one before ends."""
        origins, headings, curvatures, lengths, speeds = (
            np.array(column, dtype=float) for column in zip(*pieces)
        )
        starts, times = schedule(lengths, speeds)
        end, _ = arc_point(origins[-1], headings[-1], curvatures[-1], lengths[-1])
        return cls(starts, origins, headings, curvatures, speeds, times, end)

    @property
    def length(self) -> float:
        return float(self.starts[-1])

    @property
    def speed(self) -> float:
        return float(np.max(self.speeds))

    @property
    def waypoints(self) -> np.ndarray:
        return np.vstack((self.origins, self.end[None]))

    def at(self, t: Any) -> tuple[Any, Any]:
        """Position (2,) m and velocity (2,) m/s at time ``t`` (s; a float, or traced)."""
        xp = namespace(t, self.starts)
        starts, speeds, times = xp.asarray(self.starts), xp.asarray(self.speeds), xp.asarray(self.times)
        travelled, piece = travel(t, starts, speeds, times)
        origins, headings = xp.asarray(self.origins), xp.asarray(self.headings)
        position, tangent = arc_point(
            origins[piece], headings[piece], xp.asarray(self.curvatures)[piece], travelled - starts[piece]
        )
        done = travelled >= starts[-1]
        return xp.where(done, xp.asarray(self.end), position), xp.where(done, 0.0, speeds[piece] * tangent)

    def outline(self) -> tuple[np.ndarray, float]:
        """Each line's start, and points at most 2 degrees apart along each arc (an arc of more
        than a lap: one lap and then on to its end, the rest repeating the circle); the margin is
        the largest chord's sagitta."""
        points, margin = [], 0.0
        for origin, heading, curvature, length in zip(
            self.origins, self.headings, self.curvatures, np.diff(self.starts)
        ):
            if curvature == 0:
                points.append(origin[None])
                continue
            angle = abs(curvature) * length
            if angle > 2 * math.pi:
                angle = 2 * math.pi + angle % (2 * math.pi)
            steps = max(1, math.ceil(angle / _OUTLINE_STEP))
            sigma = np.linspace(0.0, angle / abs(curvature), steps, endpoint=False)
            points.append(arc_point(origin, heading, curvature, sigma)[0])
            margin = max(margin, (1 - math.cos(angle / steps / 2)) / abs(curvature))
        return np.vstack([*points, self.end[None]]), margin


def turns(waypoints: np.ndarray) -> np.ndarray:
    """The signed turn (rad, in (-pi, pi], > 0 to the left) at each inner waypoint of a polyline
    (k - 2,), whose consecutive waypoints (k, 2) m are distinct."""
    legs = np.diff(waypoints, axis=0)
    before, after = legs[:-1], legs[1:]
    cross = before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0]
    return np.arctan2(cross, np.sum(before * after, axis=1))


def rounded(waypoints: np.ndarray, turn_radius: float, speeds: np.ndarray) -> ArcPath:
    """The polyline through ``waypoints`` (k >= 2, 2) m with each corner replaced by the circular
    arc of radius ``turn_radius`` (m) tangent to both its legs, so that the direction never jumps.

    A corner turning by theta is cut ``turn_radius tan(|theta| / 2)`` m back along both legs; leg j
    is travelled at ``speeds[j]`` (m/s), an arc at the slower of its two legs' speeds. The caller
    checks that the cuts fit their legs (``corner_cuts``) and that no corner is a reversal.
    """
    legs = np.diff(waypoints, axis=0)
    lengths = np.linalg.norm(legs, axis=1)
    directions = legs / lengths[:, None]
    turn = turns(waypoints)
    cut = corner_cuts(waypoints, turn_radius)
    pieces: list[tuple[Any, Any, float, float, float]] = []
    for j in range(len(legs)):
        line = lengths[j] - cut[j] - cut[j + 1]
        if line > 0:  # a leg used up by its two arcs has no straight part left
            pieces.append((waypoints[j] + cut[j] * directions[j], directions[j], 0.0, line, speeds[j]))
        if j + 1 < len(legs) and turn[j] != 0:
            corner = waypoints[j + 1] - cut[j + 1] * directions[j]
            curvature = math.copysign(1.0 / turn_radius, turn[j])
            speed = min(speeds[j], speeds[j + 1])
            pieces.append((corner, directions[j], curvature, turn_radius * abs(turn[j]), speed))
    return ArcPath.of(pieces)


def corner_cuts(waypoints: np.ndarray, turn_radius: float) -> np.ndarray:
    """How far (m) each waypoint's rounding arc starts before it and ends after it (k,): 0 at the
    ends, ``turn_radius tan(|theta| / 2)`` at a corner turning by theta (about 1.6e16 turn radii
    at a reversal, which no leg fits)."""
    return np.concatenate(([0.0], turn_radius * np.tan(np.abs(turns(waypoints)) / 2), [0.0]))


def circle(
    center: np.ndarray, radius: float, laps: float, start_angle: float, clockwise: bool, speed: float
) -> ArcPath:
    """``laps`` turns of the circle of ``radius`` (m) around ``center`` (2,) m at ``speed`` (m/s),
    starting at polar angle ``start_angle`` (rad), counter-clockwise unless ``clockwise``."""
    radial = np.array([math.cos(start_angle), math.sin(start_angle)])
    turn = -1.0 if clockwise else 1.0
    heading = turn * np.array([-radial[1], radial[0]])
    return ArcPath.of(
        [(center + radius * radial, heading, turn / radius, 2 * math.pi * radius * laps, speed)]
    )
