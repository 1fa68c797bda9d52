"""Statistics of a study's runs, per scenario, ablation variant, configuration and metric, over
the seeds that the configuration shares with the baseline:

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
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from scipy import stats

from platoon_opt.study.config import AllocatorConfig


class Comparison(Protocol):
    """What the statistics read of a study (``platoon_opt.study.harness.Study``)."""

    @property
    def baseline(self) -> AllocatorConfig: ...

    @property
    def configs(self) -> Sequence[AllocatorConfig]: ...

    @property
    def scenarios(self) -> Sequence[Any]: ...

    @property
    def variants(self) -> Sequence[Any]: ...

    @property
    def seeds(self) -> Sequence[int]: ...

    @property
    def paper_iterations(self) -> Mapping[str, int]: ...


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
        Metric("program_changes", "steps answered by another program", "count"),
        Metric("solve_time_median", "allocator time per step median", "s"),
        Metric("solve_time_p95", "allocator time per step p95", "s"),
        Metric("solve_steps", "steps that solved", "count"),
        Metric("solve_time_per_solve_median", "allocator time per solve median", "s"),
        Metric("solve_time_per_solve_p95", "allocator time per solve p95", "s"),
        Metric("step_time", "whole step time", "s"),
        Metric("step_cpu_time", "whole step CPU time", "s"),
    )
}


# "Best" ranks by the errors of the paper's Fig. 4 (mean position without the transient).
SCORE_METRICS = ("mean_position_after_transient", "var_x", "var_y")


def interval(values: np.ndarray) -> tuple[float, float]:
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
    result["ci_low"], result["ci_high"] = interval(values)
    result["baseline_mean"] = reference = float(baseline.mean())
    result["win_vs_baseline"] = _win_rate(values, baseline, lower_is_better)
    if best is not None and np.all(np.isfinite(best)):
        result["win_vs_best_m"] = _win_rate(values, np.asarray(best, dtype=float), lower_is_better)
    if reference != 0:
        difference = values - baseline
        result["change"] = 100 * float(difference.mean()) / reference
        low, high = interval(difference)
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
    runs: Iterable[Mapping[str, Any]] | RunTable, study: Comparison, scenario: str, variant: str = "base"
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


def summarize(study: Comparison, runs: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per scenario, variant, configuration and metric of ``METRICS`` (see the module
    docstring for the statistics)."""
    table = RunTable(runs)
    baseline = study.baseline.label
    rows = []
    for scenario in study.scenarios:
        best_m = roles(table, study, scenario.name)["best_m"]
        for variant in study_variants(study, scenario.name, table):
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
                        table.values(scenario.name, variant, references[1], key, seeds)
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


def study_variants(study: Comparison, scenario: str, table: RunTable) -> list[str]:
    """ "base" and the ablation variants that the baseline ran on ``scenario``."""
    names = ["base"] + [v.name for v in study.variants]
    return [v for v in names if table.has(scenario, v, study.baseline.label)]
