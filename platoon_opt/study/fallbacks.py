"""How often a configuration fell back, where a reader sees it: one warning line on stderr per
run (``simulate``) or per configuration and scenario (a study), and the report's table.

A step falls back when its allocator raised (the controller answered, status
``fallback:<Type>: <message>``) or answered with a fallback of its own. A few such steps are a
solver's bad moments; more than ``WARN_SHARE`` of a run's steps means its errors are partly the
fallback's, and the line says which allocator, how many steps and the first status.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, NamedTuple

import numpy as np

from platoon_opt.trajectory import Trajectory

# Above this share of its steps a run (or a configuration on a scenario) is reported.
WARN_SHARE = 0.01


class FallbackCount(NamedTuple):
    """Fallbacks of one configuration on one scenario (and variant), over its runs.

    Attributes:
        scenario: the scenario's name, with the ablation variant in parentheses if not ``base``.
        config: the configuration's label (or the allocator's name, for one run).
        runs: runs counted.
        steps: their steps.
        fallbacks: steps that fell back.
        first: the status of the first step that fell back ("" if none), and ``where`` (its
            seed and time, in words).
    """

    scenario: str
    config: str
    runs: int
    steps: int
    fallbacks: int
    first: str
    where: str

    @property
    def share(self) -> float:
        """Fallbacks per step (0 for no steps)."""
        return self.fallbacks / self.steps if self.steps else 0.0

    @property
    def too_many(self) -> bool:
        """More than ``WARN_SHARE`` of the steps fell back."""
        return self.share > WARN_SHARE

    def warning(self) -> str:
        """One line: ``platoon-opt: warning: ALLOCATOR fell back on K of N steps ...``."""
        runs = f" over {self.runs} runs" if self.runs > 1 else ""
        return (
            f"platoon-opt: warning: {self.config} fell back on {self.fallbacks:,} of {self.steps:,} steps "
            f"({100 * self.share:.3g} %) on {self.scenario}{runs}; first {self.where}: {self.first}"
        )


def first_fallback(trajectory: Trajectory) -> tuple[str, float | None]:
    """The status and time (s) of the run's first step that fell back; ("", None) if none."""
    steps = np.flatnonzero(trajectory.fell_back)
    if not steps.size:
        return "", None
    return str(trajectory.status[steps[0]]), float(trajectory.t[steps[0]])


def run_count(trajectory: Trajectory, config: str) -> FallbackCount:
    """The fallbacks of one run."""
    status, t = first_fallback(trajectory)
    where = f"at t = {t:.4g} s" if t is not None else ""
    fallbacks = int(np.count_nonzero(trajectory.fell_back))
    scenario = f"{trajectory.scenario} (seed {trajectory.seed})"
    return FallbackCount(scenario, config, 1, trajectory.steps, fallbacks, status, where)


def study_counts(runs: Iterable[Mapping[str, Any]]) -> list[FallbackCount]:
    """The fallbacks of every configuration on every scenario (and variant) of a study's runs
    (result dicts of ``runs.run_spec``), in the order first seen."""
    cells: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for run in runs:
        variant = run.get("variant", "base")
        scenario = run["scenario"] if variant == "base" else f"{run['scenario']} ({variant})"
        cells.setdefault((scenario, run["config"]), []).append(run)
    counts = []
    for (scenario, config), cell in cells.items():
        fell = sorted((r for r in cell if r.get("fallback_steps", 0)), key=lambda r: r["seed"])
        first, where = "", ""
        if fell:
            first = str(fell[0].get("first_fallback", ""))
            t = fell[0].get("first_fallback_t")
            where = f"in seed {fell[0]['seed']}" + (f" at t = {t:.4g} s" if isinstance(t, float) else "")
        counts.append(
            FallbackCount(
                scenario,
                config,
                len(cell),
                sum(int(r.get("steps", 0)) for r in cell),
                sum(int(r.get("fallback_steps", 0)) for r in cell),
                first,
                where,
            )
        )
    return counts


def share_text(count: FallbackCount) -> str:
    """A count's share of the steps for a table cell, flagged above ``WARN_SHARE``."""
    text = f"{100 * count.share:.3g} %"
    return f"**{text}, above {100 * WARN_SHARE:g} %**" if count.too_many else text


def report_note(runs: Iterable[Mapping[str, Any]]) -> str:
    """The report's paragraph on the configurations that fell back on more than ``WARN_SHARE``
    of their steps (markdown), or "" if none did."""
    counts = [count for count in study_counts(runs) if count.too_many]
    if not counts:
        return ""
    lines = [
        f"**Fallbacks on more than {100 * WARN_SHARE:g} % of the steps**: the errors of these runs are "
        "partly the fallback's (every configuration's count is in the compute-time section).\n"
    ]
    for count in counts:
        lines.append(
            f"- `{count.config}` on {count.scenario}: {count.fallbacks:,} of {count.steps:,} steps "
            f"({100 * count.share:.3g} %) over {count.runs} runs; first {count.where}: `{count.first}`"
        )
    return "\n".join(lines) + "\n"
