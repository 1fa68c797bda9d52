"""Smooth parametric target paths, travelled by arc length: a figure-eight and a spline.

A curve c(u) (m) is given in closed form in a parameter u that is not arc length. On the host,
when the scenario is read, the arc length s(u) is tabulated at nodes u_i (8-point Gauss-Legendre
on each interval: exact to rounding for these smooth integrands), with the exact slopes
du/ds = 1 / |c'(u_i)|. At run time u(s) is the cubic Hermite interpolant of those values and slopes
(``searchsorted`` and one cubic), and the target is at c(u(s)) with velocity
c'(u) u'(s) v: the exact time derivative of that position, by the chain rule. Its speed
|c'(u)| u'(s) v differs from v only by the interpolation's error, which is O(h^3) for intervals of
arc length h; the table is refined (the intervals halved) until that relative error, measured at
five points inside every interval, is at most ``SPEED_TOLERANCE`` (1e-9). The position is always on
the curve, at the scheduled arc length exactly at every node and off it between two nodes by at
most that relative error times the interval's length.

* "figure_eight": the lemniscate of Gerono scaled per axis, c(u) = centre + (L/2 sin 2 pi u,
  W/2 sin 4 pi u) for u in [0, 1) per lap: L long (along x), W wide, through its centre at u = 0
  heading north-east; |c'| > 0 everywhere (cos 2 pi u and cos 4 pi u never vanish together).
* "spline": the centripetal Catmull-Rom spline through the waypoints (Yuksel et al. 2011: no
  cusp or self-intersection inside a segment), one cubic per segment between consecutive waypoints
  in the spline's knot parameter, with end tangents from reflected phantom points. Its direction is
  continuous at the waypoints; its curvature is not.

A curve whose table the largest size (``_MOST_NODES``) cannot bring under 1e-6 is refused where the
scenario file is read (``scenario_target``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from platoon_opt.arrays import namespace, pytree, searchsorted
from platoon_opt.paths import schedule, travel

# Largest relative error of the target's speed the arc-length table may leave.
SPEED_TOLERANCE = 1e-9
# Table intervals per segment (a spline's segment, a figure-eight's lap) to start from, and the
# most nodes a table may hold (its memory inside the compiled loop: 3 float64 arrays).
_FIRST = 64
_MOST_NODES = 2**18
_GAUSS = np.polynomial.legendre.leggauss(8)
_CHECKS = np.linspace(0.0, 1.0, 7)[1:-1]  # where inside each interval the speed is checked
# Intervals of a curve's outline (``CurvePath.outline``): an obstacle field measures its distance to
# every one for every candidate; their sagitta on the shipped curves is below 1 mm.
_OUTLINE = 512


def curve(shape: str, coefficients: Any, knots: Any, u: Any) -> tuple[Any, Any]:
    """c(u) (..., 2) m and c'(u) (..., 2) m per unit of u, for u (...,): a figure-eight's
    ``coefficients`` are [centre, half-extents] (2, 2); a spline's are per segment (S, 4, 2), the
    power-basis coefficients of c in u - knots[q] on segment q, which spans u in
    [knots[q], knots[q + 1]] ((S + 1,); unused for a figure-eight)."""
    xp = namespace(coefficients, knots, u)
    if shape == "figure_eight":
        center, half = coefficients[0], coefficients[1]
        phase = 2 * np.pi * u
        c = center + xp.stack((half[0] * xp.sin(phase), half[1] * xp.sin(2 * phase)), axis=-1)
        dc = 2 * np.pi * xp.stack((half[0] * xp.cos(phase), 2 * half[1] * xp.cos(2 * phase)), axis=-1)
        return c, dc
    segment = xp.clip(searchsorted(knots, u, side="right") - 1, 0, coefficients.shape[0] - 1)
    tau = (u - knots[segment])[..., None]
    a0, a1, a2, a3 = (coefficients[segment][..., j, :] for j in range(4))
    return a0 + tau * (a1 + tau * (a2 + tau * a3)), a1 + tau * (2 * a2 + 3 * tau * a3)


def parameter(nodes: Any, arcs: Any, slopes: Any, s: Any) -> tuple[Any, Any]:
    """u(s) and du/ds (1/m) at arc length ``s`` (...,) m: the cubic Hermite interpolant of the
    table's ``nodes`` u_i, arc lengths ``arcs`` s_i (N + 1,) m and ``slopes`` du/ds (N + 1,)."""
    xp = namespace(nodes, arcs, slopes, s)
    i = xp.clip(searchsorted(arcs, s, side="right") - 1, 0, arcs.shape[0] - 2)
    h = arcs[i + 1] - arcs[i]
    x = (s - arcs[i]) / h
    rise, m0, m1 = nodes[i + 1] - nodes[i], slopes[i] * h, slopes[i + 1] * h
    a2, a3 = 3 * rise - 2 * m0 - m1, m0 + m1 - 2 * rise
    return nodes[i] + x * (m0 + x * (a2 + x * a3)), (m0 + x * (2 * a2 + 3 * x * a3)) / h


def tabulate(shape: str, coefficients: np.ndarray, knots: np.ndarray) -> tuple[np.ndarray, ...]:
    """The arc-length table (nodes, arcs, slopes) of the curve over u in [knots[0], knots[-1]],
    nodes spaced evenly within each segment, and the largest relative speed error of its
    interpolant (measured): intervals are halved until that error is at most ``SPEED_TOLERANCE``
    or the table would exceed ``_MOST_NODES``."""
    per = _FIRST
    while True:
        fractions = np.arange(per) / per
        nodes = np.append((knots[:-1, None] + np.diff(knots)[:, None] * fractions).ravel(), knots[-1])
        h = np.diff(nodes)
        inner = nodes[:-1, None] + h[:, None] * (_GAUSS[0] + 1) / 2
        speed = np.linalg.norm(curve(shape, coefficients, knots, inner)[1], axis=-1)
        arcs = np.concatenate((np.zeros(1), np.cumsum(speed @ _GAUSS[1] * h / 2)))
        slopes = 1.0 / np.linalg.norm(curve(shape, coefficients, knots, nodes)[1], axis=-1)
        checks = (arcs[:-1, None] + np.diff(arcs)[:, None] * _CHECKS).ravel()
        u, rate = parameter(nodes, arcs, slopes, checks)
        tangent = curve(shape, coefficients, knots, u)[1]
        error = float(np.max(np.abs(np.linalg.norm(tangent, axis=-1) * rate - 1)))
        # Done when within tolerance, at the largest table, or not a number (a cusp: |c'| = 0).
        if not error > SPEED_TOLERANCE or 2 * nodes.size > _MOST_NODES:
            return nodes, arcs, slopes, np.array(error)
        per *= 2


def figure_eight(center: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients (2, 2) and knots (2,) of the figure-eight ``size`` = [length, width] (m)
    around ``center`` (2,) m."""
    return np.vstack((center, size / 2)), np.array([0.0, 1.0])


def catmull_rom(waypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients (k - 1, 4, 2) and knots (k,) of the centripetal Catmull-Rom spline through
    ``waypoints`` (k >= 2, 2) m, consecutive ones distinct. The parameter is the spline's knot
    parameter (knot spacing |P_{j+1} - P_j|^(1/2)), in which the Barry-Goldman construction is
    C^1: c' is continuous at the waypoints, so the arc-length table's slopes are too. Phantom end
    points mirror the second and the second-last waypoint."""
    points = np.vstack((2 * waypoints[0] - waypoints[1], waypoints, 2 * waypoints[-1] - waypoints[-2]))
    gaps = np.sqrt(np.linalg.norm(np.diff(points, axis=0), axis=1))  # knot spacing (k + 1,)
    chords = np.diff(points, axis=0) / gaps[:, None]  # (P_{j+1} - P_j) / (t_{j+1} - t_j)
    # dc/dt at each waypoint, from its two neighbours (k, 2).
    tangents = chords[:-1] - (points[2:] - points[:-2]) / (gaps[:-1] + gaps[1:])[:, None] + chords[1:]
    start, end, span = waypoints[:-1], waypoints[1:], gaps[1:-1, None]
    m0, m1 = tangents[:-1], tangents[1:]
    # The Hermite cubic with end tangents m0, m1 over [0, span], in powers of u - knot.
    cubic = (
        start,
        m0,
        (3 * (end - start) / span - 2 * m0 - m1) / span,
        (2 * (start - end) / span + m0 + m1) / span**2,
    )
    return np.stack(cubic, axis=1), np.concatenate((np.zeros(1), np.cumsum(gaps[1:-1])))


def _wrapped(shape: str, travelled: Any, lap: Any) -> Any:
    """Arc length ``travelled`` (m) within the table: around the lap of a closed curve."""
    if shape == "figure_eight":
        return travelled - lap * namespace(travelled, lap).floor(travelled / lap)
    return travelled


@pytree(
    data=("coefficients", "knots", "nodes", "arcs", "slopes", "starts", "speeds", "times", "end"),
    static=("shape",),
)
@dataclass(frozen=True)
class CurvePath:
    """A parametric curve travelled by arc length at a speed constant on each piece.

    Attributes:
        shape: "figure_eight" (closed: the arc length wraps around at every lap) or "spline".
        coefficients, knots: the curve (``curve``): (2, 2) and (2,), or (S, 4, 2) and (S + 1,).
        nodes, arcs, slopes: the arc-length table of one lap or of the whole spline (N + 1,):
            u_i, s(u_i) (m) and du/ds (1/m).
        starts, speeds, times: the pieces (a spline's segments; all laps of a figure-eight as one):
            arc length (P + 1,) m, speed (P,) m/s and time (P + 1,) s, as in ``paths.ArcPath``.
        end: (2,) the last point, where the target holds, m.
    """

    shape: str
    coefficients: Any
    knots: Any
    nodes: Any
    arcs: Any
    slopes: Any
    starts: Any
    speeds: Any
    times: Any
    end: Any

    @classmethod
    def of(
        cls,
        shape: str,
        curve_: tuple[np.ndarray, np.ndarray],
        table: tuple[np.ndarray, ...],
        speeds: np.ndarray,
        laps: float = 1.0,
    ) -> CurvePath:
        """The curve ``shape`` of ``curve_`` (coefficients, knots: ``figure_eight`` or
        ``catmull_rom``) with its arc-length ``table`` (``tabulate``), at ``speeds`` (m/s; one per
        spline segment, one for a figure-eight), ``laps`` times (a figure-eight)."""
        coefficients, knots = curve_
        nodes, arcs, slopes = table[:3]
        segments = knots.size - 1
        if shape == "spline":
            lengths = np.diff(arcs[:: (nodes.size - 1) // segments])
        else:
            lengths = np.array([arcs[-1] * laps])
        starts, times = schedule(lengths, speeds)
        u_end, _ = parameter(nodes, arcs, slopes, _wrapped(shape, starts[-1], arcs[-1]))
        end, _ = curve(shape, coefficients, knots, u_end)
        return cls(shape, coefficients, knots, nodes, arcs, slopes, starts, speeds, times, end)

    @property
    def length(self) -> float:
        return float(self.starts[-1])

    @property
    def speed(self) -> float:
        return float(np.max(self.speeds))

    @property
    def waypoints(self) -> np.ndarray:
        """A spline's waypoints; a figure-eight's start and end."""
        if self.shape == "spline":
            return np.vstack((self.coefficients[:, 0], self.end[None]))
        return np.vstack((self.coefficients[0], self.end))

    def at(self, t: Any) -> tuple[Any, Any]:
        """Position (2,) m and velocity (2,) m/s at time ``t`` (s; a float, or traced)."""
        xp = namespace(t, self.arcs)
        starts, speeds, times, arcs = (
            xp.asarray(a) for a in (self.starts, self.speeds, self.times, self.arcs)
        )
        travelled, piece = travel(t, starts, speeds, times)
        u, rate = parameter(
            xp.asarray(self.nodes), arcs, xp.asarray(self.slopes), _wrapped(self.shape, travelled, arcs[-1])
        )
        position, tangent = curve(self.shape, xp.asarray(self.coefficients), xp.asarray(self.knots), u)
        done = travelled >= starts[-1]
        return xp.where(done, xp.asarray(self.end), position), xp.where(
            done, 0.0, tangent * rate * speeds[piece]
        )

    def outline(self) -> tuple[np.ndarray, float]:
        """The curve at table nodes (at most ``_OUTLINE + 1`` over one lap); the margin is twice
        the largest distance of an interval's mid-point from its chord (the largest distance lies
        near the mid-point, the curvature varying little over an interval)."""
        stride = -(-(self.nodes.size - 1) // _OUTLINE)
        u = self.nodes[::stride]
        if self.shape == "figure_eight" and self.length < self.arcs[-1]:  # less than one lap
            u = u[u <= parameter(self.nodes, self.arcs, self.slopes, np.array(self.length))[0]]
        points = curve(self.shape, self.coefficients, self.knots, u)[0]
        middle = curve(self.shape, self.coefficients, self.knots, (u[:-1] + u[1:]) / 2)[0]
        chord, offset = points[1:] - points[:-1], middle - points[:-1]
        cross = np.abs(chord[:, 0] * offset[:, 1] - chord[:, 1] * offset[:, 0]) / np.linalg.norm(
            chord, axis=1
        )
        return np.vstack((points, self.end[None])), 2 * float(np.max(cross, initial=0.0))
