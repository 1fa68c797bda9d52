"""The scenario file's ``[target]`` table: the kind of path and the keys it takes, checked one
line per error (file, key path, value as written), and the path built (``paths``, ``curves``).
docs/scenarios.md lists the keys."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from platoon_opt import curves, paths
from platoon_opt.curves import CurvePath
from platoon_opt.scenario_checks import MIN_POSITIVE, Checks, key_path

# The keys each kind of path takes besides ``kind``, ``speed`` and ``start_offset``, and the ones
# it needs.
TARGET_KEYS = {
    "polyline": ("waypoints", "speeds"),
    "rounded": ("waypoints", "turn_radius", "speeds"),
    "circle": ("center", "radius", "laps", "start_angle_deg", "clockwise"),
    "figure_eight": ("center", "size", "laps"),
    "spline": ("waypoints", "speeds"),
}
TARGET_NEEDS = {
    "polyline": ("waypoints",),
    "rounded": ("waypoints", "turn_radius"),
    "circle": ("center", "radius"),
    "figure_eight": ("center", "size"),
    "spline": ("waypoints",),
}
# A curve's arc-length table must leave the target's speed at most this far (relative) from the
# asked one; it is refined to 1e-9 (``curves.SPEED_TOLERANCE``) where its size allows.
_SPEED_ERROR = 1e-6


def target(checks: Checks, table: dict[str, Any]) -> paths.Path:
    """``[target]``: the path (``paths``, ``curves``); ``start_offset`` is checked here and used
    by ``scenario_tables.platoon``."""
    kind = table.get("kind", "polyline")
    if kind not in TARGET_KEYS:
        raise checks.must("target.kind", " or ".join(map(repr, TARGET_KEYS)), kind)
    takes = ("kind", "speed", "start_offset", *TARGET_KEYS[kind])
    for key, value in table.items():
        if key not in takes:
            rule = f"left out with target.kind = {kind!r} (it takes {', '.join(takes[1:])})"
            raise checks.must(key_path("target", key), rule, value)
    checks.require(table, "target", TARGET_NEEDS[kind])
    if "start_offset" in table:
        checks.point("target.start_offset", table["start_offset"])
    pieces = len(table["waypoints"]) - 1 if "waypoints" in table else 1
    speeds = _speeds(checks, table, pieces)
    if kind in ("circle", "figure_eight"):
        center = np.array(checks.point("target.center", table["center"]))
        laps = checks.number("target.laps", table.get("laps", 1.0), positive=True)
        if kind == "circle":
            radius = checks.number("target.radius", table["radius"], positive=True)
            start = math.radians(checks.number("target.start_angle_deg", table.get("start_angle_deg", -90.0)))
            path: paths.Path = paths.circle(
                center, radius, laps, start, table.get("clockwise", False), speeds[0]
            )
        else:
            size = np.array(checks.vector("target.size", table["size"], 2))
            for i, value in enumerate(size):
                if not value >= MIN_POSITIVE:
                    raise checks.must(f"target.size[{i}]", f">= {MIN_POSITIVE:g} (m)", table["size"][i])
            shape = curves.figure_eight(center, size)
            arcs = curves.tabulate("figure_eight", *shape)
            if not arcs[3] <= _SPEED_ERROR:
                rule = "less elongated (the arc-length table cannot resolve the curve)"
                raise checks.must("target.size", rule, table["size"])
            path = CurvePath.of("figure_eight", shape, arcs, speeds, laps)
        return path
    points = _waypoints(checks, table["waypoints"], 1 if kind == "polyline" else 2)
    if kind == "polyline":
        if "speeds" in table:
            return paths.TargetPath(points, float(np.max(speeds)), speeds)
        return paths.TargetPath(points, float(speeds[0]))
    if kind == "rounded":
        radius = checks.number("target.turn_radius", table["turn_radius"], positive=True)
        _fit_corners(checks, points, radius, table)
        return paths.rounded(points, radius, speeds)
    return _spline(checks, points, speeds, table["waypoints"])


def _speeds(checks: Checks, table: dict[str, Any], pieces: int) -> np.ndarray:
    """``speed`` (m/s) for every one of ``pieces``, or ``speeds``, one per leg (pieces,)."""
    if "speed" in table and "speeds" in table:
        raise checks.must(
            "target.speeds", "left out when target.speed is given (one or the other)", table["speeds"]
        )
    if "speeds" in table:
        value = table["speeds"]
        if pieces < 1:
            raise checks.must("target.speeds", "left out with fewer than two waypoints (no leg)", value)
        if not isinstance(value, list) or len(value) != pieces:
            raise checks.must(
                "target.speeds", f"a list of {pieces} speeds, one per leg of target.waypoints", value
            )
        return np.array([checks.number(f"target.speeds[{i}]", v, positive=True) for i, v in enumerate(value)])
    if "speed" not in table:
        raise checks.error("missing key target.speed (or target.speeds, one per leg)")
    return np.full(max(pieces, 1), checks.number("target.speed", table["speed"], positive=True))


def _waypoints(checks: Checks, waypoints: list[Any], least: int) -> np.ndarray:
    """``target.waypoints`` (k >= least, 2) m, consecutive points distinct."""
    if len(waypoints) < least:
        what = "a non-empty list of [x, y]" if least == 1 else f"a list of at least {least} [x, y]"
        raise checks.must("target.waypoints", what, waypoints)
    points = np.array([checks.point(f"target.waypoints[{i}]", p) for i, p in enumerate(waypoints)])
    for i in range(1, len(points)):
        # A shorter leg has no direction in floating point (its length squared underflows).
        if not np.linalg.norm(points[i] - points[i - 1]) >= MIN_POSITIVE:
            rule = f"at least {MIN_POSITIVE:g} m from the point before it"
            raise checks.must(f"target.waypoints[{i}]", rule, waypoints[i])
    return points


def _fit_corners(checks: Checks, points: np.ndarray, radius: float, table: dict[str, Any]) -> None:
    """Every corner of a rounded path is no reversal, and its arcs fit the legs beside it."""
    turns = paths.turns(points)
    for i, turn in enumerate(turns, start=1):
        if abs(turn) >= math.pi * (1 - 1e-12):
            rule = "no reversal with target.kind = 'rounded' (no arc rounds a 180-degree turn)"
            raise checks.must(f"target.waypoints[{i}]", rule, table["waypoints"][i])
    cuts = paths.corner_cuts(points, radius)
    legs = np.linalg.norm(np.diff(points, axis=0), axis=1)
    for j, leg in enumerate(legs):
        if cuts[j] + cuts[j + 1] > leg * (1 + 1e-12):
            rule = (
                f"small enough for the arcs at target.waypoints[{j}] and [{j + 1}] to fit their "
                f"{leg:.6g} m leg (they need {cuts[j] + cuts[j + 1]:.6g} m)"
            )
            raise checks.must("target.turn_radius", rule, table["turn_radius"])


def _spline(checks: Checks, points: np.ndarray, speeds: np.ndarray, waypoints: list[Any]) -> CurvePath:
    """The spline through ``points``, refused at a waypoint that sends it straight back: a cusp,
    where c' vanishes (only at a waypoint: a centripetal segment has none inside), or so nearly
    one that the arc-length table cannot resolve it."""
    coefficients, knots = curves.catmull_rom(points)
    # c' in the knot parameter is about sqrt(chord) (m^(1/2)) beside a waypoint.
    legs = np.linalg.norm(np.diff(points, axis=0), axis=1)
    scale = np.sqrt(np.minimum(np.append(legs, np.inf), np.insert(legs, 0, np.inf)))
    ratio = np.linalg.norm(curves.curve("spline", coefficients, knots, knots)[1], axis=-1) / scale
    table = curves.tabulate("spline", coefficients, knots) if ratio.min() >= 1e-6 else None
    if table is None or not table[3] <= _SPEED_ERROR:
        j = int(np.argmin(ratio))
        rule = "no point where target.kind = 'spline' turns straight back (a cusp)"
        raise checks.must(f"target.waypoints[{j}]", rule, waypoints[j])
    return CurvePath.of("spline", (coefficients, knots), table, speeds)
