"""The report of a study: ``report.md`` (the paper's table beside ours, the sweep over m, compute
times, the ablation, the scenarios), ``results.csv``, ``summary.csv``, ``results.json`` and the
figures, written into the study's output folder.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from platoon_opt.metrics import ERROR_METRICS
from platoon_opt.study.best_m import best_m_section
from platoon_opt.study.config import AllocatorConfig
from platoon_opt.study.crosscheck import cross_check_section
from platoon_opt.study.fallbacks import report_note
from platoon_opt.study.figures import plot_ablation, plot_runs, plot_sweep
from platoon_opt.study.harness import StudyResult
from platoon_opt.study.markdown import (
    change_text,
    cpu_minutes,
    duration_text,
    mean_text,
    percent,
    seeds_text,
    table,
)
from platoon_opt.study.output import write_atomic, write_csv, write_json
from platoon_opt.study.paper import PAPER_RESULTS, paper_sized, verdict
from platoon_opt.study.runs import scenario_definition
from platoon_opt.study.scenario_section import scenario_section
from platoon_opt.study.statistics import METRICS, RunTable, roles, study_variants, summarize
from platoon_opt.study.timing_report import timing_section
from platoon_opt.study.winners import winners_section


class _Report:
    """Builds report.md from a study's summary rows."""

    def __init__(self, result: StudyResult, summary: list[dict[str, Any]], command: str, out: Path) -> None:
        self.result, self.study, self.command, self.out = result, result.study, command, out
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
            f"Command: `{self.command}`. Seeds {seeds_text(study.seeds)} per configuration"
            + (f", ablation on seeds {seeds_text(study.ablation_seeds)}" if study.variants else "")
            + f"; {len(self.result.runs)} runs ({self.result.computed} computed now, the rest reused from "
            f"`runs/`) in {duration_text(self.result.wall_time)}. Baseline: `{self.baseline}`.\n",
            "Every configuration of a seed starts from the same initial state (ring phase, headings, "
            "obstacle jitter drawn from the seed) and chases the same target. Percent changes are "
            f"against `{self.baseline}` on the same seeds, with 95 % intervals (paired t-interval of "
            'the per-seed differences, divided by the baseline mean); negative is better. "Best" '
            "(best m, best other allocator) has the lowest average, over mean position after the "
            "transient, var_x and var_y, of its mean error divided by the baseline's.\n",
            f"Compute: {cpu_minutes(self.result.runs):.1f} CPU-minutes in the runs themselves, "
            f"{os.cpu_count()} CPUs on this machine.\n",
        ]
        note = report_note(self.result.runs)
        if note:
            parts.append(note)
        # The paper's changes are against m = 0: beside changes against another baseline they mislead.
        if study.baseline.iteration_count == 0 and any(s.name in PAPER_RESULTS for s in study.scenarios):
            parts.append(self.paper_section())
        parts.append(self.sweep_section(figures))
        parts += [s for s in (winners_section(study, self.table), best_m_section(study, self.table)) if s]
        if self.result.checks:
            parts.append(cross_check_section(self.result.checks))
        parts.append(timing_section(self.study, self.result.runs, self.row))
        if study.variants:
            parts.append(self.ablation_section(ablation_figure))
        parts.append(scenario_section(self.study.scenarios, self.study.duration, self.study.seeds, self.out))
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
                        *(change_text(self.row(scenario.name, label, k)) for k in keys),
                        mean_text(flips) if flips else "—",
                    ]
                )
            base_flips = self.row(scenario.name, self.baseline, "gear_flips")
            out.append(f"### {scenario.name}: {paper['label']}\n")
            out.append(
                f"Percent change of the integrated absolute error against `{self.baseline}` "
                f"(`{self.baseline}` itself: {self._absolute(scenario.name)}; "
                f"gear flips {mean_text(base_flips) if base_flips else '—'}).\n"
            )
            out.append(table(header, rows))
            if role["paper_m"] is not None:
                verdicts = []
                for key, value in paper["changes"].items():
                    row = self.row(scenario.name, role["paper_m"].label, key)
                    best = self.row(scenario.name, role["best_m"].label if role["best_m"] else None, key)
                    verdicts.append(
                        [
                            METRICS[key].title,
                            f"{value:+.1f} %",
                            change_text(row),
                            verdict(row["change"], row["change_low"], row["change_high"], value)
                            if row
                            else "—",
                            verdict(best["change"], best["change_low"], best["change_high"], value)
                            if best
                            else "—",
                        ]
                    )
                out.append(
                    table(
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
                parts.append(f"{METRICS[key].title} {mean_text(row)} {METRICS[key].unit}")
        return "; ".join(parts)

    def sweep_section(self, figures: Mapping[str, Sequence[Path]]) -> str:
        out = [
            "## Sweep over m (Fig. 4 data), the other allocators as extra rows\n",
            "Mean over seeds ± half-width of the 95 % interval; integrated absolute errors in m s "
            "(mean position) and m^2 s (variances). Path: which loop ran the configuration's runs, "
            "the compiled engine (the allocator's step compiled with the model, a batch of seeds in "
            "one call) or the host loop (the allocator called once per step, e.g. Clarabel).\n",
        ]
        for scenario in self.study.scenarios:
            name = scenario.name
            configs = [c.label for c in self.study.configs if self.table.has(name, "base", c.label)]
            best = self.roles[name]["best_m"]
            out.append(f"### {name}\n")
            out.append(
                table(
                    [
                        "config",
                        "path",
                        *(METRICS[k].title for k in ERROR_METRICS),
                        "gear flips",
                        "time inside obstacles (unit s)",
                        "min clearance (m)",
                    ],
                    [
                        [
                            f"`{c}`",
                            self._path(name, c),
                            *(mean_text(self.row(name, c, k)) for k in ERROR_METRICS),
                        ]
                        + [
                            mean_text(self.row(name, c, k))
                            for k in ("gear_flips", "time_inside_obstacles", "min_clearance")
                        ]
                        for c in configs
                    ],
                )
            )
            out.append(f"Percent change against `{self.baseline}` [95 % interval]:\n")
            out.append(
                table(
                    ["config", *(METRICS[k].title for k in ERROR_METRICS)],
                    [
                        [f"`{c}`", *(change_text(self.row(name, c, k)) for k in ERROR_METRICS)]
                        for c in configs
                    ],
                )
            )
            out.append(
                f"Median per-seed change; win rate against `{self.baseline}`; win rate against the best m "
                f"(`{best.label if best else '—'}`):\n"
            )
            out.append(
                table(
                    ["config", *(METRICS[k].title for k in ERROR_METRICS)],
                    [
                        [f"`{c}`", *(self._wins(self.row(name, c, k), c, best) for k in ERROR_METRICS)]
                        for c in configs
                    ],
                )
            )
            for path in figures.get(name, ()):
                out.append(f"![{path.stem}](figures/{path.name})\n")
        return "\n".join(out)

    def _path(self, scenario: str, config: str) -> str:
        """Which loop ran the configuration's runs on the scenario: "compiled", "host" or both."""
        paths = {
            run.get("path", "host")
            for run in self.result.runs
            if (run["scenario"], run["variant"], run["config"]) == (scenario, "base", config)
        }
        return " and ".join(sorted(paths))

    def _wins(self, row: Mapping[str, Any] | None, config: str, best: AllocatorConfig | None) -> str:
        """Median change; win rates against the baseline and the best m ("—" against itself)."""
        if row is None:
            return "—"
        median = f"{row['median_change']:+.1f} %" if math.isfinite(row["median_change"]) else "—"
        against_baseline = "—" if config == self.baseline else percent(row["win_vs_baseline"])
        against_best = "—" if best is None or config == best.label else percent(row["win_vs_best_m"])
        return f"{median}; {against_baseline}; {against_best}"

    def ablation_section(self, figure: Path | None) -> str:
        study = self.study
        out = [
            "## Ablation: modelling choices the paper leaves open\n",
            "Variants (each applied to the scenario file): "
            + "; ".join(f"`{v.name}`: {v.title}" for v in study.variants)
            + f'. Seeds {seeds_text(study.ablation_seeds)}. The Eq. 6 "ahead" test does nothing without '
            "obstacles, so travel-only variants are skipped there.\n",
        ]
        verdicts = []
        for scenario in study.scenarios:
            name = scenario.name
            variants = study_variants(study, name, self.table)
            out.append(f"### {name}\n")
            out.append(f"The baseline `{self.baseline}` under each variant (mean over seeds ± half-width):\n")
            out.append(
                table(
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
                                mean_text(self.row(name, self.baseline, k, v))
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
                    cells = [change_text(self.row(name, config.label, k, v)) for k in ERROR_METRICS]
                    flips = self.row(name, config.label, "gear_flips", v)
                    sized = "—"
                    if paper is not None:
                        count = 0
                        for key, value in paper["changes"].items():
                            row = self.row(name, config.label, key, v)
                            count += row is not None and paper_sized(
                                row["change"], row["change_low"], row["change_high"], value
                            )
                        sized = f"{count} of {len(paper['changes'])}"
                        if config.iteration_count == paper["m"]:
                            verdicts.append((name, v, count, len(paper["changes"])))
                    rows.append(
                        [f"`{config.label}`", f"`{v}`", *cells, mean_text(flips) if flips else "—", sized]
                    )
            out.append(f"Percent change against `{self.baseline}` of the same variant [95 % interval]:\n")
            out.append(
                table(
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
            matched = [f"`{v}` on {s} ({c} of {k})" for s, v, c, k in verdicts if c == k]
            out.append(
                "At the paper's m, "
                + (
                    "every paper number of a scenario is matched in size under: " + ", ".join(matched) + "."
                    if matched
                    else f"no variant matches all of a scenario's paper numbers in size; the closest is "
                    f"`{best[1]}` on {best[0]} ({best[2]} of {best[3]})."
                )
                + "\n"
            )
        if figure is not None:
            out.append(f"![ablation](figures/{figure.name})\n")
        return "\n".join(out)


def write_report(result: StudyResult, out: str | Path, *, command: str = "", figures: bool = True) -> Path:
    """Write ``results.csv`` (per run), ``summary.csv``, ``results.json``, the figures
    (``figures/*.png``, unless ``figures`` is False) and ``report.md`` into ``out``; return the
    report's path."""
    out = Path(out)
    folder = out / "figures"
    study = result.study
    summary = summarize(result.study, result.runs)
    table = RunTable(result.runs)
    keyed = {(r["scenario"], r["variant"], r["config"], r["metric"]): r for r in summary}

    drawn: dict[str, list[Path]] = {}
    ablation_figure = None
    if figures:
        folder.mkdir(parents=True, exist_ok=True)
        for scenario in study.scenarios:
            paths = [plot_sweep(table, study, scenario.name, folder / f"sweep_{scenario.name}.png")]
            panels = result.figures.get(scenario.name, [])
            if panels:
                paths = plot_runs(panels, scenario.name, scenario.transient, folder) + paths
            drawn[scenario.name] = paths
        if study.variants and any(s.name in PAPER_RESULTS for s in study.scenarios):
            ablation_figure = plot_ablation(keyed, study, PAPER_RESULTS, folder / "ablation.png")

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
            "scenarios": [scenario_definition(s, out) for s in study.scenarios],
            "variants": [vars(v) for v in study.variants],
            "roles": {
                name: {k: c.label if c else None for k, c in roles(table, study, name).items()}
                for name in (s.name for s in study.scenarios)
            },
            "paper": PAPER_RESULTS,
            "wall_time": result.wall_time,
            "cross_checks": [check._asdict() for check in result.checks],
            "runs": result.runs,
            "summary": summary,
        },
    )
    text = _Report(result, summary, command, out).render(drawn, ablation_figure)
    return write_atomic(out / "report.md", text)


def _cell(value: Any) -> Any:
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True)
    return value


def paper_tables(result: StudyResult) -> str:
    """The report's "paper's table beside ours" section (markdown), empty without paper
    scenarios or with a baseline other than m = 0; the CLI prints it."""
    study = result.study
    if study.baseline.iteration_count != 0 or not any(s.name in PAPER_RESULTS for s in study.scenarios):
        return ""
    return _Report(result, summarize(result.study, result.runs), "", Path(".")).paper_section()
