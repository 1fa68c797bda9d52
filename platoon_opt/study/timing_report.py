"""The compute-time section of a study's report: time per step and per solve, fallbacks and
program changes per configuration (``report.write_report`` puts it in report.md)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from platoon_opt.study.fallbacks import share_text, study_counts
from platoon_opt.study.harness import Study
from platoon_opt.study.markdown import number, table

# (scenario, configuration label, metric) -> the summary row, or None.
Row = Callable[[str, str, str], dict[str, Any] | None]


def timing_section(study: Study, runs: Iterable[Mapping[str, Any]], row: Row) -> str:
    """The report's section on compute time per step and per solve, fallbacks and program
    changes: a table per scenario, a row per configuration (``row`` looks up a summary row by
    scenario, configuration and metric)."""
    out = [
        "## Compute time per step and per solve\n",
        "Allocator, per step: the allocation alone (wall time; mean over seeds of each run's median "
        "and 95th percentile over every step). Per solve: the same over the steps whose allocation "
        "ran a solve of its own, leaving out those that reused an earlier one (`nmpc` hands its "
        "stored plan between solves, in about 0 s); for every other allocator each step is a "
        "solve. Whole step: the allocation plus the problem set-up, the unit controllers, the "
        "kinematics and the logging, per step (CPU time of the worker, and wall time, which grows "
        "when the machine runs other work). Fallback: steps per run whose allocation fell back "
        "(the allocator's own fallback, e.g. `nmpc`'s to `qp`, or the controller's projection of "
        "the nominal velocity when the allocator raised), and their share of all steps, flagged "
        "above 1 %. Program changes: steps per run answered by another program than the "
        "configuration's (a `cone` variant on the polygon, strict priority's stage 1 alone, a "
        "projection); a fallback to another exact solver of the same program is a fallback step "
        "but no program change.\n",
    ]
    # (metric, column) of the times, shown in ms.
    columns = (
        ("solve_time_median", "allocator per step, median (ms)"),
        ("solve_time_p95", "p95 (ms)"),
        ("solve_time_per_solve_median", "allocator per solve, median (ms)"),
        ("solve_time_per_solve_p95", "p95 (ms)"),
        ("step_cpu_time", "whole step CPU (ms)"),
        ("step_time", "whole step wall (ms)"),
    )
    shares = {(c.scenario, c.config): c for c in study_counts(runs)}
    for scenario in study.scenarios:
        rows = []
        for config in study.configs:
            cells = [row(scenario.name, config.label, key) for key, _ in columns]
            fallback = row(scenario.name, config.label, "fallback_steps")
            if fallback is None:
                continue
            solves = row(scenario.name, config.label, "solve_steps")
            changes = row(scenario.name, config.label, "program_changes")
            rows.append(
                [f"`{config.label}`"]
                + [f"{1e3 * c['mean']:.3g}" if c and math.isfinite(c["mean"]) else "—" for c in cells]
                + [number(solves["mean"], 4) if solves else "—", number(fallback["mean"], 3)]
                + [number(changes["mean"], 3) if changes else "—"]
                + [share_text(shares[(scenario.name, config.label)])]
            )
        out.append(f"### {scenario.name}\n")
        header = [
            "config",
            *(title for _, title in columns),
            "solves per run",
            "fallback steps per run",
            "program changes per run",
            "fallback share",
        ]
        out.append(table(header, rows))
    return "\n".join(out)
