"""The achievable sets C_i of the dual allocator, in a form fit for repeated projection
(docs/dual.md, section 5).

``make_sets(sets, speed, sides)`` turns the model's ``AchievableSets`` (n units) into
``SectorSets`` (speed "cone": the steering sector cut by the speed disk, exact) or
``PolygonSets`` (speed "polygon": the sector cut by the inscribed ``sides``-gon). Both offer

* ``project(wx, wy)``: the nearest points v = P_C(w) of plane velocities (n,) x 2, m/s, with the
  generalized Jacobian of the projection (``Projection``);
* ``support(gx, gy)``: a point of each C_i maximizing ``g_i . v`` (n,) x 2, m/s;
* ``unit_point(a, b, *shape)`` with ``shape`` from ``unit_shapes()``: the projection of one unit's
  folded local point in Python floats, for the scalar evaluator of
  ``platoon_opt.solvers.dual.newton``.

The projection works in each sector's local frame (a along its centre direction, b across it),
folded onto b >= 0: every set is symmetric about its centre direction. Its generalized Jacobian
is ``alpha I + beta f f^T`` for each unit (docs/dual.md, equation (10)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from platoon_opt.limits import AchievableSets

# The smallest normal float (np.finfo is slow to ask at every step).
TINY = float(np.finfo(float).tiny)


@dataclass(frozen=True)
class Frame:
    """Local frames of n sectors: centre direction (cos, sin) (n,), half-width h (rad), and the
    speed-disk radius (m/s). ``half`` has shape (1,) when every sector has the same width
    (no rate limit), so that per-segment data broadcast instead of being stored per unit."""

    cos: np.ndarray
    sin: np.ndarray
    half: np.ndarray
    radius: float

    @classmethod
    def of(cls, sets: AchievableSets) -> Frame:
        centre = sets.axis + (sets.lower + sets.upper) / 2
        half = (sets.upper - sets.lower) / 2
        if half.size and (half == half[0]).all():
            half = half[:1]
        return cls(np.cos(centre), np.sin(centre), half, float(sets.max_speed))

    def to_local(self, wx: np.ndarray, wy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a, |b|, sign of b) of plane velocities (n,) x 2."""
        b = self.cos * wy - self.sin * wx
        return self.cos * wx + self.sin * wy, np.abs(b), np.copysign(1.0, b)

    def to_plane(self, a: np.ndarray, b: np.ndarray, side: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Plane vectors (n,) x 2 of folded local vectors (a, b >= 0) on ``side``."""
        b = side * b
        return self.cos * a - self.sin * b, self.sin * a + self.cos * b


@dataclass(frozen=True)
class Projection:
    """Velocities v = P_C(w) (n,) x 2 (m/s) and, lazily, the generalized Jacobian of the
    projection ``jacobian`` = (dxx, dxy, dyy) (n,) x 3 of each 2 x 2 block.

    The Jacobian is kept in the folded local form ``alpha I + beta f f^T``, f = (fa, fb) on
    ``side``, and mapped to the plane only when a Newton step or the line search needs it;
    ``factor`` (n,) multiplies it (the inverse unit weights of a weighted program).
    """

    vx: np.ndarray
    vy: np.ndarray
    frame: Frame
    side: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    fa: np.ndarray
    fb: np.ndarray
    factor: np.ndarray | None = None

    @classmethod
    def of(cls, frame: Frame, pa, pb, side, alpha, beta, fa, fb) -> Projection:
        """From the folded local point (pa, pb) and the local Jacobian."""
        vx, vy = frame.to_plane(pa, pb, side)
        return cls(vx, vy, frame, side, alpha, beta, fa, fb)

    @cached_property
    def jacobian(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(dxx, dxy, dyy), each (n,)."""
        fx, fy = self.frame.to_plane(self.fa, self.fb, self.side)
        alpha, beta = self.alpha, self.beta
        if self.factor is not None:
            alpha, beta = alpha * self.factor, beta * self.factor
        bx = beta * fx
        return alpha + bx * fx, bx * fy, alpha + beta * fy * fy


@dataclass(frozen=True)
class SectorSets:
    """C_i = steering sector cut by the speed disk (exact); the projection of
    ``AchievableSets.project``, with its Jacobian."""

    frame: Frame
    edge_cos: np.ndarray
    edge_sin: np.ndarray

    @classmethod
    def of(cls, sets: AchievableSets) -> SectorSets:
        frame = Frame.of(sets)
        return cls(frame, np.cos(frame.half), np.sin(frame.half))

    def project(self, wx: np.ndarray, wy: np.ndarray) -> Projection:
        """Project plane velocities (n,) x 2 onto the sets: onto the cone (w, the nearer edge
        ray or the apex), then shorten to the disk (P_{K cap B} = P_B o P_K).

        Cases are blended arithmetically (``x + flag * (y - x)``): ``np.where`` with a mask
        that varies unit to unit is several times slower than the arithmetic itself.
        """
        frame, ch, sh, radius = self.frame, self.edge_cos, self.edge_sin, self.frame.radius
        a, b, side = frame.to_local(wx, wy)
        inside = (a * sh >= b * ch).astype(float)
        along = np.maximum(a * ch + b * sh, 0.0)  # on the nearer edge ray (b >= 0: the upper)
        pa, pb = along * ch, along * sh
        pa += inside * (a - pa)
        pb += inside * (b - pb)
        length = np.sqrt(pa * pa + pb * pb)
        clipped = np.maximum(length, radius)
        scale = radius / clipped
        within = (length <= radius).astype(float)
        # Jacobian: in the cone, I inside the disk and scale * t t^T on the arc (t tangent);
        # on the ray, e e^T strictly between the apex and the disk; 0 at the apex and corner.
        alpha = inside * within
        arc = inside - alpha
        beta = arc * scale + (1.0 - inside) * within * (along > 0)
        inverse = arc / clipped
        fa = ch + inside * (-pb * inverse - ch)
        fb = sh + inside * (pa * inverse - sh)
        return Projection.of(frame, pa * scale, pb * scale, side, alpha, beta, fa, fb)

    def support(self, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A point of each C_i maximizing ``g_i . v`` (n,) x 2, m/s: on the arc when g_i points
        into the sector, else its corner on the nearer edge, or the apex when g_i points away."""
        frame, ch, sh, radius = self.frame, self.edge_cos, self.edge_sin, self.frame.radius
        a, b, side = frame.to_local(gx, gy)
        into = a * sh >= b * ch
        arc = radius / np.maximum(np.sqrt(a * a + b * b), TINY)
        corner = radius * (a * ch + b * sh > 0)
        return frame.to_plane(
            np.where(into, a * arc, corner * ch), np.where(into, b * arc, corner * sh), side
        )

    @staticmethod
    def unit_point(a: float, b: float, ch: float, sh: float, radius: float) -> tuple[float, ...]:
        """``SectorSets.project`` for one folded local point (b >= 0): (pa, pb, alpha, beta, fa, fb)."""
        if a * sh >= b * ch:
            length2 = a * a + b * b
            if length2 <= radius * radius:
                return a, b, 1.0, 0.0, 0.0, 0.0
            length = math.sqrt(length2)
            scale = radius / length
            return a * scale, b * scale, 0.0, scale, -b / length, a / length
        along = max(a * ch + b * sh, 0.0)
        if along > radius:
            return radius * ch, radius * sh, 0.0, 0.0, ch, sh
        return along * ch, along * sh, 0.0, (1.0 if along > 0 else 0.0), ch, sh

    def unit_shapes(self) -> list[tuple[float, ...]]:
        """Per sector (or one for all alike) the arguments of ``unit_point`` after the point:
        (edge cos, edge sin, radius)."""
        radius = self.frame.radius
        return [(ch, sh, radius) for ch, sh in zip(self.edge_cos.tolist(), self.edge_sin.tolist())]


@dataclass(frozen=True)
class _PolygonGeometry:
    """Boundary segments of sector-cut polygons in folded local coordinates, as (segments, k)
    arrays (k = n, or 1 when all sectors are alike): segment 0 is the edge ray from the apex
    to the corner U, the others the polygon chain from (R, 0) to U; plus the outward normals
    (edges, 1) and offset of the polygon edges that can meet a sector."""

    edge_cos: np.ndarray
    edge_sin: np.ndarray
    start_a: np.ndarray
    start_b: np.ndarray
    dir_a: np.ndarray
    dir_b: np.ndarray
    inv_length2: np.ndarray  # 1 / |direction|^2, 0 for a degenerate (point) segment
    unit_a: np.ndarray  # unit direction
    unit_b: np.ndarray
    normal_a: np.ndarray
    normal_b: np.ndarray
    offset: float

    @classmethod
    def of(cls, half: np.ndarray, radius: float, sides: int) -> _PolygonGeometry:
        """For half-widths ``half`` (k,) rad, disk radius (m/s) and ``sides``."""
        step = 2 * math.pi / sides
        offset = radius * math.cos(step / 2)
        # Corner U: the edge ray at angle h meets the polygon edge spanning h.
        mid = (np.floor(half / step) + 0.5) * step
        corner = offset / np.cos(half - mid)
        ch, sh = np.cos(half), np.sin(half)
        ua, ub = corner * ch, corner * sh
        edges = max(1, math.ceil(float(np.max(half, initial=0.0)) / step))
        # Chain vertices: polygon vertex j (angle j step) while inside the sector, else U.
        angles = np.arange(edges + 1) * step
        within = angles[:, None] < half[None, :]
        va = np.where(within, radius * np.cos(angles)[:, None], ua)
        vb = np.where(within, radius * np.sin(angles)[:, None], ub)
        dir_a = np.concatenate((ua[None], va[1:] - va[:-1]))
        dir_b = np.concatenate((ub[None], vb[1:] - vb[:-1]))
        length2 = dir_a * dir_a + dir_b * dir_b
        inv_length2 = np.where(length2 > 0, 1.0 / np.where(length2 > 0, length2, 1.0), 0.0)
        unit = np.sqrt(inv_length2)
        normal = (np.arange(edges) + 0.5)[:, None] * step
        return cls(
            ch,
            sh,
            np.concatenate((np.zeros((1, half.size)), va[:-1])),
            np.concatenate((np.zeros((1, half.size)), vb[:-1])),
            dir_a,
            dir_b,
            inv_length2,
            dir_a * unit,
            dir_b * unit,
            np.cos(normal),
            np.sin(normal),
            offset,
        )

    @cached_property
    def unit_shapes(self) -> list[tuple]:
        """Per sector (k) the arguments of ``PolygonSets.unit_point`` after the point, as Python floats:
        (edge cos, edge sin, normals, offset, segments), each segment (start a, b, direction
        a, b, 1 / |direction|^2, unit direction a, b). Cached with the geometry, which the
        uniform case keeps across steps."""
        normals = list(zip(self.normal_a[:, 0].tolist(), self.normal_b[:, 0].tolist()))
        arrays = (
            self.start_a,
            self.start_b,
            self.dir_a,
            self.dir_b,
            self.inv_length2,
            self.unit_a,
            self.unit_b,
        )
        segments = [list(zip(*column)) for column in zip(*(array.T.tolist() for array in arrays))]
        return [
            (ch, sh, normals, self.offset, segment)
            for ch, sh, segment in zip(self.edge_cos.tolist(), self.edge_sin.tolist(), segments)
        ]


@lru_cache(maxsize=16)
def _uniform_polygon(half: float, radius: float, sides: int) -> _PolygonGeometry:
    """The geometry shared by sectors of one half-width, kept across steps."""
    return _PolygonGeometry.of(np.array([half]), radius, sides)


@dataclass(frozen=True)
class PolygonSets:
    """C_i = steering sector cut by the regular ``sides``-gon inscribed in the speed disk, with a
    vertex at the sector's centre direction: the set of ``AchievableSets.polygon(sides)``.

    In folded local coordinates the boundary with b >= 0 is the edge ray from the apex to the
    corner U (where the ray meets the polygon) and the polygon chain from (R, 0) to U. A point
    outside C_i projects to the nearest point over these segments; inside, to itself.
    """

    frame: Frame
    geometry: _PolygonGeometry

    @classmethod
    def of(cls, sets: AchievableSets, sides: int) -> PolygonSets:
        if sides < 3:
            raise ValueError(f"polygon sides must be >= 3, got {sides!r}")
        frame = Frame.of(sets)
        if frame.half.size == 1:
            return cls(frame, _uniform_polygon(float(frame.half[0]), frame.radius, sides))
        return cls(frame, _PolygonGeometry.of(frame.half, frame.radius, sides))

    def project(self, wx: np.ndarray, wy: np.ndarray) -> Projection:
        """Project plane velocities (n,) x 2 onto the sets (cases blended arithmetically, as in
        ``SectorSets.project``)."""
        g = self.geometry
        a, b, side = self.frame.to_local(wx, wy)
        # Inside the cone and every polygon edge that can meet it (the others hold anyway).
        inside = (a * g.edge_sin >= b * g.edge_cos) & (a * g.normal_a + b * g.normal_b <= g.offset).all(
            axis=0
        )
        # Nearest point of every boundary segment, (segments, n); the point is taken on its
        # segment (not w - r, which loses digits when w is far away).
        da, db = a - g.start_a, b - g.start_b
        t = np.minimum(np.maximum((da * g.dir_a + db * g.dir_b) * g.inv_length2, 0.0), 1.0)
        ra, rb = da - t * g.dir_a, db - t * g.dir_b
        distance = ra * ra + rb * rb
        qa, qb = g.start_a + t * g.dir_a, g.start_b + t * g.dir_b
        # Jacobian: e e^T on a segment's interior (e its direction); 0 at a vertex.
        interior = ((t > 0) & (t < 1)).astype(float)
        best, pa, pb, beta, fa, fb = distance[0], qa[0], qb[0], interior[0], g.unit_a[0], g.unit_b[0]
        for k in range(1, distance.shape[0]):
            nearer = (distance[k] < best).astype(float)
            best = np.minimum(best, distance[k])
            pa = pa + nearer * (qa[k] - pa)
            pb = pb + nearer * (qb[k] - pb)
            beta = beta + nearer * (interior[k] - beta)
            fa = fa + nearer * (g.unit_a[k] - fa)
            fb = fb + nearer * (g.unit_b[k] - fb)
        # Inside: w itself, Jacobian I.
        flag = inside.astype(float)
        pa += flag * (a - pa)
        pb += flag * (b - pb)
        return Projection.of(self.frame, pa, pb, side, flag, beta * (1.0 - flag), fa, fb)

    def support(self, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A vertex of each C_i maximizing ``g_i . v`` (n,) x 2, m/s: the apex, the chain's vertices
        (the segments' starts) or its end U."""
        g = self.geometry
        a, b, side = self.frame.to_local(gx, gy)
        va = np.concatenate((g.start_a, g.start_a[-1:] + g.dir_a[-1:]))
        vb = np.concatenate((g.start_b, g.start_b[-1:] + g.dir_b[-1:]))
        best = np.argmax(a * va + b * vb, axis=0)[None]
        shape = (va.shape[0], a.size)
        pa = np.take_along_axis(np.broadcast_to(va, shape), best, axis=0)[0]
        pb = np.take_along_axis(np.broadcast_to(vb, shape), best, axis=0)[0]
        return self.frame.to_plane(pa, pb, side)

    def unit_shapes(self) -> list[tuple]:
        """See ``_PolygonGeometry.unit_shapes``."""
        return self.geometry.unit_shapes

    @staticmethod
    def unit_point(
        a: float, b: float, ch: float, sh: float, normals, offset: float, segments
    ) -> tuple[float, ...]:
        """``PolygonSets.project`` for one folded local point (b >= 0): (pa, pb, alpha, beta, fa, fb)."""
        if a * sh >= b * ch:
            # A loop, not all() over a generator: creating the generator costs more than the test.
            for na, nb in normals:
                if a * na + b * nb > offset:
                    break
            else:
                return a, b, 1.0, 0.0, 0.0, 0.0
        best = math.inf
        for sa, sb, ea, eb, inv_length2, ua, ub in segments:
            da, db = a - sa, b - sb
            t = min(max((da * ea + db * eb) * inv_length2, 0.0), 1.0)
            ra, rb = da - t * ea, db - t * eb
            distance2 = ra * ra + rb * rb
            if distance2 < best:
                best, chosen = distance2, (sa + t * ea, sb + t * eb, 0.0, (1.0 if 0 < t < 1 else 0.0), ua, ub)
        return chosen


def make_sets(sets: AchievableSets, speed: str, sides: int) -> SectorSets | PolygonSets:
    """The projection-ready form of ``sets``: exact sector (``"cone"``) or ``sides``-gon."""
    return SectorSets.of(sets) if speed == "cone" else PolygonSets.of(sets, sides)
