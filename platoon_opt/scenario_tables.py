"""The scenario file's tables that need more than one check per key: ``[task.desired]``,
``[vehicle]`` (in the file's units) and ``[safety]`` (docs/scenarios.md). Each takes the file's
``Checks`` so that an error names the file, the key path and the value as written."""

from __future__ import annotations

import math
from typing import Any

from platoon_opt.errors import ConfigurationError
from platoon_opt.safety import MODES, SafetyParams
from platoon_opt.scenario_checks import MAX_MAGNITUDE, MIN_POSITIVE, Checks, key_path, show
from platoon_opt.vehicle import VehicleLimits


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
    values: dict[str, float] = {}
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
