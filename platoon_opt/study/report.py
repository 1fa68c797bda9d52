"""Statistics, tables, figures and the report of a harness study.

Statistics (per scenario, ablation variant, configuration and metric, over the seeds that
the configuration shares with the baseline):

- mean over seeds with a 95 % t-interval;
- percent change of the mean against the baseline (m = 0),
  ``100 (mean_c - mean_0) / mean_0``, with a 95 % interval from the paired t-interval
  of the per-seed differences ``x_c - x_0`` divided by ``mean_0``;
- median over seeds of the per-seed percent change;
- win rate against the baseline and against the best m: the fraction of seeds where the
  configuration is better (ties count one half).

"Best" (best m, best other allocator) minimizes the score: the average over
``SCORE_METRICS`` of the ratio of the configuration's mean to the baseline's mean.
"""

from __future__ import annotations

import math
import os
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from platoon_opt.study.output import write_atomic, write_csv, write_json

if TYPE_CHECKING:
    from platoon_opt.simulation import Trajectory
    from platoon_opt.study.harness import AllocatorConfig, Study, StudyResult


@dataclass(frozen=True)
class Metric:
    """A per-run score: its key in a run's result, title, unit, and whether lower is better."""

    key: str
    title: str
    unit: str
    lower_is_better: bool = True


METRICS = {
    m.key: m
    for m in (
        Metric("mean_position", "mean position", "m s"),
        Metric("mean_position_after_transient", "mean position after transient", "m s"),
        Metric("var_x", "var_x", "m^2 s"),
        Metric("var_y", "var_y", "m^2 s"),
        Metric("gear_flips", "gear flips", "count"),
        Metric("time_inside_obstacles", "time inside obstacles", "unit s"),
        Metric("min_clearance", "min clearance", "m", lower_is_better=False),
        Metric("min_unit_distance", "min unit distance", "m", lower_is_better=False),
        Metric("fallback_steps", "fallback steps", "count"),
        Metric("solve_time_median", "allocator time median", "s"),
        Metric("solve_time_p95", "allocator time p95", "s"),
        Metric("step_time", "whole step time", "s"),
        Metric("step_cpu_time", "whole step CPU time", "s"),
    )
}
ERROR_METRICS = ("mean_position", "mean_position_after_transient", "var_x", "var_y")
# "Best" ranks by the errors of the paper's Fig. 4 (mean position without the transient).
SCORE_METRICS = ("mean_position_after_transient", "var_x", "var_y")

# The paper's percent changes against m = 0 (Sec. 4 and Fig. 5; DESIGN.md).
PAPER_RESULTS: dict[str, dict[str, Any]] = {
    "paper_no_obstacles": {
        "m": 4,
        "label": "Sec. 4, no obstacles",
        "changes": {
            "mean_position": -5.3,
            "mean_position_after_transient": -21.0,
            "var_x": -78.5,
            "var_y": -68.4,
        },
    },
    "paper_obstacles": {
        "m": 3,
        "label": "Fig. 5, obstacles, random headings",
        "changes": {"mean_position": -53.6, "var_x": -71.7, "var_y": -46.0},
    },
}


# --- statistics --------------------------------------------------------------------------------


def _interval(values: np.ndarray) -> tuple[float, float]:
    """Half-width-based 95 % t-interval of the mean of ``values`` (nan with fewer than 2)."""
    n = values.shape[0]
    mean = float(values.mean())
    if n < 2:
        return math.nan, math.nan
    half = float(stats.t.ppf(0.975, n - 1) * values.std(ddof=1) / math.sqrt(n))
    return mean - half, mean + half


def _win_rate(values: np.ndarray, reference: np.ndarray, lower_is_better: bool) -> float:
    better = values < reference if lower_is_better else values > reference
    return float((np.count_nonzero(better) + 0.5 * np.count_nonzero(values == reference)) / values.shape[0])


def paired_statistics(
    values: np.ndarray, baseline: np.ndarray, best: np.ndarray | None, lower_is_better: bool = True
) -> dict[str, float]:
    """Statistics of one configuration's metric against the baseline, paired by seed.

    Args:
        values, baseline: the metric per seed (k,), same seeds in the same order.
        best: the best m's metric on the same seeds (k,), or None.

    Returns:
        ``n, mean, ci_low, ci_high, baseline_mean, change, change_low, change_high,
        median_change, win_vs_baseline, win_vs_best_m`` (changes in percent, win rates in
        [0, 1]); nan where undefined (non-finite values, a zero baseline, one seed).
    """
    values, baseline = np.asarray(values, dtype=float), np.asarray(baseline, dtype=float)
    nan = math.nan
    result = dict.fromkeys(
        (
            "mean",
            "ci_low",
            "ci_high",
            "baseline_mean",
            "change",
            "change_low",
            "change_high",
            "median_change",
            "win_vs_baseline",
            "win_vs_best_m",
        ),
        nan,
    )
    result["n"] = float(values.shape[0])
    if values.shape[0] == 0 or not (np.all(np.isfinite(values)) and np.all(np.isfinite(baseline))):
        return result
    result["mean"] = float(values.mean())
    result["ci_low"], result["ci_high"] = _interval(values)
    result["baseline_mean"] = reference = float(baseline.mean())
    result["win_vs_baseline"] = _win_rate(values, baseline, lower_is_better)
    if best is not None and np.all(np.isfinite(best)):
        result["win_vs_best_m"] = _win_rate(values, np.asarray(best, dtype=float), lower_is_better)
    if reference != 0:
        difference = values - baseline
        result["change"] = 100 * float(difference.mean()) / reference
        low, high = _interval(difference)
        result["change_low"], result["change_high"] = 100 * low / reference, 100 * high / reference
        nonzero = baseline != 0
        if np.any(nonzero):
            result["median_change"] = float(np.median(100 * difference[nonzero] / baseline[nonzero]))
    return result


class RunTable:
    """Runs indexed by (scenario, variant, config label) -> {seed: result}."""

    def __init__(self, runs: Iterable[Mapping[str, Any]]) -> None:
        self.index: dict[tuple[str, str, str], dict[int, Mapping[str, Any]]] = defaultdict(dict)
        for run in runs:
            self.index[(run["scenario"], run["variant"], run["config"])][int(run["seed"])] = run

    def has(self, scenario: str, variant: str, config: str) -> bool:
        """Whether any run of this cell exists."""
        return (scenario, variant, config) in self.index

    def seeds(self, scenario: str, variant: str, *configs: str) -> list[int]:
        """Seeds that every one of ``configs`` ran, sorted."""
        common = None
        for config in configs:
            seeds = set(self.index.get((scenario, variant, config), {}))
            common = seeds if common is None else common & seeds
        return sorted(common or ())

    def values(
        self, scenario: str, variant: str, config: str, metric: str, seeds: Sequence[int]
    ) -> np.ndarray:
        """The metric per seed (len(seeds),)."""
        cell = self.index[(scenario, variant, config)]
        return np.array([float(cell[s].get(metric, math.nan)) for s in seeds])


def score(table: RunTable, scenario: str, variant: str, config: str, baseline: str) -> float:
    """Average over ``SCORE_METRICS`` of mean(config) / mean(baseline) on their common seeds
    (lower is better; 1 = the baseline)."""
    seeds = table.seeds(scenario, variant, config, baseline)
    if not seeds:
        return math.inf
    ratios = []
    for metric in SCORE_METRICS:
        reference = table.values(scenario, variant, baseline, metric, seeds).mean()
        value = table.values(scenario, variant, config, metric, seeds).mean()
        ratios.append(value / reference if reference > 0 else 1.0)
    return float(np.mean(ratios))


def _best(
    table: RunTable, scenario: str, variant: str, configs: Sequence[AllocatorConfig], baseline: str
) -> AllocatorConfig | None:
    present = [c for c in configs if c.label != baseline and table.has(scenario, variant, c.label)]
    if not present:
        return None
    return min(present, key=lambda c: score(table, scenario, variant, c.label, baseline))


def roles(
    runs: Iterable[Mapping[str, Any]], study: Study, scenario: str, variant: str = "base"
) -> dict[str, AllocatorConfig | None]:
    """The configurations the report singles out for a scenario.

    Returns:
        ``{"paper_m": the paper's m if the study ran it, "best_m": the best m other than the
        baseline, "best_other": the best allocator other than the paper's iteration}``
        (None where absent).
    """
    table = runs if isinstance(runs, RunTable) else RunTable(runs)
    baseline = study.baseline.label
    paper_m = study.paper_iterations.get(scenario)
    iterative = [c for c in study.configs if c.iteration_count is not None]
    return {
        "paper_m": next((c for c in iterative if c.iteration_count == paper_m), None),
        "best_m": _best(table, scenario, variant, iterative, baseline),
        "best_other": _best(
            table, scenario, variant, [c for c in study.configs if c.iteration_count is None], baseline
        ),
    }


def summarize(result: StudyResult) -> list[dict[str, Any]]:
    """One row per scenario, variant, configuration and metric of ``METRICS`` (see the module
    docstring for the statistics)."""
    study = result.study
    table = RunTable(result.runs)
    baseline = study.baseline.label
    rows = []
    for scenario in study.scenarios:
        best_m = roles(table, study, scenario.name)["best_m"]
        for variant in _variants(study, scenario.name, table):
            for config in study.configs:
                if not table.has(scenario.name, variant, config.label):
                    continue
                references = [baseline] + (
                    [best_m.label] if best_m and table.has(scenario.name, variant, best_m.label) else []
                )
                seeds = table.seeds(scenario.name, variant, config.label, *references)
                for key, metric in METRICS.items():
                    values = table.values(scenario.name, variant, config.label, key, seeds)
                    base = table.values(scenario.name, variant, baseline, key, seeds)
                    best = (
                        table.values(scenario.name, variant, best_m.label, key, seeds)
                        if len(references) > 1
                        else None
                    )
                    rows.append(
                        {
                            "scenario": scenario.name,
                            "variant": variant,
                            "config": config.label,
                            "allocator": config.name,
                            "metric": key,
                            "unit": metric.unit,
                            **paired_statistics(values, base, best, metric.lower_is_better),
                        }
                    )
    return rows


def _variants(study: Study, scenario: str, table: RunTable) -> list[str]:
    names = ["base"] + [v.name for v in study.variants]
    return [v for v in names if table.has(scenario, v, study.baseline.label)]


def verdict(ours: float, low: float, high: float, paper: float) -> str:
    """Whether our percent change matches the paper's in direction and order of size.

    Direction: "yes" when the 95 % interval lies on the paper's side of 0, "no" when on the
    other side, "unclear" when it contains 0. Size: "same order" within a factor of 3 of
    the paper's change, else "smaller" / "larger" (with the ratio).
    """
    if not math.isfinite(ours):
        return "n/a"
    sign = math.copysign(1.0, paper)
    if sign * low > 0 and sign * high > 0:
        direction = "yes"
    elif sign * low < 0 and sign * high < 0:
        direction = "no"
    else:
        direction = "unclear"
    ratio = ours / paper
    if ratio <= 0:
        size = "opposite sign"
    else:
        size = "same order" if 1 / 3 <= ratio <= 3 else ("smaller" if ratio < 1 / 3 else "larger")
    return f"direction {direction}; {size} (x{ratio:.2f})"


def paper_sized(ours: float, low: float, high: float, paper: float) -> bool:
    """A reduction of the paper's size: significant, same direction, within a factor of 3."""
    return verdict(ours, low, high, paper).startswith("direction yes; same order")


# --- figures ------------------------------------------------------------------------------------


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_sweep(table: RunTable, study: Study, scenario: str, path: str | Path) -> Path:
    """Fig. 4 analog: integrated errors against m (mean over seeds, 95 % intervals), every
    other allocator as a horizontal band (mean line, interval shaded); one panel per error."""
    plt = _plt()
    iterative = [
        c for c in study.configs if c.iteration_count is not None and table.has(scenario, "base", c.label)
    ]
    others = [c for c in study.configs if c.iteration_count is None and table.has(scenario, "base", c.label)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharex=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"][1:]
    for ax, key in zip(axes.ravel(), ERROR_METRICS):
        metric = METRICS[key]
        ms, means, halves = [], [], []
        for config in iterative:
            values = table.values(
                scenario, "base", config.label, key, table.seeds(scenario, "base", config.label)
            )
            low, high = _interval(values)
            ms.append(config.iteration_count)
            means.append(values.mean())
            halves.append((high - low) / 2 if math.isfinite(low) else 0.0)
        ax.errorbar(ms, means, yerr=halves, marker="o", color="black", capsize=3, label="iterative, m")
        # Line styles too: allocators solving the same problem (qp and dual) coincide.
        styles = ("-", "--", ":", "-.")
        for k, (color, config) in enumerate(zip(colors * 3, others)):
            values = table.values(
                scenario, "base", config.label, key, table.seeds(scenario, "base", config.label)
            )
            low, high = _interval(values)
            ax.axhline(values.mean(), color=color, lw=1.8, ls=styles[k % len(styles)], label=config.label)
            if math.isfinite(low):
                ax.axhspan(low, high, color=color, alpha=0.15, lw=0)
        ax.set_title(metric.title)
        ax.set_ylabel(f"integrated |error| ({metric.unit.replace('^2', '$^2$')})")
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("iterations m of the paper's projection")
        if ms:
            ax.set_xticks(ms)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=9)
    fig.suptitle(f"{scenario}: integrated errors over {len(study.seeds)} seeds (mean, 95 % interval)")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_ablation(
    summary: Mapping[tuple[str, str, str, str], Mapping[str, Any]], study: Study, path: str | Path
) -> Path:
    """Percent change against m = 0 at the paper's m under each ablation variant (bars with
    95 % intervals), the paper's numbers as black diamonds; one panel per paper scenario."""
    plt = _plt()
    scenarios = [s.name for s in study.scenarios if s.name in PAPER_RESULTS]
    fig, axes = plt.subplots(1, len(scenarios), figsize=(6.5 * len(scenarios), 4.8), squeeze=False)
    variants = ["base"] + [v.name for v in study.variants]
    for ax, scenario in zip(axes[0], scenarios):
        paper = PAPER_RESULTS[scenario]
        label = f"m={paper['m']}"
        keys = list(paper["changes"])
        shown = [v for v in variants if (scenario, v, label, keys[0]) in summary]
        width = 0.8 / max(len(shown), 1)
        for j, variant in enumerate(shown):
            rows = [summary[(scenario, variant, label, k)] for k in keys]
            x = np.arange(len(keys)) + (j - (len(shown) - 1) / 2) * width
            change = np.array([r["change"] for r in rows])
            error = np.array(
                [[r["change"] - r["change_low"], r["change_high"] - r["change"]] for r in rows]
            ).T
            ax.bar(x, change, width, yerr=np.nan_to_num(error), capsize=2, label=variant)
        ax.plot(np.arange(len(keys)), [paper["changes"][k] for k in keys], "D", color="black", label="paper")
        ax.axhline(0, color="0.3", lw=0.8)
        # A few wide intervals would flatten the rest: clip the axis (the tables have the numbers).
        bottom, top = ax.get_ylim()
        ax.set_ylim(max(bottom, -150.0), min(top, 300.0))
        ax.set_xticks(
            np.arange(len(keys)), [METRICS[k].title.replace(" after transient", "\nafter 4 s") for k in keys]
        )
        ax.set_ylabel(f"change of integrated error at {label} vs m=0 (%, axis clipped)")
        ax.set_title(f"{scenario} ({paper['label']})")
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_runs(
    panels: Sequence[tuple[str, Trajectory]], scenario: str, transient: float, folder: Path
) -> list[Path]:
    """Fig. 2/5 analog (trajectories side by side, one per (title, trajectory) panel) and
    Fig. 3 analog (task errors over time after the common transient); returns the PNG paths."""
    from platoon_opt.study.figures import draw_trajectory, plot_errors

    plt = _plt()
    trajectories = [trajectory for _, trajectory in panels]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.6 * len(panels), 5.4), squeeze=False)
    for ax, (title, trajectory) in zip(axes[0], panels):
        draw_trajectory(ax, trajectory)
        ax.set_title(f"{title}\n{trajectory.allocator}", fontsize=10)
    fig.suptitle(
        f"{scenario}, seed {trajectories[0].seed}: units (triangles, apex = heading), "
        "target (diamonds), obstacles (circles)"
    )
    fig.tight_layout()
    trajectory_path = folder / f"trajectories_{scenario}.png"
    fig.savefig(trajectory_path, dpi=110)
    plt.close(fig)
    errors_path = plot_errors(trajectories, folder / f"errors_{scenario}.png", start=transient)
    return [trajectory_path, errors_path]


# --- report --------------------------------------------------------------------------------------


def _num(value: float, digits: int = 4) -> str:
    return f"{value:.{digits}g}" if math.isfinite(value) else "—"


def _mean(row: Mapping[str, Any]) -> str:
    if not math.isfinite(row["mean"]):
        return "—"
    if not math.isfinite(row["ci_low"]):
        return _num(row["mean"])
    return f"{_num(row['mean'])} ± {_num((row['ci_high'] - row['ci_low']) / 2, 2)}"


def _change(row: Mapping[str, Any] | None) -> str:
    if row is None or not math.isfinite(row["change"]):
        return "—"
    if not math.isfinite(row["change_low"]):
        return f"{row['change']:+.1f} %"
    return f"{row['change']:+.1f} % [{row['change_low']:+.1f}, {row['change_high']:+.1f}]"


def _percent(value: float) -> str:
    return f"{100 * value:.0f} %" if math.isfinite(value) else "—"


def _table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


class _Report:
    """Builds report.md from a study's summary rows."""

    def __init__(self, result: StudyResult, summary: list[dict[str, Any]], command: str) -> None:
        self.result, self.study, self.command = result, result.study, command
        self.table = RunTable(result.runs)
        self.rows = {(r["scenario"], r["variant"], r["config"], r["metric"]): r for r in summary}
        self.roles = {s.name: roles(self.table, self.study, s.name) for s in self.study.scenarios}
        self.baseline = self.study.baseline.label

    def row(
        self, scenario: str, config: str | None, metric: str, variant: str = "base"
    ) -> dict[str, Any] | None:
        return self.rows.get((scenario, variant, config, metric)) if config else None

    def render(self, figures: Mapping[str, Sequence[Path]], ablation_figure: Path | None) -> str:
        study = self.study
        parts = [
            "# Integrated errors: the paper's iteration against the optimization allocators\n",
            f"Command: `{self.command}`. Seeds {_seeds(study.seeds)} per configuration"
            + (f", ablation on seeds {_seeds(study.ablation_seeds)}" if study.variants else "")
            + f"; {len(self.result.runs)} runs ({self.result.computed} computed now, the rest reused from "
            f"`runs/`) in {duration_text(self.result.wall_time)}. Baseline: `{self.baseline}`.\n",
            "Every configuration of a seed starts from the same initial state (ring phase, headings, "
            "obstacle jitter drawn from the seed) and chases the same target. Percent changes are "
            f"against `{self.baseline}` on the same seeds, with 95 % intervals (paired t-interval of "
            'the per-seed differences, divided by the baseline mean); negative is better. "Best" '
            "(best m, best other allocator) has the lowest average, over mean position after the "
            "transient, var_x and var_y, of its mean error divided by the baseline's.\n",
            f"Compute: {_cpu_minutes(self.result.runs):.1f} CPU-minutes in the runs themselves, "
            f"{os.cpu_count()} CPUs on this machine.\n",
        ]
        if any(s.name in PAPER_RESULTS for s in study.scenarios):
            parts.append(self.paper_section())
        parts.append(self.sweep_section(figures))
        parts.append(self.timing_section())
        if study.variants:
            parts.append(self.ablation_section(ablation_figure))
        parts.append(self.scenario_section())
        parts.append(
            "## Files\n\n`results.csv`: one row per run (every metric). `summary.csv`: one row per "
            "scenario, variant, configuration and metric (mean, interval, change, median change, win "
            "rates). `results.json`: the study, the runs and the summary. `runs/`: one file per run; "
            "rerunning the command reuses them (delete the folder, or pass `--fresh`, to start over).\n"
        )
        return "\n".join(parts)

    def paper_section(self) -> str:
        out = ["## The paper's table beside ours\n"]
        for scenario in self.study.scenarios:
            if scenario.name not in PAPER_RESULTS:
                continue
            paper = PAPER_RESULTS[scenario.name]
            role = self.roles[scenario.name]
            keys = ERROR_METRICS
            header = ["", *(METRICS[k].title for k in keys), "gear flips"]
            rows = [
                [
                    f"**paper**, m = {paper['m']}",
                    *(f"{paper['changes'][k]:+.1f} %" if k in paper["changes"] else "—" for k in keys),
                    "—",
                ]
            ]
            shown = []
            if role["paper_m"] is not None:
                shown.append((f"ours, m = {paper['m']} (paper's m)", role["paper_m"].label))
            if role["best_m"] is not None:
                shown.append((f"ours, best m = {role['best_m'].iteration_count}", role["best_m"].label))
            shown += [
                (f"ours, `{c.label}`", c.label) for c in self.study.configs if c.iteration_count is None
            ]
            for title, label in shown:
                flips = self.row(scenario.name, label, "gear_flips")
                rows.append(
                    [
                        title,
                        *(_change(self.row(scenario.name, label, k)) for k in keys),
                        _mean(flips) if flips else "—",
                    ]
                )
            base_flips = self.row(scenario.name, self.baseline, "gear_flips")
            out.append(f"### {scenario.name}: {paper['label']}\n")
            out.append(
                f"Percent change of the integrated absolute error against `{self.baseline}` "
                f"(`{self.baseline}` itself: {self._absolute(scenario.name)}; "
                f"gear flips {_mean(base_flips) if base_flips else '—'}).\n"
            )
            out.append(_table(header, rows))
            if role["paper_m"] is not None:
                verdicts = []
                for key, value in paper["changes"].items():
                    row = self.row(scenario.name, role["paper_m"].label, key)
                    best = self.row(scenario.name, role["best_m"].label if role["best_m"] else None, key)
                    verdicts.append(
                        [
                            METRICS[key].title,
                            f"{value:+.1f} %",
                            _change(row),
                            verdict(row["change"], row["change_low"], row["change_high"], value)
                            if row
                            else "—",
                            verdict(best["change"], best["change_low"], best["change_high"], value)
                            if best
                            else "—",
                        ]
                    )
                out.append(
                    _table(
                        [
                            "paper's number",
                            "paper",
                            f"ours at m = {paper['m']}",
                            "match at the paper's m",
                            "match at our best m",
                        ],
                        verdicts,
                    )
                )
        out.append(
            'Direction: "yes" when the 95 % interval excludes 0 on the paper\'s side, "unclear" when it '
            'contains 0. Size: "same order" within a factor of 3 of the paper\'s change.\n'
        )
        return "\n".join(out)

    def _absolute(self, scenario: str) -> str:
        parts = []
        for key in ERROR_METRICS:
            row = self.row(scenario, self.baseline, key)
            if row:
                parts.append(f"{METRICS[key].title} {_mean(row)} {METRICS[key].unit}")
        return "; ".join(parts)

    def sweep_section(self, figures: Mapping[str, Sequence[Path]]) -> str:
        out = [
            "## Sweep over m (Fig. 4 data), the other allocators as extra rows\n",
            "Mean over seeds ± half-width of the 95 % interval; integrated absolute errors in m s "
            "(mean position) and m^2 s (variances).\n",
        ]
        for scenario in self.study.scenarios:
            name = scenario.name
            configs = [c.label for c in self.study.configs if self.table.has(name, "base", c.label)]
            best = self.roles[name]["best_m"]
            out.append(f"### {name}\n")
            out.append(
                _table(
                    [
                        "config",
                        *(METRICS[k].title for k in ERROR_METRICS),
                        "gear flips",
                        "time inside obstacles (unit s)",
                        "min clearance (m)",
                    ],
                    [
                        [f"`{c}`", *(_mean(self.row(name, c, k)) for k in ERROR_METRICS)]
                        + [
                            _mean(self.row(name, c, k))
                            for k in ("gear_flips", "time_inside_obstacles", "min_clearance")
                        ]
                        for c in configs
                    ],
                )
            )
            out.append(f"Percent change against `{self.baseline}` [95 % interval]:\n")
            out.append(
                _table(
                    ["config", *(METRICS[k].title for k in ERROR_METRICS)],
                    [[f"`{c}`", *(_change(self.row(name, c, k)) for k in ERROR_METRICS)] for c in configs],
                )
            )
            out.append(
                f"Median per-seed change; win rate against `{self.baseline}`; win rate against the best m "
                f"(`{best.label if best else '—'}`):\n"
            )
            out.append(
                _table(
                    ["config", *(METRICS[k].title for k in ERROR_METRICS)],
                    [[f"`{c}`", *(self._wins(self.row(name, c, k)) for k in ERROR_METRICS)] for c in configs],
                )
            )
            for path in figures.get(name, ()):
                out.append(f"![{path.stem}](figures/{path.name})\n")
        return "\n".join(out)

    @staticmethod
    def _wins(row: Mapping[str, Any] | None) -> str:
        if row is None:
            return "—"
        median = f"{row['median_change']:+.1f} %" if math.isfinite(row["median_change"]) else "—"
        return f"{median}; {_percent(row['win_vs_baseline'])}; {_percent(row['win_vs_best_m'])}"

    def timing_section(self) -> str:
        out = [
            "## Compute time per step\n",
            "Allocator: the allocation alone (wall time; mean over seeds of each run's median and 95th "
            "percentile). Whole step: the allocation plus the problem set-up, the unit controllers, the "
            "kinematics and the logging, per step (CPU time of the worker, and wall time, which grows when "
            "the machine runs other work). Fallback: steps per run where the allocator failed and the "
            "controller projected the nominal velocity instead.\n",
        ]
        keys = ("solve_time_median", "solve_time_p95", "step_cpu_time", "step_time")
        for scenario in self.study.scenarios:
            rows = []
            for config in self.study.configs:
                cells = [self.row(scenario.name, config.label, k) for k in keys]
                fallback = self.row(scenario.name, config.label, "fallback_steps")
                if fallback is None:
                    continue
                rows.append(
                    [f"`{config.label}`"]
                    + [f"{1e3 * c['mean']:.3g}" if c and math.isfinite(c["mean"]) else "—" for c in cells]
                    + [_num(fallback["mean"], 3)]
                )
            out.append(f"### {scenario.name}\n")
            header = ["config", "allocator median (ms)", "allocator p95 (ms)", "whole step CPU (ms)"]
            out.append(_table([*header, "whole step wall (ms)", "fallback steps per run"], rows))
        return "\n".join(out)

    def ablation_section(self, figure: Path | None) -> str:
        study = self.study
        out = [
            "## Ablation: modelling choices the paper leaves open\n",
            "Variants (each applied to the scenario file): "
            + "; ".join(f"`{v.name}`: {v.title}" for v in study.variants)
            + f'. Seeds {_seeds(study.ablation_seeds)}. The Eq. 6 "ahead" test does nothing without '
            "obstacles, so travel-only variants are skipped there.\n",
        ]
        verdicts = []
        for scenario in study.scenarios:
            name = scenario.name
            variants = _variants(study, name, self.table)
            out.append(f"### {name}\n")
            out.append(f"The baseline `{self.baseline}` under each variant (mean over seeds ± half-width):\n")
            out.append(
                _table(
                    [
                        "variant",
                        *(METRICS[k].title for k in ERROR_METRICS),
                        "gear flips",
                        "time inside obstacles (unit s)",
                    ],
                    [
                        [
                            f"`{v}`",
                            *(
                                _mean(self.row(name, self.baseline, k, v))
                                for k in (*ERROR_METRICS, "gear_flips", "time_inside_obstacles")
                            ),
                        ]
                        for v in variants
                    ],
                )
            )
            paper = PAPER_RESULTS.get(name)
            configs = [c for c in self.result.ablation_configs.get(name, []) if c.label != self.baseline]
            rows = []
            for config in configs:
                for v in variants:
                    cells = [_change(self.row(name, config.label, k, v)) for k in ERROR_METRICS]
                    flips = self.row(name, config.label, "gear_flips", v)
                    sized = "—"
                    if paper is not None:
                        count = 0
                        for key, value in paper["changes"].items():
                            row = self.row(name, config.label, key, v)
                            count += bool(row) and paper_sized(
                                row["change"], row["change_low"], row["change_high"], value
                            )
                        sized = f"{count} of {len(paper['changes'])}"
                        if config.iteration_count == paper["m"]:
                            verdicts.append((name, v, count, len(paper["changes"])))
                    rows.append(
                        [f"`{config.label}`", f"`{v}`", *cells, _mean(flips) if flips else "—", sized]
                    )
            out.append(f"Percent change against `{self.baseline}` of the same variant [95 % interval]:\n")
            out.append(
                _table(
                    [
                        "config",
                        "variant",
                        *(METRICS[k].title for k in ERROR_METRICS),
                        "gear flips",
                        "paper-sized numbers",
                    ],
                    rows,
                )
            )
        if verdicts:
            out.append(
                '"Paper-sized numbers": how many of the paper\'s percent changes for the scenario are '
                "matched in direction (interval excludes 0) and within a factor of 3.\n"
            )
            best = max(verdicts, key=lambda v: v[2] / v[3])
            sized = [f"`{v}` on {s} ({c} of {k})" for s, v, c, k in verdicts if c == k]
            out.append(
                "At the paper's m, "
                + (
                    "every paper number of a scenario is matched in size under: " + ", ".join(sized) + "."
                    if sized
                    else f"no variant matches all of a scenario's paper numbers in size; the closest is "
                    f"`{best[1]}` on {best[0]} ({best[2]} of {best[3]})."
                )
                + "\n"
            )
        if figure is not None:
            out.append(f"![ablation](figures/{figure.name})\n")
        return "\n".join(out)

    def scenario_section(self) -> str:
        from platoon_opt.study.harness import scenario_definition

        out = ["## Scenarios (everything needed to re-run the numbers)\n"]
        for scenario in self.study.scenarios:
            d = scenario_definition(scenario)
            duration = self.study.duration or d["duration"]
            obstacles = (
                ", ".join(
                    f"({o['center'][0]:g}, {o['center'][1]:g}) r {o['radius']:g}" for o in d["obstacles"]
                )
                or "none"
            )
            varies = d["seed_varies"]
            rows = [
                ["file", f"`{d['source']}`"],
                [
                    "units",
                    f"{d['n']}, start around ({d['center'][0]:g}, {d['center'][1]:g}) m on a ring with "
                    f"variances {d['variance'][0]:g}, {d['variance'][1]:g} m^2 (also the goal)",
                ],
                ["time", f"dt {d['dt']:g} s, {duration:g} s simulated, transient {d['transient']:g} s"],
                [
                    "target",
                    f"{d['target']['speed']:g} m/s through "
                    + " → ".join(f"({x:g}, {y:g})" for x, y in d["target"]["waypoints"]),
                ],
                [
                    "gains",
                    f"K = diag({', '.join(f'{g:g}' for g in d['task']['gains'])}), "
                    f"K_alpha {d['vehicle']['steering_gain']:g} 1/s",
                ],
                [
                    "avoidance",
                    f"d_minr {d['avoidance']['d_minr']:g} m, d_mino {d['avoidance']['d_mino']:g} m, "
                    f'"ahead" on the {d["avoidance"]["ahead_reference"]}',
                ],
                [
                    "vehicle",
                    f"r {d['vehicle']['wheel_radius']:g} m, d {d['vehicle']['length']:g} m, "
                    f"max speed {d['vehicle']['max_speed']:g} m/s, "
                    f"max steering {d['vehicle']['max_steering_deg']:g} deg, "
                    f"max steering rate {d['vehicle']['max_steering_rate']:g} rad/s, gear hysteresis "
                    f"{d['vehicle']['gear_hysteresis_deg']:g} deg",
                ],
                [
                    "obstacles",
                    obstacles
                    + (
                        f" (centres jittered by N(0, {varies['obstacle_jitter']:g} m) per seed)"
                        if varies["obstacle_jitter"]
                        else ""
                    ),
                ],
                [
                    "a seed varies",
                    ", ".join(
                        k
                        for k, on in (
                            ("ring phase", varies["ring_phase"]),
                            ("headings", varies["headings"]),
                            ("obstacle centres", bool(varies["obstacle_jitter"])),
                        )
                        if on
                    )
                    or "nothing",
                ],
                ["seeds", _seeds(self.study.seeds)],
            ]
            out.append(f"### {scenario.name}\n")
            out.append(_table(["", ""], rows))
        return "\n".join(out)


def duration_text(seconds: float) -> str:
    """ "42 s" or "3.5 min"."""
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def _cpu_minutes(runs: Iterable[Mapping[str, Any]]) -> float:
    return sum(float(r.get("cpu_time", math.nan)) for r in runs) / 60


def _seeds(seeds: Sequence[int]) -> str:
    seeds = list(seeds)
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))) and len(seeds) > 2:
        return f"{seeds[0]}..{seeds[-1]}"
    return ", ".join(map(str, seeds))


def write_report(result: StudyResult, out: str | Path, *, command: str = "") -> Path:
    """Write ``results.csv`` (per run), ``summary.csv``, ``results.json``, the figures
    (``figures/*.png``) and ``report.md`` into ``out``; return the report's path."""
    from platoon_opt.study.harness import scenario_definition

    out = Path(out)
    folder = out / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    study = result.study
    summary = summarize(result)
    table = RunTable(result.runs)
    keyed = {(r["scenario"], r["variant"], r["config"], r["metric"]): r for r in summary}

    figures: dict[str, list[Path]] = {}
    for scenario in study.scenarios:
        paths = [plot_sweep(table, study, scenario.name, folder / f"sweep_{scenario.name}.png")]
        panels = result.figures.get(scenario.name, [])
        if panels:
            paths = plot_runs(panels, scenario.name, scenario.transient, folder) + paths
        figures[scenario.name] = paths
    ablation_figure = None
    if study.variants and any(s.name in PAPER_RESULTS for s in study.scenarios):
        ablation_figure = plot_ablation(keyed, study, folder / "ablation.png")

    run_keys = [k for k in result.runs[0] if k != "options"] + ["options"] if result.runs else []
    write_csv(
        out / "results.csv",
        run_keys,
        [[_cell(run.get(k)) for k in run_keys] for run in result.runs],
    )
    summary_keys = list(summary[0]) if summary else []
    write_csv(out / "summary.csv", summary_keys, [[_cell(r[k]) for k in summary_keys] for r in summary])
    write_json(
        out / "results.json",
        {
            "command": command,
            "seeds": list(study.seeds),
            "ablation_seeds": list(study.ablation_seeds),
            "duration": study.duration,
            "baseline": study.baseline.as_dict(),
            "configs": [c.as_dict() for c in study.configs],
            "scenarios": [scenario_definition(s) for s in study.scenarios],
            "variants": [vars(v) for v in study.variants],
            "roles": {
                name: {k: c.label if c else None for k, c in roles(table, study, name).items()}
                for name in (s.name for s in study.scenarios)
            },
            "paper": PAPER_RESULTS,
            "wall_time": result.wall_time,
            "runs": result.runs,
            "summary": summary,
        },
    )
    text = _Report(result, summary, command).render(figures, ablation_figure)
    return write_atomic(out / "report.md", text)


def _cell(value: Any) -> Any:
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    if isinstance(value, dict):
        import json

        return json.dumps(value, sort_keys=True)
    return value


def paper_tables(result: StudyResult) -> str:
    """The report's "paper's table beside ours" section (markdown), empty without paper
    scenarios; the CLI prints it."""
    if not any(s.name in PAPER_RESULTS for s in result.study.scenarios):
        return ""
    return _Report(result, summarize(result), "").paper_section()
