"""The achievable sets C_i of the dual allocator, in a form fit for repeated projection
(docs/dual.md, section 5). Array-API style: numpy in, numpy out on the host; traced inside the
compiled solve (``platoon_opt.arrays.namespace``), with static shapes.

``make_sets(sets, speed, sides)`` turns the model's ``AchievableSets`` (n units) into
``SectorSets`` (speed "cone": the steering sector cut by the speed disk, exact) or
``PolygonSets`` (speed "polygon": the sector cut by the inscribed ``sides``-gon). Both offer

* ``project(wx, wy)``: the nearest points v = P_C(w) of plane velocities (n,) x 2, m/s, with the
  generalized Jacobian of the projection (``Projection``);
* ``support(gx, gy)``: a point of each C_i maximizing ``g_i . v`` (n,) x 2, m/s.

The projection works in each sector's local frame (a along its centre direction, b across it),
folded onto b >= 0: every set is symmetric about its centre direction. Its generalized Jacobian
is ``alpha I + beta f f^T`` for each unit (docs/dual.md, equation (10)), handed back in the plane.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from platoon_opt.arrays import namespace, pytree
from platoon_opt.limits import AchievableSets

# Polygons of at most this many units keep their boundary for the whole solve; larger ones
# rebuild it in each pass (``PolygonSets``; measured in docs/dual.md, section 4).
KEEP_BOUNDARY_UP_TO = 4096
# The smallest normal float (np.finfo is slow to ask at every step).
TINY = float(np.finfo(float).tiny)


class Projection(NamedTuple):
    """Velocities v = P_C(w) (n,) x 2 (m/s) and the generalized Jacobian of the projection,
    ``alpha I + beta f f^T`` per unit: alpha, beta (n,), f = (fx, fy) (n,) x 2 of unit length
    (or 0 where beta is 0), in the plane."""

    vx: Any
    vy: Any
    alpha: Any
    beta: Any
    fx: Any
    fy: Any

    @property
    def jacobian(self) -> tuple[Any, Any, Any]:
        """The 2 x 2 blocks as (dxx, dxy, dyy), each (n,)."""
        bx = self.beta * self.fx
        return self.alpha + bx * self.fx, bx * self.fy, self.alpha + self.beta * self.fy * self.fy


@pytree(data=("cos", "sin", "half", "edge_cos", "edge_sin", "radius"))
@dataclass(frozen=True)
class Frame:
    """Local frames of n sectors: centre direction (cos, sin) (n,), half-width h (n,), rad, its
    cos and sin (n,), and the speed-disk radius (m/s). Computed once per step: the projections
    inside the Newton loop are arithmetic alone."""

    cos: Any
    sin: Any
    half: Any
    edge_cos: Any
    edge_sin: Any
    radius: Any

    @classmethod
    def of(cls, sets: AchievableSets) -> Frame:
        xp = namespace(sets.axis, sets.lower)
        centre = sets.axis + (sets.lower + sets.upper) / 2
        half = (sets.upper - sets.lower) / 2
        return cls(xp.cos(centre), xp.sin(centre), half, xp.cos(half), xp.sin(half), sets.max_speed)

    def to_local(self, wx: Any, wy: Any) -> tuple[Any, Any, Any]:
        """(a, |b|, sign of b) of plane velocities (n,) x 2."""
        xp = namespace(wx, self.cos)
        b = self.cos * wy - self.sin * wx
        return self.cos * wx + self.sin * wy, xp.abs(b), xp.where(b < 0, -1.0, 1.0)

    def to_plane(self, a: Any, b: Any, side: Any) -> tuple[Any, Any]:
        """Plane vectors (n,) x 2 of folded local vectors (a, b >= 0) on ``side``."""
        b = side * b
        return self.cos * a - self.sin * b, self.sin * a + self.cos * b

    def projection(self, pa: Any, pb: Any, side: Any, alpha: Any, beta: Any, fa: Any, fb: Any) -> Projection:
        """The ``Projection`` of a folded local point (pa, pb) with its local Jacobian."""
        vx, vy = self.to_plane(pa, pb, side)
        fx, fy = self.to_plane(fa, fb, side)
        return Projection(vx, vy, alpha, beta, fx, fy)


@pytree(data=("frame",))
@dataclass(frozen=True)
class SectorSets:
    """C_i = steering sector cut by the speed disk (exact); the projection of
    ``AchievableSets.project``, with its Jacobian."""

    frame: Frame

    @classmethod
    def of(cls, sets: AchievableSets) -> SectorSets:
        return cls(Frame.of(sets))

    def project(self, wx: Any, wy: Any) -> Projection:
        """Project plane velocities (n,) x 2 onto the sets: onto the cone (w, the nearer edge
        ray or the apex), then shorten to the disk (P_{K cap B} = P_B o P_K). Cases are blended
        arithmetically (``x + flag * (y - x)``), which numpy and XLA both run without branches."""
        frame = self.frame
        xp = namespace(wx, frame.cos)
        ch, sh, radius = frame.edge_cos, frame.edge_sin, frame.radius
        a, b, side = frame.to_local(wx, wy)
        inside = xp.where(a * sh >= b * ch, 1.0, 0.0)
        along = xp.maximum(a * ch + b * sh, 0.0)  # on the nearer edge ray (b >= 0: the upper)
        pa = along * ch + inside * (a - along * ch)
        pb = along * sh + inside * (b - along * sh)
        length = xp.sqrt(pa * pa + pb * pb)
        clipped = xp.maximum(length, radius)
        scale = radius / clipped
        within = xp.where(length <= radius, 1.0, 0.0)
        # Jacobian: in the cone, I inside the disk and scale * t t^T on the arc (t tangent);
        # on the ray, e e^T strictly between the apex and the disk; 0 at the apex and corner.
        alpha = inside * within
        arc = inside - alpha
        beta = arc * scale + (1.0 - inside) * within * xp.where(along > 0, 1.0, 0.0)
        inverse = arc / clipped
        fa = ch + inside * (-pb * inverse - ch)
        fb = sh + inside * (pa * inverse - sh)
        return frame.projection(pa * scale, pb * scale, side, alpha, beta, fa, fb)

    def support(self, gx: Any, gy: Any) -> tuple[Any, Any]:
        """A point of each C_i maximizing ``g_i . v`` (n,) x 2, m/s: on the arc when g_i points
        into the sector, else its corner on the nearer edge, or the apex when g_i points away."""
        frame = self.frame
        xp = namespace(gx, frame.cos)
        ch, sh, radius = frame.edge_cos, frame.edge_sin, frame.radius
        a, b, side = frame.to_local(gx, gy)
        into = a * sh >= b * ch
        arc = radius / xp.maximum(xp.sqrt(a * a + b * b), TINY)
        corner = radius * xp.where(a * ch + b * sh > 0, 1.0, 0.0)
        return frame.to_plane(
            xp.where(into, a * arc, corner * ch), xp.where(into, b * arc, corner * sh), side
        )


def polygon_edges(sides: int) -> int:
    """The polygon edges that can bound a sector narrower than pi on one side of its centre
    direction (a static count: ``ceil((pi / 2) / step)``, step = 2 pi / sides)."""
    return max(1, math.ceil(sides / 4))


@pytree(data=("frame", "ua", "ub", "boundary"), static=("sides",))
@dataclass(frozen=True)
class PolygonSets:
    """C_i = steering sector cut by the regular ``sides``-gon inscribed in the speed disk, with a
    vertex at the sector's centre direction: the set of ``AchievableSets.polygon(sides)``.

    In folded local coordinates the boundary with b >= 0 is the edge ray from the apex to the
    corner U (where the ray meets the polygon) and the polygon chain from (R, 0) to U. A point
    outside C_i projects to the nearest point over these segments; inside, to itself. The chain
    has ``polygon_edges(sides)`` segments whatever the sector's width (static shapes): the
    vertices beyond the sector collapse onto U, leaving segments of length 0.

    The vertices and segments follow from U (``_boundary``). Up to ``KEEP_BOUNDARY_UP_TO`` units
    they are built once and kept (reading them costs less than rebuilding them where a pass's
    arrays fit in cache); beyond, each pass rebuilds them from U, a few operations per unit,
    where keeping them would hold about 24 floats per unit for the whole solve.

    Attributes:
        frame: the sectors' frames.
        ua, ub: the corner U (n,) in folded local coordinates, m/s.
        boundary: ``_boundary()`` kept, or None (rebuilt in each pass).
        sides: the polygon's sides.
    """

    frame: Frame
    ua: Any
    ub: Any
    boundary: Any
    sides: int

    @classmethod
    def of(cls, sets: AchievableSets, sides: int) -> PolygonSets:
        if sides < 3:
            raise ValueError(f"polygon sides must be >= 3, got {sides!r}")
        frame = Frame.of(sets)
        xp = namespace(frame.cos)
        step = 2 * math.pi / sides
        offset = frame.radius * math.cos(step / 2)
        # Corner U: the edge ray at angle h meets the polygon edge spanning h.
        corner = offset / xp.cos(frame.half - (xp.floor(frame.half / step) + 0.5) * step)
        polygon = cls(frame, corner * frame.edge_cos, corner * frame.edge_sin, None, sides)
        if frame.cos.shape[-1] <= KEEP_BOUNDARY_UP_TO:
            polygon = dataclasses.replace(polygon, boundary=polygon._boundary())
        return polygon

    def _boundary(self) -> tuple[list[Any], list[Any], list[tuple[Any, Any, Any, Any, Any]]]:
        """The boundary's vertices va, vb (``polygon_edges + 2`` of them, each (n,)): the apex,
        then the chain from (R, 0) to U (polygon vertex j, at angle j step, while inside the
        sector, else U); and its segments, each (dir_a, dir_b, 1 / |dir|^2 (0 for length 0),
        normal_a, normal_b), from its start (the ray from the apex, chain segment k from vertex
        k): the ray apex -> U, then the chain."""
        xp = namespace(self.ua)
        frame, step = self.frame, 2 * math.pi / self.sides
        edges = polygon_edges(self.sides)
        angles, normal = np.arange(edges + 1) * step, (np.arange(edges) + 0.5) * step
        zero = xp.zeros_like(self.ua)
        va, vb = [zero], [zero]
        for angle, cos, sin in zip(angles, np.cos(angles), np.sin(angles)):
            within = angle < frame.half
            va.append(xp.where(within, frame.radius * cos, self.ua))
            vb.append(xp.where(within, frame.radius * sin, self.ub))
        starts = [(va[0], vb[0])] + list(zip(va[1:-1], vb[1:-1]))
        ends = [(va[-1], vb[-1])] + list(zip(va[2:], vb[2:]))
        normals = [(-frame.edge_sin, frame.edge_cos)] + list(zip(np.cos(normal), np.sin(normal)))
        segments = []
        for (start_a, start_b), (end_a, end_b), (normal_a, normal_b) in zip(starts, ends, normals):
            dir_a, dir_b = end_a - start_a, end_b - start_b
            length2 = dir_a * dir_a + dir_b * dir_b
            inverse = xp.where(length2 > 0, 1.0 / xp.where(length2 > 0, length2, 1.0), 0.0)
            segments.append((dir_a, dir_b, inverse, normal_a, normal_b))
        return va, vb, segments

    def project(self, wx: Any, wy: Any) -> Projection:
        """Project plane velocities (n,) x 2 onto the sets. A point outside projects onto the
        segment in whose normal strip it lies (``0 < t < 1`` along the segment and beyond its line),
        else onto the nearest vertex. Both tests are linear in w: comparing squared distances
        instead leaves a far point (the dual's iterates reach 1e3 m/s) undecided between a segment's
        interior and its end to sqrt(rounding) (2e-7 m/s measured), which differs with the order
        of the operations (numpy, XLA)."""
        xp = namespace(wx, self.frame.cos)
        frame = self.frame
        va, vb, segments = self.boundary if self.boundary is not None else self._boundary()
        a, b, side = frame.to_local(wx, wy)
        # The nearest vertex (|v|^2 - 2 w . v: the squared distance less |w|^2, linear in w),
        # found by a running minimum (a gather per unit costs more than the comparisons).
        pa, pb, best = va[0], vb[0], va[0] * va[0] + vb[0] * vb[0] - 2 * (a * va[0] + b * vb[0])
        for k in range(1, len(va)):
            score = va[k] * va[k] + vb[k] * vb[k] - 2 * (a * va[k] + b * vb[k])
            nearer = score < best
            pa, pb, best = xp.where(nearer, va[k], pa), xp.where(nearer, vb[k], pb), xp.minimum(score, best)
        # Jacobian: e e^T on a segment's interior (e its direction); 0 at a vertex.
        beta, fa, fb, found = (
            xp.zeros_like(a),
            xp.zeros_like(a),
            xp.zeros_like(a),
            xp.zeros_like(a, dtype=bool),
        )
        for k, (dir_a, dir_b, inverse, normal_a, normal_b) in enumerate(segments):
            start_a, start_b = va[k], vb[k]  # the ray starts at the apex, chain segment k at vertex k
            da, db = a - start_a, b - start_b
            t = (da * dir_a + db * dir_b) * inverse
            take = (t > 0) & (t < 1) & (da * normal_a + db * normal_b > 0) & ~found
            unit = xp.sqrt(inverse)
            pa = xp.where(take, start_a + t * dir_a, pa)
            pb = xp.where(take, start_b + t * dir_b, pb)
            beta = xp.where(take, 1.0, beta)
            fa = xp.where(take, dir_a * unit, fa)
            fb = xp.where(take, dir_b * unit, fb)
            found = found | take
        # Inside the cone and every polygon edge that can meet it (the others hold anyway): w
        # itself, Jacobian I.
        offset = frame.radius * math.cos(math.pi / self.sides)
        inside = a * frame.edge_sin >= b * frame.edge_cos
        for _, _, _, normal_a, normal_b in segments[1:]:
            inside = inside & (a * normal_a + b * normal_b <= offset)
        flag = xp.where(inside, 1.0, 0.0)
        pa = pa + flag * (a - pa)
        pb = pb + flag * (b - pb)
        return frame.projection(pa, pb, side, flag, beta * (1.0 - flag), fa, fb)

    def support(self, gx: Any, gy: Any) -> tuple[Any, Any]:
        """A vertex of each C_i maximizing ``g_i . v`` (n,) x 2, m/s: the apex, the chain's vertices
        or its end U."""
        xp = namespace(gx, self.frame.cos)
        a, b, side = self.frame.to_local(gx, gy)
        boundary = self.boundary if self.boundary is not None else self._boundary()
        va, vb = (xp.stack(v) for v in boundary[:2])
        best = xp.argmax(a[None, :] * va + b[None, :] * vb, axis=0)[None, :]
        pa = xp.take_along_axis(va, best, axis=0)[0]
        pb = xp.take_along_axis(vb, best, axis=0)[0]
        return self.frame.to_plane(pa, pb, side)


def make_sets(sets: AchievableSets, speed: str, sides: int) -> SectorSets | PolygonSets:
    """The projection-ready form of ``sets``: exact sector (``"cone"``) or ``sides``-gon."""
    return SectorSets.of(sets) if speed == "cone" else PolygonSets.of(sets, sides)
