"""The fuzzer's scenario files: the shipped ones mutated (``platoon_opt.study.fuzz``).

A mutation takes a shipped scenario file and returns its bytes changed in one way (a family:
a deleted key, a wrong type, bytes that are not UTF-8, ...), with what the change was and whether
docs/scenarios.md makes the result an error (``must_fail``): a file that breaks a documented rule
must be refused, one that may be valid must either run sanely or be refused with one line.
Data-level mutations change the parsed table and write it back (``dump``); text-level ones
change the file's text.
"""

from __future__ import annotations

import datetime
import math
import random
from typing import Any, NamedTuple

from platoon_opt.scenario_checks import MAX_MAGNITUDE, MIN_POSITIVE, REQUIRED, SCHEMA
from platoon_opt.scenarios import SCENARIO_DIR, tomllib

Path = tuple[str | int, ...]

# Keys whose values must be > 0 (docs/scenarios.md), and >= 0; by their path without indices.
POSITIVE = {
    "simulation.dt",
    "simulation.duration",
    "platoon.variance",
    "target.speed",
    "avoidance.d_minr",
    "avoidance.d_mino",
    "obstacles.radius",
    "task.desired.var_x",
    "task.desired.var_y",
} | {f"vehicle.{k}" for k in ("wheel_radius", "length", "max_speed", "max_steering_rate", "steering_gain")}
NON_NEGATIVE = {"simulation.transient", "seed.obstacle_jitter", "task.gains", "vehicle.gear_hysteresis_deg"}
DEGREES = {"vehicle.max_steering_deg": (0.0, 90.0), "vehicle.gear_hysteresis_deg": (0.0, 90.0)}
EXTREMES = (1e308, -1e308, 1e-308, -1e-308, 5e-324, -0.0, 0, 0.0, 1e16, -1e16, 2**63 - 1, -(2**63))
NOT_FINITE = (math.nan, math.inf, -math.inf)
# docs/scenarios.md's defaults of [vehicle], in the file's units.
VEHICLE = {
    "wheel_radius": 0.025,
    "length": 0.25,
    "max_speed": 1.0,
    "max_steering_deg": 45.0,
    "max_steering_rate": 40.0,
    "steering_gain": 100.0,
    "gear_hysteresis_deg": 30.0,
}
BAD_UTF8 = (b"\xff", b"\xc3", b"\x80", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80", b"\xc0\xaf", b"\xfe\xff")


class Mutation(NamedTuple):
    """A mutated scenario file.

    Attributes:
        kind: the family and what it did ("type-swap:string-for-number").
        note: the change in words (which key, which value).
        data: the file's bytes.
        must_fail: docs/scenarios.md makes it an error (exit 2), else it may be valid.
    """

    kind: str
    note: str
    data: bytes
    must_fail: bool


def shipped() -> dict[str, str]:
    """The shipped scenario files' texts by name."""
    return {path.stem: path.read_text() for path in sorted(SCENARIO_DIR.glob("*.toml"))}


# --- TOML out ---------------------------------------------------------------------------------


def _value(value: Any) -> str:
    """One TOML value (inline)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        escaped = "".join(
            {'"': '\\"', "\\": "\\\\"}.get(c, c) if c.isprintable() else f"\\u{ord(c):04x}" for c in value
        )
        return f'"{escaped}"'
    if isinstance(value, (datetime.date, datetime.time)):
        return value.isoformat()
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML for {value!r}")


def _key(key: str) -> str:
    bare = key and all(c.isascii() and (c.isalnum() or c in "_-") for c in key)
    return key if bare else _value(key)


def _is_tables(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def dump(data: dict[str, Any], prefix: str = "") -> str:
    """``data`` as TOML text: scalars and inline values first, then tables and arrays of tables."""
    lines, later = [], []
    for key, value in data.items():
        if isinstance(value, dict) or _is_tables(value):
            later.append((key, value))
        else:
            lines.append(f"{_key(key)} = {_value(value)}")
    text = "\n".join(lines) + ("\n" if lines else "")
    for key, value in later:
        name = f"{prefix}.{_key(key)}" if prefix else _key(key)
        if isinstance(value, dict):
            text += f"\n[{name}]\n" + dump(value, name)
        else:
            for table in value:
                text += f"\n[[{name}]]\n" + dump(table, name)
    return text


# --- paths in a table -------------------------------------------------------------------------


def nodes(data: Any, path: Path = ()) -> list[tuple[Path, Any]]:
    """Every (path, value) below ``data``: keys of tables and entries of lists, depth first."""
    found: list[tuple[Path, Any]] = []
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else ()
    for key, value in items:
        found.append(((*path, key), value))
        found += nodes(value, (*path, key))
    return found


def dotted(path: Path) -> str:
    """``("task", "gains", 2)`` -> ``"task.gains[2]"`` (as an error message names it)."""
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text


def rule_key(path: Path) -> str:
    """The path without list indices (``obstacles[2].radius`` -> ``obstacles.radius``)."""
    return ".".join(str(part) for part in path if isinstance(part, str))


def _get(data: Any, path: Path) -> Any:
    for part in path:
        data = data[part]
    return data


def _set(data: Any, path: Path, value: Any) -> None:
    _get(data, path[:-1])[path[-1]] = value


def _delete(data: Any, path: Path) -> None:
    del _get(data, path[:-1])[path[-1]]


def expected_type(path: Path) -> str:
    """The type docs/scenarios.md gives the value at ``path``: a SCHEMA type, or "number" for a
    vector's entry and a desired value, "point" for a waypoint, "table" for an obstacle."""
    key = rule_key(path)
    if key.startswith("task.desired."):
        return "number"
    if isinstance(path[-1], int):
        if len(path) > 1 and isinstance(path[-2], int):
            return "number"  # a waypoint's coordinate
        return {"target.waypoints": "point", "obstacles": "table"}.get(rule_key(path[:-1]), "number")
    if path[0] == "obstacles" and len(path) == 3:
        return {"center": "list", "radius": "number"}[str(path[2])]
    schema: Any = SCHEMA
    for part in key.split("."):
        schema = schema[part]
    return "table" if isinstance(schema, dict) else str(schema)


def required(path: Path, data: dict[str, Any]) -> bool:
    """Whether deleting ``path`` (or emptying it) breaks a documented rule."""
    if isinstance(path[-1], int):
        parent = rule_key(path[:-1])
        if isinstance(path[-2], int) or parent not in ("obstacles", "target.waypoints"):
            return True  # a fixed-length vector ([x, y], the variances, the gains) loses an entry
        return parent == "target.waypoints" and len(_get(data, path[:-1])) == 1
    if len(path) == 1:
        return str(path[0]) in REQUIRED[""]
    if path[0] == "obstacles":
        return True
    if path[:2] == ("task", "desired"):
        return True  # every desired component but the means is required, and no mean is given
    return str(path[-1]) in REQUIRED.get(rule_key(path[:-1]), ())


def breaks_range(path: Path, value: Any) -> bool:
    """Whether number ``value`` at ``path`` breaks a documented range (not the cross-key ones)."""
    key = rule_key(path)
    if abs(value) > MAX_MAGNITUDE**2 or (abs(value) > MAX_MAGNITUDE and not _square(key)):
        return True
    if key in DEGREES:
        low, high = DEGREES[key]
        return not (low < value < high if key.endswith("steering_deg") else low <= value < high)
    if key in POSITIVE:
        return not value > 0 or value < MIN_POSITIVE and not _square(key)
    if key in NON_NEGATIVE:
        return value < 0
    if key == "platoon.n":
        return not 2 <= value <= 1_000_000
    return False


def _square(key: str) -> bool:
    return key in ("platoon.variance", "task.desired.var_x", "task.desired.var_y", "task.desired.cov_xy")


# --- the families -----------------------------------------------------------------------------


def _wrong_values(kind: str, rng: random.Random) -> Any:
    """A value of a type other than ``kind``."""
    choices: dict[str, list[Any]] = {
        "number": ["1.0", "", True, [1.0], {"a": 1}, datetime.date(2020, 1, 1), []],
        "integer": [8.0, 2.5, "8", False, [8], {}, datetime.time(7, 32)],
        "string": [1, 0.5, True, ["a"], {"kind": "x"}, []],
        "boolean": [1, 0, "true", "yes", [True], {}],
        "list": ["[0, 0]", 1.0, {"x": 0}, True, "", 0],
        "point": ["0, 0", 1.0, {"x": 0, "y": 0}, [[0, 0]], [0, "1"], []],
        "table": [1, "x", [1, 2], True, [], 0.5],
    }
    return rng.choice(choices[kind])


def _numeric(data: dict[str, Any]) -> list[tuple[Path, Any]]:
    return [(p, v) for p, v in nodes(data) if isinstance(v, (int, float)) and not isinstance(v, bool)]


def data_mutation(family: str, data: dict[str, Any], rng: random.Random) -> tuple[str, str, bool]:
    """Change ``data`` in place by ``family``; returns (kind, note, must_fail)."""
    if family == "delete-key":
        path, _ = rng.choice(nodes(data))
        fails = required(path, data)
        _delete(data, path)
        return f"delete-key:{rule_key(path)}", f"deleted {dotted(path)}", fails
    if family == "type-swap":
        path, value = rng.choice(nodes(data))
        kind = expected_type(path)
        wrong = _wrong_values(kind, rng)
        _set(data, path, wrong)
        return f"type-swap:{type(wrong).__name__}-for-{kind}", f"{dotted(path)} = {wrong!r}", True
    if family in ("extreme-number", "not-finite", "value-tweak"):
        path, value = rng.choice(_numeric(data))
        if family == "not-finite":
            new = rng.choice(NOT_FINITE)
            _set(data, path, new)
            return f"not-finite:{rule_key(path)}", f"{dotted(path)} = {new!r}", True
        units = rule_key(path) == "platoon.n"
        if family == "extreme-number":
            # No huge valid platoon: a run of a million units is slow, not wrong.
            new = rng.choice((2**63 - 1, -(2**63), 0, 10**7, 1e308, -0.0) if units else EXTREMES)
        elif units:
            new = rng.choice((0, 1, 2, 3, -1, 16, 64, 8.0, 2.5))
        else:
            factor = rng.choice((-1.0, 0.0, 1e3, 1e-3, -1e-3, 0.5, 2.0, 1.5, 10.0))
            new = value * factor if rng.random() < 0.8 else value + rng.choice((-1, 1, -100, 100))
        _set(data, path, new)
        kind = f"{family}:{rule_key(path)}"
        if rule_key(path) == "platoon.n" and isinstance(new, float):
            return kind, f"{dotted(path)} = {new!r}", True
        return kind, f"{dotted(path)} = {new!r}", breaks_range(path, new) or _cross_fails(data)
    if family == "wrong-nesting":
        return _nest(data, rng)
    if family == "empty-table":
        tables = [(p, v) for p, v in nodes(data) if isinstance(v, (dict, list)) and v]
        path, value = rng.choice(tables)
        empty: Any = {} if isinstance(value, dict) else []
        keys = value if isinstance(value, dict) else range(len(value))
        fails = any(required((*path, k), data) for k in keys)
        if rule_key(path) in ("target.waypoints", "obstacles") and isinstance(value, list):
            fails = rule_key(path) == "target.waypoints"
        _set(data, path, empty)
        return f"empty-table:{type(empty).__name__}", f"{dotted(path)} emptied", fails
    if family == "unknown-key":
        owners: list[tuple[Path, dict[str, Any]]] = [((), data)]
        owners += [(p, v) for p, v in nodes(data) if isinstance(v, dict)]
        path, table = rng.choice(owners)
        name = rng.choice(("bogus", "dT", "Dt", "N", "n2", "ｎ", "", " ", "simulation", "kind_", "x.y"))
        while name in table:
            name += "_"
        table[name] = rng.choice((1, "x", [1], {"a": 1}, True, 0.5))
        return f"unknown-key:{rule_key(path) or 'top'}", f"added {dotted((*path, name))}", True
    raise ValueError(f"no data mutation {family!r}")


def _cross_fails(data: dict[str, Any]) -> bool:
    """The cross-key rules of docs/scenarios.md, where the keys are numbers."""
    try:
        sim = data["simulation"]
        dt, duration, transient = sim["dt"], sim["duration"], sim.get("transient", 4.0)
        if duration < dt or transient >= duration or duration / dt > 1e7:
            return True
        desired = data["task"].get("desired", {})
        if "cov_xy" in desired:
            return not abs(desired["cov_xy"]) < math.sqrt(max(desired["var_x"] * desired["var_y"], 0.0))
    except (KeyError, TypeError, ZeroDivisionError, OverflowError):
        return False
    return False


def _nest(data: dict[str, Any], rng: random.Random) -> tuple[str, str, bool]:
    """A key or table put where it does not belong."""
    leaves = [(p, v) for p, v in nodes(data) if isinstance(p[-1], str) and len(p) <= 3]
    path, value = rng.choice(leaves)
    how = rng.choice(("move", "wrap", "array") + (("flatten",) if len(path) > 1 else ()))
    if how == "move":
        targets: list[tuple[Path, dict[str, Any]]] = [((), data)]
        targets += [
            (p, v)
            for p, v in nodes(data)
            if isinstance(v, dict) and p != path[:-1] and p[: len(path)] != path
        ]
        target_path, target = rng.choice(targets)
        name = str(path[-1])
        if name in target or (not target_path and len(path) == 1):
            target_path, target = ("bogus",), data.setdefault("bogus", {})
        _delete(data, path)
        target[name] = value
        return "wrong-nesting:move", f"{dotted(path)} moved into [{dotted(target_path)}]", True
    if how == "wrap":
        _set(data, path, {str(path[-1]): value})
        return "wrong-nesting:wrap", f"{dotted(path)} wrapped in a table of itself", True
    if how == "array":
        _set(data, path, [value] if isinstance(value, dict) else [{"value": value}])
        return "wrong-nesting:array", f"{dotted(path)} made an array of tables", True
    _delete(data, path)
    data[dotted(path)] = value  # a quoted dotted key at the top: "simulation.dt" = 0.01
    return "wrong-nesting:flatten", f"{dotted(path)} as one top-level key", True


def text_mutation(family: str, text: str, rng: random.Random) -> tuple[str, str, bytes, bool]:
    """Change the file's text by ``family``; returns (kind, note, bytes, must_fail)."""
    data = text.encode()
    lines = text.splitlines(keepends=True)
    if family == "duplicate-key":
        candidates = [i for i, line in enumerate(lines) if "=" in line and not line.lstrip().startswith("#")]
        headers = [i for i, line in enumerate(lines) if line.startswith("[")]
        i = rng.choice(candidates + headers)
        copy = lines[i] if rng.random() < 0.5 or i in headers else lines[i].split("=")[0] + "= 1\n"
        where = rng.choice((i + 1, len(lines)))
        if where == len(lines) and i not in headers:
            where = i + 1  # at the end it would belong to the last table
        lines.insert(where, copy)
        # A repeated [[obstacles]] is an obstacle without keys; anything else is repeated TOML.
        return "duplicate-key", f"line {i + 1} repeated: {lines[i].strip()!r}", "".join(lines).encode(), True
    if family == "random-bytes":
        pool = b" \t\n\r=[]{}\"'#.,-+_:0123456789abcdefxyzEeinf\x00\x01\x1b\x7f\xc3\xa9\xe2\x82\xac"
        chunk = bytes(rng.choice(pool) for _ in range(rng.randint(1, 8)))
        at = rng.randrange(len(data) + 1)
        return "random-bytes", f"{chunk!r} at byte {at}", data[:at] + chunk + data[at:], False
    if family == "not-utf8":
        chunk = rng.choice(BAD_UTF8)
        at = rng.randrange(len(data) + 1)
        while 0 < at < len(data) and (data[at] & 0xC0) == 0x80:
            at -= 1  # not inside a character: the file stays valid elsewhere
        return "not-utf8", f"{chunk!r} at byte {at}", data[:at] + chunk + data[at:], True
    if family == "empty-file":
        body = rng.choice(("", "\n", "# nothing but a comment\n", "\ufeff", "   \n\t\n", "[simulation]\n"))
        return "empty-file", f"the file is {body!r}", body.encode(), True
    if family == "truncate":
        at = rng.randrange(len(data))
        return "truncate", f"cut at byte {at} of {len(data)}", data[:at], False
    raise ValueError(f"no text mutation {family!r}")


DATA_FAMILIES = (
    "delete-key",
    "type-swap",
    "extreme-number",
    "not-finite",
    "value-tweak",
    "wrong-nesting",
    "empty-table",
    "unknown-key",
)
TEXT_FAMILIES = ("duplicate-key", "random-bytes", "not-utf8", "empty-file", "truncate")
FILE_FAMILIES = DATA_FAMILIES + TEXT_FAMILIES


def mutate(family: str, rng: random.Random, texts: dict[str, str] | None = None) -> tuple[str, Mutation]:
    """A shipped file (its name) and its mutation by ``family``."""
    texts = texts if texts is not None else shipped()
    name = rng.choice(sorted(texts))
    text = texts[name]
    if family in TEXT_FAMILIES:
        return name, Mutation(*text_mutation(family, text, rng))
    data = tomllib.loads(text)
    if rng.random() < 0.5:
        data["vehicle"] = dict(VEHICLE)  # the defaults, written out: their keys get mutated too
    kind, note, fails = data_mutation(family, data, rng)
    return name, Mutation(kind, note, dump(data).encode(), fails)
