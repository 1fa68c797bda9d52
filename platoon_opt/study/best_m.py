"""The report's comparison against the best m: every allocator that is not the paper's iteration,
paired by seed against the best m of 0..8 (by the report's score, and per error), as ratios of
means with bootstrap intervals (``ratios``)."""

from __future__ import annotations

from collections.abc import Sequence

from platoon_opt.metrics import ERROR_METRICS
from platoon_opt.study.config import AllocatorConfig
from platoon_opt.study.markdown import table
from platoon_opt.study.ratios import NEGLIGIBLE, RESAMPLES, Change, change_text, paired_change
from platoon_opt.study.statistics import METRICS, Comparison, RunTable, score

# Compared by their differences (counts and durations, often 0 for every seed of the best m).
DIFFERENCES = ("gear_flips", "time_inside_obstacles")


def best_m_by_score(table_: RunTable, study: Comparison, scenario: str) -> AllocatorConfig | None:
    """The m of 0..8 (the baseline included) with the lowest score, or None if no m ran."""
    iterative = [
        c for c in study.configs if c.iteration_count is not None and table_.has(scenario, "base", c.label)
    ]
    if not iterative:
        return None
    baseline = study.baseline.label
    return min(iterative, key=lambda c: score(table_, scenario, "base", c.label, baseline))


def best_m_of(table_: RunTable, study: Comparison, scenario: str, metric: str) -> AllocatorConfig | None:
    """The m with the lowest mean of ``metric`` over the seeds every m ran, or None."""
    iterative = [
        c for c in study.configs if c.iteration_count is not None and table_.has(scenario, "base", c.label)
    ]
    seeds = table_.seeds(scenario, "base", *(c.label for c in iterative))
    if not iterative or not seeds:
        return None
    return min(iterative, key=lambda c: float(table_.values(scenario, "base", c.label, metric, seeds).mean()))


def _iterative(table_: RunTable, study: Comparison, scenario: str) -> list[AllocatorConfig]:
    """The study's m that ran on ``scenario``."""
    return [
        c for c in study.configs if c.iteration_count is not None and table_.has(scenario, "base", c.label)
    ]


def compare(table_: RunTable, scenario: str, config: str, reference: str, metric: str) -> Change:
    """``config`` against ``reference`` on their common seeds (``ratios.paired_change``)."""
    seeds = table_.seeds(scenario, "base", config, reference)
    values = table_.values(scenario, "base", config, metric, seeds)
    base = table_.values(scenario, "base", reference, metric, seeds)
    return paired_change(
        values, base, lower_is_better=METRICS[metric].lower_is_better, ratio=metric not in DIFFERENCES
    )


def best_m_section(study: Comparison, table_: RunTable) -> str:
    """Per scenario: the allocators other than the iteration against the best m by score, and
    against the best m of each error; "" if no scenario ran both kinds."""
    parts = [
        "## Against the best m\n",
        "Each allocator other than the paper's iteration against the best m of the study on the same "
        "seeds, paired by seed. An error: the percent change of its mean, the ratio of the two means "
        f"minus 1, with the 95 % percentile interval of that ratio over {RESAMPLES:,} paired bootstrap "
        "resamples of the seeds (it cannot leave -100 %); where the best m's mean is below "
        f"{NEGLIGIBLE:g} in the metric's units, the mean paired difference in those units with its 95 % "
        "t-interval instead. Gear flips and time inside obstacles: the mean paired difference with its "
        "95 % t-interval. Negative is better. Wins: the seeds on which the allocator's error is lower, "
        "of all (ties count one half). The first table takes the best m by the report's score "
        "(mean error after the transient, var_x, var_y, each relative to the baseline, averaged); "
        "the second the best m of each error, named in its column.\n",
    ]
    others = [c for c in study.configs if c.iteration_count is None]
    for scenario in study.scenarios:
        name = scenario.name
        present = [c.label for c in others if table_.has(name, "base", c.label)]
        best = best_m_by_score(table_, study, name)
        if best is None or not present:
            continue
        keys = (*ERROR_METRICS, *DIFFERENCES)
        header = ["allocator", *(METRICS[k].title for k in keys), "wins (mean position, var_x, var_y)"]
        rows = [_row(table_, name, label, {k: best.label for k in keys}) for label in present]
        parts.append(f"### {name}: against the best m by score, `{best.label}`\n")
        parts.append(table(header, rows))
        per_metric = {k: best_m_of(table_, study, name, k) for k in keys}
        references = {k: (c.label if c else best.label) for k, c in per_metric.items()}
        header = [
            "allocator",
            *(f"{METRICS[k].title} (vs `{references[k]}`)" for k in keys),
            "wins (mean position, var_x, var_y)",
        ]
        parts.append(f"### {name}: against the best m of each error\n")
        parts.append(table(header, [_row(table_, name, label, references) for label in present]))
    return "\n".join(parts) if len(parts) > 2 else ""


def _row(table_: RunTable, scenario: str, label: str, references: dict[str, str]) -> Sequence[str]:
    changes = {k: compare(table_, scenario, label, ref, k) for k, ref in references.items()}
    wins = "; ".join(_wins(changes[k]) for k in ("mean_position", "var_x", "var_y"))
    units = {k: "" if METRICS[k].unit == "count" else METRICS[k].unit for k in changes}
    return [f"`{label}`", *(change_text(c, units[k]) for k, c in changes.items()), wins]


def _wins(change: Change) -> str:
    return "—" if change.n == 0 else f"{change.wins * change.n:g}/{change.n}"
