"""The report's "Who wins where": one row per scenario, one column per error, the best allocator
other than the paper's iteration against the best m of that error (``best_m``), with the verdict
of the paired interval."""

from __future__ import annotations

import math

from platoon_opt.metrics import ERROR_METRICS
from platoon_opt.study.best_m import best_m_of, compare
from platoon_opt.study.markdown import table
from platoon_opt.study.ratios import Change, change_text
from platoon_opt.study.statistics import METRICS, Comparison, RunTable

# The columns: the four errors and the time inside obstacles.
COLUMNS = (*ERROR_METRICS, "time_inside_obstacles")


def verdict(change: Change) -> str:
    """The verdict of a paired change: "win" when its whole 95 % interval lies below 0 (better),
    "loss" when above, "tie" when it holds 0, "n/a" without an interval."""
    if change.n == 0 or math.isnan(change.high):
        return "n/a"
    if change.high < 0:
        return "win"
    if change.low > 0:
        return "loss"
    return "tie"


def _cell(table_: RunTable, study: Comparison, scenario: str, metric: str) -> tuple[str, str]:
    """The best other allocator of ``metric`` against its best m: the cell's text and verdict."""
    others = [
        c.label for c in study.configs if c.iteration_count is None and table_.has(scenario, "base", c.label)
    ]
    best_m = best_m_of(table_, study, scenario, metric)
    seeds = table_.seeds(scenario, "base", *others) if others else ()
    if best_m is None or not others or not seeds:
        return "—", "n/a"
    best = min(others, key=lambda label: float(table_.values(scenario, "base", label, metric, seeds).mean()))
    change = compare(table_, scenario, best, best_m.label, metric)
    outcome = verdict(change)
    unit = "" if METRICS[metric].unit == "count" else METRICS[metric].unit
    mark = {"win": " **win**", "loss": " loss", "tie": "", "n/a": ""}[outcome]
    return f"`{best}` vs `{best_m.label}`: {change_text(change, unit)}{mark}", outcome


def _changes(study: Comparison, table_: RunTable, label: str) -> list[tuple[Change, str]]:
    """``label`` against the best m of each error on every scenario it ran: each change, with the
    cell's name ("scenario, error vs `m=k`")."""
    changes = []
    for scenario in study.scenarios:
        if not table_.has(scenario.name, "base", label):
            continue
        for metric in ERROR_METRICS:
            best_m = best_m_of(table_, study, scenario.name, metric)
            if best_m is not None:
                change = compare(table_, scenario.name, label, best_m.label, metric)
                changes.append((change, f"{scenario.name}, {METRICS[metric].title} vs `{best_m.label}`"))
    return changes


def _each_allocator(study: Comparison, table_: RunTable) -> list[list[str]]:
    """Per allocator other than the iteration: its verdicts against the best m of each error over
    every scenario it ran (wins, intervals holding 0, losses) and its worst cell."""
    rows = []
    for config in (c for c in study.configs if c.iteration_count is None):
        changes = _changes(study, table_, config.label)
        if not changes:
            continue
        outcomes = [verdict(change) for change, _ in changes]
        ratios = [(c, name) for c, name in changes if c.kind == "ratio" and not math.isnan(c.value)]
        worst = "—"
        if ratios:
            change, name = max(ratios, key=lambda item: item[0].value)
            worst = f"{name}: {change_text(change, '')}"
        counts = [str(outcomes.count(key)) for key in ("win", "tie", "loss")]
        rows.append([f"`{config.label}`", *counts, worst])
    return rows


def winners_section(study: Comparison, table_: RunTable) -> str:
    """The table over every scenario that ran both the iteration and another allocator; "" when
    fewer than two did."""
    rows, outcomes = [], []
    for scenario in study.scenarios:
        cells = [_cell(table_, study, scenario.name, metric) for metric in COLUMNS]
        if all(outcome == "n/a" for _, outcome in cells):
            continue
        rows.append([scenario.name, *(text for text, _ in cells)])
        outcomes += [outcome for (_, outcome), metric in zip(cells, COLUMNS) if metric in ERROR_METRICS]
    if len(rows) < 2:
        return ""
    counts = {key: outcomes.count(key) for key in ("win", "tie", "loss")}
    return "\n".join(
        [
            "## Who wins where\n",
            "Per scenario and error: the allocator other than the paper's iteration with the lowest "
            "mean, against the m of 0..8 with the lowest mean of that error, both picked on these "
            'seeds, paired by seed (the change and its interval as in "Against the best m"). '
            "**win**: the whole 95 % interval below 0; loss: above 0; otherwise the interval "
            f"holds 0. Over the four errors: {counts['win']} wins, {counts['tie']} cells whose "
            f"interval holds 0, {counts['loss']} losses, of {len(outcomes)}.\n",
            table(["scenario", *(METRICS[m].title for m in COLUMNS)], rows),
            "\n### Each allocator on every scenario\n",
            "One allocator, not the best of each cell: its change against the best m of each error, "
            "as above, on every scenario and error, counted by verdict, and its worst cell (the "
            "largest change of a ratio).\n",
            table(
                ["allocator", "wins", "intervals holding 0", "losses", "worst cell"],
                _each_allocator(study, table_),
            ),
        ]
    )
