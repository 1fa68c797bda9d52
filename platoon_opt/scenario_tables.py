"""The scenario file's tables that need more than one check per key: ``[platoon]`` (with the keys
of ``[seed]`` that shape it), ``[obstacle_field]``, ``[task.desired]``, ``[vehicle]`` (in the
file's units) and ``[safety]`` (docs/scenarios.md; ``[target]`` is ``scenario_target``). Each takes the file's
``Checks`` so that an error names the file, the key path and the value as written."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from platoon_opt import formations
from platoon_opt.errors import ConfigurationError
from platoon_opt.obstacle_fields import ObstacleField
from platoon_opt.paths import Path
from platoon_opt.safety import MODES, SafetyParams
from platoon_opt.scenario_checks import (
    MAX_MAGNITUDE,
    MAX_UNITS,
    MIN_POSITIVE,
    REQUIRED,
    Checks,
    key_path,
    show,
)
from platoon_opt.vehicle import VehicleLimits

# The most obstacles a field may draw (each is tested against all placed before it).
MAX_FIELD = 1_000


def desired(checks: Checks, table: dict[str, Any], names: tuple[str, ...]) -> dict[str, float]:
    """``[task.desired]``: a value for every component but the means, which follow the target.
    A variance (``var_*``) must be > 0 and a covariance (``cov_xy``) inside the variances'
    bound, |cov_xy| < sqrt(var_x var_y): no formation has another covariance matrix."""
    follow = ("mean_x", "mean_y")
    for key, value in table.items():
        if key not in names or key in follow:
            valid = ", ".join(name for name in names if name not in follow)
            raise checks.error(f"unknown key {key_path('task.desired', key)} = {show(value)}; valid: {valid}")
    checks.require(table, "task.desired", tuple(name for name in names if name not in follow))
    desired = {}
    for key, value in table.items():
        square = key.startswith("var_")
        bound = MAX_MAGNITUDE**2 if square or key.startswith("cov_") else MAX_MAGNITUDE
        desired[key] = checks.number(f"task.desired.{key}", value, bound=bound)
        if square and not desired[key] > 0:
            raise checks.must(f"task.desired.{key}", "> 0 (a variance, m^2)", value)
    if "cov_xy" in desired and {"var_x", "var_y"} <= desired.keys():
        limit = math.sqrt(desired["var_x"] * desired["var_y"])
        if not abs(desired["cov_xy"]) < limit:
            rule = f"inside (-sqrt(var_x var_y), sqrt(var_x var_y)) = (-{limit:.6g}, {limit:.6g})"
            raise checks.must("task.desired.cov_xy", rule, table["cov_xy"])
    return desired


def limits(checks: Checks, vehicle: dict[str, Any]) -> VehicleLimits:
    """``[vehicle]`` in the file's units (degrees for the angles), checked there, so that an
    error names the key and the value as written."""
    values: dict[str, Any] = {}
    for key in ("wheel_radius", "length", "max_speed", "max_steering_rate", "steering_gain"):
        if key in vehicle:
            values[key] = checks.number(f"vehicle.{key}", vehicle[key], positive=True)
    if "max_steering_deg" in vehicle:
        value = vehicle["max_steering_deg"]
        degrees = checks.number("vehicle.max_steering_deg", value, bound=90)
        if not 0 < degrees < 90:
            raise checks.must("vehicle.max_steering_deg", "in (0, 90) degrees", value)
        if degrees < MIN_POSITIVE:  # a subnormal angle is 0 rad once converted: no steering
            raise checks.must("vehicle.max_steering_deg", f">= {MIN_POSITIVE:g} degrees", value)
        values["max_steering"] = math.radians(degrees)
    if "gear_hysteresis_deg" in vehicle:
        value = vehicle["gear_hysteresis_deg"]
        degrees = checks.number("vehicle.gear_hysteresis_deg", value, bound=90)
        if not 0 <= degrees < 90:
            raise checks.must("vehicle.gear_hysteresis_deg", "in [0, 90) degrees", value)
        values["gear_hysteresis"] = math.radians(degrees)
    return VehicleLimits(**values)


def safety(checks: Checks, table: dict[str, Any], limits: VehicleLimits, dt: float) -> SafetyParams:
    """``[safety]``: the barrier constraints' mode and numbers (``SafetyParams``), checked against
    the vehicle and the step (``SafetyParams.check``) when the mode is "barrier"."""
    values: dict[str, Any] = {}
    if "mode" in table:
        if table["mode"] not in MODES:
            raise checks.must("safety.mode", " or ".join(repr(mode) for mode in MODES), table["mode"])
        values["mode"] = table["mode"]
    if "barrier_rate" in table:
        rate = checks.number("safety.barrier_rate", table["barrier_rate"], positive=True)
        if rate > 1:
            raise checks.must("safety.barrier_rate", "in (0, 1]", table["barrier_rate"])
        values["barrier_rate"] = rate
    for key in ("safety_distance", "neighbour_cutoff"):
        if key in table:
            values[key] = checks.number(f"safety.{key}", table[key], positive=True)
    if "obstacle_margin" in table:
        values["obstacle_margin"] = checks.number(
            "safety.obstacle_margin", table["obstacle_margin"], at_least=0
        )
    if "turning_room" in table:  # a boolean: the schema checked its type
        values["turning_room"] = table["turning_room"]
    params = SafetyParams(**values)
    if params.enabled:
        try:
            params.check(limits, dt)
        except ConfigurationError as error:
            raise checks.error(str(error)) from None
    return params


def platoon(
    checks: Checks, table: dict[str, Any], seed: dict[str, Any], target: dict[str, Any], start: np.ndarray
) -> dict[str, Any]:
    """``[platoon]`` and the keys of ``[seed]`` that shape it: the ``Scenario`` fields n, center,
    variance, heading, headings, formation, positions and vary_ring_phase. ``target`` is the
    ``[target]`` table (its ``start_offset``, checked) and ``start`` (2,) m where the target starts."""
    n = table["n"]
    if n < 2:
        raise checks.must("platoon.n", ">= 2", n)
    if n > MAX_UNITS:
        raise checks.must("platoon.n", f"<= {MAX_UNITS:,}", n)
    formation = table.get("formation", "ring")
    if formation not in formations.FORMATIONS:
        raise checks.must("platoon.formation", " or ".join(map(repr, formations.FORMATIONS)), formation)
    if formation != "ring" and "ring_phase" in seed:
        rule = f"left out with platoon.formation = {formation!r} (only a ring has a phase)"
        raise checks.must("seed.ring_phase", rule, seed["ring_phase"])
    if formation != "explicit" and "positions" in table:
        rule = f"left out with platoon.formation = {formation!r} (positions are for 'explicit')"
        raise checks.must("platoon.positions", rule, table["positions"])
    fields = dict(
        n=n,
        formation=formation,
        heading=checks.number("platoon.heading", table.get("heading", math.pi / 2)),
        headings=_headings(checks, table, seed),
        vary_ring_phase=formation == "ring" and seed.get("ring_phase", True),
    )
    if formation == "explicit":
        if "start_offset" in target:
            rule = "left out with platoon.formation = 'explicit' (the positions place the platoon)"
            raise checks.must("target.start_offset", rule, target["start_offset"])
        return fields | _explicit(checks, table, n)
    if formation == "ring" and n == 2 and not fields["vary_ring_phase"]:
        # Two units at phases 0 and pi lie on the x axis: no ring scaling gives them a var_y.
        raise checks.must("platoon.n", ">= 3 when seed.ring_phase = false (two units have no var_y)", n)
    if formation == "grid" and n < 3:
        raise checks.must("platoon.n", ">= 3 with platoon.formation = 'grid' (one row has no var_y)", n)
    if "variance" not in table:
        raise checks.error("missing key platoon.variance")
    variance = np.array(checks.vector("platoon.variance", table["variance"], 2, bound=MAX_MAGNITUDE**2))
    for i, value in enumerate(variance):
        if not value > 0:
            raise checks.must(f"platoon.variance[{i}]", "> 0 (m^2)", table["variance"][i])
    if "start_offset" not in target:
        if "center" not in table:
            raise checks.error("missing key platoon.center (or target.start_offset)")
        center = np.array(checks.point("platoon.center", table["center"]))
    elif "center" in table:
        raise checks.must(
            "platoon.center", "left out when target.start_offset places the platoon", table["center"]
        )
    else:
        center = start - np.array(target["start_offset"], dtype=float)
    return fields | dict(center=center, variance=variance, positions=None)


def _headings(checks: Checks, table: dict[str, Any], seed: dict[str, Any]) -> str:
    """``platoon.headings``, or "random" / "fixed" from ``seed.headings``; both must agree."""
    if "headings" not in table:
        return "random" if seed.get("headings", False) else "fixed"
    mode = table["headings"]
    if mode not in formations.HEADINGS:
        raise checks.must("platoon.headings", " or ".join(map(repr, formations.HEADINGS)), mode)
    if "headings" in seed and seed["headings"] != (mode == "random"):
        agree = "true" if mode == "random" else "false"
        raise checks.must(
            "seed.headings", f"{agree} or left out with platoon.headings = {mode!r}", seed["headings"]
        )
    return str(mode)


def _explicit(checks: Checks, table: dict[str, Any], n: int) -> dict[str, Any]:
    """The fields of an explicit formation: the positions as given, their mean and variances."""
    for key in ("center", "variance"):
        if key in table:
            rule = "left out with platoon.formation = 'explicit' (the positions place the platoon)"
            raise checks.must(f"platoon.{key}", rule, table[key])
    if "positions" not in table:
        raise checks.error("missing key platoon.positions (one [x, y] per unit with formation = 'explicit')")
    value = table["positions"]
    if not isinstance(value, list) or len(value) != n:
        raise checks.must("platoon.positions", f"a list of platoon.n = {n} [x, y], one per unit", value)
    positions = np.array([checks.point(f"platoon.positions[{i}]", p) for i, p in enumerate(value)])
    distance = cKDTree(positions).query(positions, k=2)[0]
    i = int(np.argmin(distance[:, 1]))
    if not distance[i, 1] >= MIN_POSITIVE:
        rule = f"at least {MIN_POSITIVE:g} m from every other unit (units must not coincide)"
        raise checks.must(f"platoon.positions[{i}]", rule, value[i])
    variance = positions.var(axis=0, ddof=1)
    if not np.all(variance > 0):
        rule = "spread along both axes (a sample variance of 0 makes the task's Jacobian singular)"
        raise checks.must("platoon.positions", rule, value)
    return dict(center=positions.mean(axis=0), variance=variance, positions=positions)


def obstacle_field(checks: Checks, table: dict[str, Any], path: Path) -> ObstacleField:
    """``[obstacle_field]``: the numbers checked, the region large enough for the obstacles'
    area (a necessary condition: a seed that still finds no place is refused when drawn)."""
    checks.require(table, "obstacle_field", REQUIRED["obstacle_field"])
    count = table["count"]
    if not 1 <= count <= MAX_FIELD:
        raise checks.must("obstacle_field.count", f"in [1, {MAX_FIELD:,}]", count)
    radii = np.array(checks.vector("obstacle_field.radius_range", table["radius_range"], 2))
    if not radii[0] >= MIN_POSITIVE:
        raise checks.must(
            "obstacle_field.radius_range[0]", f">= {MIN_POSITIVE:g} (m)", table["radius_range"][0]
        )
    if not radii[1] >= radii[0]:
        rule = "radius_range[1] >= radius_range[0] (the largest radius, m)"
        raise checks.must("obstacle_field.radius_range[1]", rule, table["radius_range"][1])
    region = np.array(checks.vector("obstacle_field.region", table["region"], 4))
    for axis in (0, 1):  # x, then y
        if not region[2 + axis] - region[axis] >= 2 * radii[1]:
            rule = f"at least 2 radius_range[1] = {2 * radii[1]:g} m above region[{axis}] = {region[axis]:g}"
            raise checks.must(f"obstacle_field.region[{2 + axis}]", rule, table["region"][2 + axis])
    path_gap = None
    if "path_gap" in table:
        path_gap = checks.number("obstacle_field.path_gap", table["path_gap"], at_least=0)
    start_gap = checks.number("obstacle_field.start_gap", table.get("start_gap", 1.0), at_least=0)
    gap = checks.number("obstacle_field.obstacle_gap", table.get("obstacle_gap", 0.0), at_least=0)
    room = (region[2] - region[0] + gap) * (region[3] - region[1] + gap)
    if count * math.pi * (radii[0] + gap / 2) ** 2 > room:
        # Discs of radius radius_range[0] + obstacle_gap / 2 around the obstacles are disjoint.
        rule = f"small enough for that many obstacles to fit in obstacle_field.region ({room:g} m^2)"
        raise checks.must("obstacle_field.count", rule, count)
    outline, margin = path.outline()
    return ObstacleField(count, radii, region, path_gap, start_gap, gap, outline, margin)
