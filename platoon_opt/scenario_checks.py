"""The checks of a scenario file, key by key, in the file's own units (docs/scenarios.md).

Every error is one ``ScenarioError`` line in one of four shapes, so that a reader (or the fuzzer,
``platoon_opt.study.fuzz``) finds the file, the key path and the value in it:

    FILE: KEY must be RULE, got VALUE
    FILE: missing key KEY
    FILE: unknown key KEY = VALUE; valid: A, B, C
    FILE: not valid TOML ... / not UTF-8 text ... / cannot read ...

``KEY`` is the path as written in the file (``vehicle.max_steering_deg``, ``obstacles[2].radius``)
and ``VALUE`` the value as read (``show``), never an internal field in other units.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from typing import Any

from platoon_opt.errors import ScenarioError

# Bounds beyond any physical platoon, so that every product the model forms stays finite and a
# run fits in memory: magnitudes (m, s, m/s, 1/s) up to MAX_MAGNITUDE, variances up to its square;
# a positive length, speed or time at least MIN_POSITIVE.
MAX_MAGNITUDE = 1e9
MIN_POSITIVE = 1e-9
# A run holds every step of every unit in memory (``simulate``): at most this many steps ...
MAX_STEPS = 10_000_000
# ... and units.
MAX_UNITS = 1_000_000
# A name becomes a folder of the results (``runs/<name>/...``): printable, short, not "." or "..".
MAX_NAME = 100

# Each table's keys and their types (a nested dict is a table). "number" accepts integers too.
SCHEMA: dict[str, Any] = {
    "name": "string",
    "description": "string",
    "simulation": {"dt": "number", "duration": "number", "transient": "number"},
    "platoon": {
        "n": "integer",
        "center": "list",
        "variance": "list",
        "heading": "number",
        "formation": "string",
        "headings": "string",
        "positions": "list",
    },
    "seed": {"ring_phase": "boolean", "headings": "boolean", "obstacle_jitter": "number"},
    "target": {
        "kind": "string",
        "speed": "number",
        "speeds": "list",
        "waypoints": "list",
        "turn_radius": "number",
        "center": "list",
        "radius": "number",
        "size": "list",
        "laps": "number",
        "start_angle_deg": "number",
        "clockwise": "boolean",
        "start_offset": "list",
    },
    "task": {"kind": "string", "gains": "list", "desired": "table"},
    "avoidance": {"d_minr": "number", "d_mino": "number", "ahead_reference": "string"},
    "vehicle": {
        "wheel_radius": "number",
        "length": "number",
        "max_speed": "number",
        "max_steering_deg": "number",
        "max_steering_rate": "number",
        "steering_gain": "number",
        "gear_hysteresis_deg": "number",
    },
    "safety": {
        "mode": "string",
        "barrier_rate": "number",
        "safety_distance": "number",
        "obstacle_margin": "number",
        "neighbour_cutoff": "number",
        "turning_room": "boolean",
    },
    "obstacles": "list",
    "obstacle_field": {
        "count": "integer",
        "radius_range": "list",
        "region": "list",
        "path_gap": "number",
        "start_gap": "number",
        "obstacle_gap": "number",
    },
}
OBSTACLE = {"center": "list", "radius": "number"}
# The keys every file needs; the ones a choice needs (a path's keys by ``target.kind``, the centre
# and variances of every formation but "explicit", the speed or speeds) are checked where the
# choice is read (``scenario_target``, ``scenario_tables``).
REQUIRED = {
    "": ("name", "simulation", "platoon", "target", "task"),
    "simulation": ("dt", "duration"),
    "platoon": ("n",),
    "target": (),
    "task": ("kind", "gains"),
    "obstacles[]": ("center", "radius"),
    "obstacle_field": ("count", "radius_range", "region"),
}
_ARTICLE = {"number": "a number", "integer": "an integer", "string": "a string", "list": "a list"}
_ARTICLE.update(boolean="true or false", table="a table")


def show(value: Any) -> str:
    """``value`` as an error message shows it: its repr, on one line, at most 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def key_path(path: str, key: str) -> str:
    """``path.key`` as TOML writes a dotted key: ``key`` bare if it is a bare TOML key, else
    quoted (``task.desired." "``), so that an empty or odd key is visible in a message."""
    part = key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)
    return f"{path}.{part}" if path else part


def is_number(value: Any) -> bool:
    """An int or float, not a bool (TOML's true is no number)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class Checks:
    """The checks of one file: ``where`` names it at the start of every message."""

    def __init__(self, where: str) -> None:
        self.where = where

    def error(self, text: str) -> ScenarioError:
        return ScenarioError(f"{self.where}: {text}")

    def must(self, key: str, rule: str, value: Any) -> ScenarioError:
        """``FILE: KEY must be RULE, got VALUE``."""
        return self.error(f"{key} must be {rule}, got {show(value)}")

    def types(self, table: Mapping[str, Any], schema: Mapping[str, Any], path: str = "") -> None:
        """Every key of ``table`` known to ``schema`` and of its type, tables recursively."""
        for key, value in table.items():
            where = key_path(path, key)
            if key not in schema:
                valid = ", ".join(schema)
                raise self.error(f"unknown key {where} = {show(value)}; valid: {valid}")
            expected = schema[key]
            if isinstance(expected, dict):
                if not isinstance(value, dict):
                    raise self.must(where, "a table", value)
                self.types(value, expected, where)
            elif not _has_type(value, expected):
                raise self.must(where, _ARTICLE[expected], value)

    def require(self, table: Mapping[str, Any], path: str, keys: tuple[str, ...]) -> None:
        """``FILE: missing key ...`` for the first of ``keys`` that ``table`` lacks."""
        for key in keys:
            if key not in table:
                raise self.error(f"missing key {path}.{key}" if path else f"missing key {key}")

    def number(
        self,
        key: str,
        value: Any,
        *,
        positive: bool = False,
        at_least: float | None = None,
        bound: float = MAX_MAGNITUDE,
    ) -> float:
        """A finite number of magnitude at most ``bound``: with ``positive`` at least
        MIN_POSITIVE, with ``at_least`` not below it."""
        if not is_number(value) or not math.isfinite(value):
            raise self.must(key, "a finite number", value)
        if positive and not value > 0:
            raise self.must(key, "> 0", value)
        if positive and value < MIN_POSITIVE:
            raise self.must(key, f">= {MIN_POSITIVE:g} (the smallest positive value)", value)
        if at_least is not None and not value >= at_least:
            raise self.must(key, f">= {at_least:g}", value)
        if abs(value) > bound:
            raise self.must(key, f"at most {bound:g} in magnitude", value)
        return float(value)

    def vector(self, key: str, value: Any, length: int, *, bound: float = MAX_MAGNITUDE) -> list[float]:
        """A list of ``length`` finite numbers, each of magnitude at most ``bound``."""
        if not isinstance(value, list) or len(value) != length:
            raise self.must(key, f"a list of {length} numbers", value)
        return [self.number(f"{key}[{i}]", v, bound=bound) for i, v in enumerate(value)]

    def point(self, key: str, value: Any) -> list[float]:
        """``[x, y]`` in metres."""
        if not isinstance(value, list) or len(value) != 2:
            raise self.must(key, "[x, y]", value)
        return self.vector(key, value, 2)

    def name(self, value: str) -> str:
        """The scenario's name (also a folder of the results)."""
        if not value.strip() or not value.isprintable() or len(value) > MAX_NAME or not value.strip("."):
            raise self.must("name", f"printable text of 1 to {MAX_NAME} characters, not dots only", value)
        return value


def _has_type(value: Any, expected: str) -> bool:
    if expected == "number":
        return is_number(value)
    if expected == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    kinds = {"string": str, "boolean": bool, "list": list, "table": dict}
    return isinstance(value, kinds[expected])


def toml_error(where: str, text: str, error: Exception) -> ScenarioError:
    """A TOML syntax error as one line: tomllib's message (with its line and column) and the
    line it points at, so that the key and the value are in the message."""
    message = str(error)
    match = re.search(r"at line (\d+), column (\d+)", message)
    shown = ""
    if match:
        lines = text.splitlines()
        number = int(match.group(1))
        if 1 <= number <= len(lines):
            shown = f": {show(lines[number - 1])}"
    return ScenarioError(f"{where}: not valid TOML: {' '.join(message.split())}{shown}")


def decode_error(where: str, data: bytes, error: UnicodeDecodeError) -> ScenarioError:
    """Bytes that are not UTF-8 as one line: where they are and what they are."""
    line = data.count(b"\n", 0, error.start) + 1
    column = error.start - (data.rfind(b"\n", 0, error.start) + 1) + 1
    bad = data[error.start : error.end]
    return ScenarioError(
        f"{where}: not UTF-8 text: bytes {bad!r} at line {line}, column {column} (TOML files are UTF-8)"
    )
