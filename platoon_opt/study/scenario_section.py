"""The report's scenario section: per scenario, everything needed to re-run its numbers (the file,
the platoon, the target path, gains, avoidance, vehicle, obstacles and what a seed varies), in
words, from ``runs.scenario_definition``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from platoon_opt.scenarios import Scenario
from platoon_opt.study.markdown import seeds_text, table
from platoon_opt.study.runs import scenario_definition


def scenario_section(
    scenarios: Sequence[Scenario], duration: float | None, seeds: Sequence[int], out: Path
) -> str:
    """The section for ``scenarios`` as run for ``duration`` s (None: each file's own) on
    ``seeds``; sources relative to ``out``."""
    parts = ["## Scenarios (everything needed to re-run the numbers)\n"]
    for scenario in scenarios:
        d = scenario_definition(scenario, out)
        vehicle, avoidance = d["vehicle"], d["avoidance"]
        simulated, desired = duration or d["duration"], d["task"]["desired"]
        rows = [
            ["file", f"`{d['source']}`"],
            [
                "units",
                f"{d['n']}, start around ({d['center'][0]:g}, {d['center'][1]:g}) m {formation_text(d)}, "
                f"headings {d['headings'].replace('_', ' ')}",
            ],
            ["time", f"dt {d['dt']:g} s, {simulated:g} s simulated, transient {d['transient']:g} s"],
            ["target", target_text(d["target"])],
            ["goal", ", ".join(f"{k} {v:g}" for k, v in desired.items()) + ", the mean on the target"],
            [
                "gains",
                f"K = diag({', '.join(f'{g:g}' for g in d['task']['gains'])}), "
                f"K_alpha {vehicle['steering_gain']:g} 1/s",
            ],
            [
                "avoidance",
                f"d_minr {avoidance['d_minr']:g} m, d_mino {avoidance['d_mino']:g} m, "
                f'"ahead" on the {avoidance["ahead_reference"]}',
            ],
            [
                "vehicle",
                f"wheel radius {vehicle['wheel_radius']:g} m, length {vehicle['length']:g} m, "
                f"max speed {vehicle['max_speed']:g} m/s, max steering {vehicle['max_steering_deg']:g} deg, "
                f"max steering rate {vehicle['max_steering_rate']:g} rad/s, gear hysteresis "
                f"{vehicle['gear_hysteresis_deg']:g} deg",
            ],
            ["obstacles", obstacles_text(d)],
            ["a seed varies", varies_text(d)],
            ["seeds", seeds_text(seeds)],
        ]
        parts.append(f"### {scenario.name}\n")
        parts.append(table(["", ""], rows))
    return "\n".join(parts)


def formation_text(d: dict[str, Any]) -> str:
    """Where the units start: the formation and the variances it is scaled to."""
    if d["positions"] is not None:
        return "at the file's positions"
    return f"in a {d['formation']} with variances {d['variance'][0]:g}, {d['variance'][1]:g} m^2"


def target_text(target: dict[str, Any]) -> str:
    """The target path: its kind, its points or shape, its speed and length."""
    table_, kind = target["table"], target["kind"]
    if kind in ("circle", "figure_eight"):
        shape = ", ".join(f"{k} {v}" for k, v in table_.items() if k not in ("kind", "speed"))
        path = f"a {kind.replace('_', '-')} ({shape})"
    else:
        points = " → ".join(f"({x:g}, {y:g})" for x, y in target["waypoints"])
        path = {"spline": "a spline through"}.get(kind, "straight legs through") + f" {points}"
        if "turn_radius" in table_:
            path += f", corners rounded to {table_['turn_radius']:g} m"
    speeds = table_.get("speeds")
    each = ", ".join(f"{v:g}" for v in speeds or ())
    speed = f"at {each} m/s per leg" if speeds else f"at {target['speed']:g} m/s"
    return f"{speed} {path}, {target['length']:.1f} m"


def obstacles_text(d: dict[str, Any]) -> str:
    """The file's obstacles, their jitter and the obstacle field a seed draws."""
    fixed = ", ".join(f"({o['center'][0]:g}, {o['center'][1]:g}) r {o['radius']:g}" for o in d["obstacles"])
    parts = [fixed] if fixed else []
    jitter = d["seed_varies"]["obstacle_jitter"]
    if fixed and jitter:
        parts[0] += f" (centres jittered by N(0, {jitter:g} m) per seed)"
    field = d["seed_varies"]["obstacle_field"]
    if field is not None:
        x0, y0, x1, y1 = field["region"]
        low, high = field["radius_range"]
        clear = f", {field['path_gap']:g} m clear of the path" if field["path_gap"] is not None else ""
        parts.append(
            f"{field['count']} per seed of radius {low:g}-{high:g} m in [{x0:g}, {x1:g}] x "
            f"[{y0:g}, {y1:g}] m, {field['obstacle_gap']:g} m apart, {field['start_gap']:g} m from the "
            f"starts{clear}"
        )
    return "; ".join(parts) or "none"


def varies_text(d: dict[str, Any]) -> str:
    """What a seed draws."""
    varies = d["seed_varies"]
    drawn = (
        ("ring phase", d["positions"] is None and d["formation"] == "ring" and varies["ring_phase"]),
        ("positions in the disk", d["positions"] is None and d["formation"] == "disk"),
        ("headings", varies["headings"]),
        ("obstacle centres", bool(varies["obstacle_jitter"])),
        ("the obstacle field", varies["obstacle_field"] is not None),
    )
    return ", ".join(k for k, on in drawn if on) or "nothing"
