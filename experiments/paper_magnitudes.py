"""The paper's magnitudes, explained: an ablation of the modelling choices the paper leaves open.

For both paper scenarios, m = 0 and the paper's m (4 without obstacles, 3 with) on every variant
below, over ``--seeds`` seeds (0 .. seeds - 1, the same for every cell, so each comparison is
paired by seed); with ``--best-m`` also m = 1..8 on the variants of ``BEST_M_VARIANTS``. Each
error's change at m against m = 0 is the ratio of means as a percent with its 95 % paired
bootstrap interval (``platoon_opt.study.ratios.paired_change``), and ``paper.verdict`` says
whether it matches the paper's number in direction and order of size. Nothing is tuned: the
variants' values were fixed before any run (the offsets 0.5, 1 and 2 m span the shipped
``_offset`` files' 1 m; K_alpha dt = 1, 0.5, 0.2 at dt = 0.01 s).

    nice -n 19 python experiments/paper_magnitudes.py --seeds 200 --best-m

Prints the table and writes experiments/results/paper_magnitudes.json (``--json``). With
``--runs DIR`` each finished run is kept there and a rerun resumes (``study.dispatch.run_specs``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from platoon_opt.scenarios import load_scenario
from platoon_opt.solvers import get_allocator
from platoon_opt.study.config import iterative_configs
from platoon_opt.study.dispatch import run_specs
from platoon_opt.study.executor import Progress
from platoon_opt.study.harness import seeds_range
from platoon_opt.study.paper import PAPER_ITERATIONS, PAPER_RESULTS, verdict
from platoon_opt.study.ratios import paired_change
from platoon_opt.study.runs import RunSpec
from platoon_opt.study.variants import Variant

# The literal reading: the paper's platoon starts on the left (1 m, the shipped ``_offset`` files'
# choice), its gear rule has no hysteresis (the paper allows backing and gives no rule), Eq. 6's
# "ahead" is on "the current heading theta" (as the base), K_alpha = 100 at dt = 0.01 s (the
# paper's K_alpha, dt not given) and a 2006 simulation's Euler steps.
LITERAL = {"start_offset": 1.0, "gear_hysteresis_deg": 0.0, "integration": "euler"}

VARIANTS = (
    Variant("base", "as in the scenario file (no offset, 30 deg hysteresis, K_alpha dt = 1, arcs)"),
    Variant("offset-0.5", "offset 0.5 m", start_offset=0.5),
    Variant("offset-1", "offset 1 m", start_offset=1.0),
    Variant("offset-2", "offset 2 m", start_offset=2.0),
    Variant("no-hysteresis", "gear rule without hysteresis", gear_hysteresis_deg=0.0),
    Variant("gain-0.5", "K_alpha dt = 0.5", steering_gain=50.0),
    Variant("gain-0.2", "K_alpha dt = 0.2", steering_gain=20.0),
    Variant("travel-ahead", 'Eq. 6 "ahead" on the travel direction', ahead_reference="travel"),
    Variant("half-dt", "dt / 2 (K_alpha dt = 0.5)", dt_scale=0.5),
    Variant("euler", "Euler steps", integration="euler"),
    Variant("offset-1-no-hysteresis", "offset 1 m, no hysteresis", start_offset=1.0, gear_hysteresis_deg=0.0),
    Variant("offset-1-euler", "offset 1 m, Euler", start_offset=1.0, integration="euler"),
    Variant("offset-1-gain-0.2", "offset 1 m, K_alpha dt = 0.2", start_offset=1.0, steering_gain=20.0),
    Variant("literal", "literal: offset 1 m, no hysteresis, Euler", **LITERAL),
    Variant("literal-offset-2", "literal with offset 2 m", **{**LITERAL, "start_offset": 2.0}),
    Variant("literal-travel", "literal, Eq. 6 on travel", **LITERAL, ahead_reference="travel"),
)
# The variants that also run m = 1..8 with --best-m.
BEST_M_VARIANTS = ("base", "offset-1", "literal")
ERRORS = ("mean_position", "mean_position_after_transient", "var_x", "var_y")
# Context besides the errors (means over the seeds).
EXTRAS = ("gear_flips", "time_inside_obstacles")
DEFAULT_JSON = Path(__file__).parent / "results" / "paper_magnitudes.json"


def specs(seeds: tuple[int, ...], best_m: bool) -> list[RunSpec]:
    """Every scenario x variant (those that affect it) x m x seed."""
    out = []
    for name, paper_m in PAPER_ITERATIONS.items():
        scenario = load_scenario(name)
        for variant in VARIANTS:
            if not variant.affects(scenario):
                continue
            ms = range(9) if best_m and variant.name in BEST_M_VARIANTS else (0, paper_m)
            for config in iterative_configs(ms):
                out += [RunSpec(scenario, variant, config, seed) for seed in seeds]
    return out


def cells(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """scenario -> variant -> {"means": m -> metric -> mean, "changes": ..., "best_m": ...}."""
    table: dict[tuple[str, str, str], dict[int, dict[str, Any]]] = {}
    for run in runs:
        table.setdefault((run["scenario"], run["variant"], run["config"]), {})[run["seed"]] = run
    out: dict[str, Any] = {}
    for name, paper_m in PAPER_ITERATIONS.items():
        paper = PAPER_RESULTS[name]["changes"]
        titles = {v.name: v.title for v in VARIANTS}
        for variant in [v.name for v in VARIANTS if (name, v.name, "m=0") in table]:
            configs = {
                int(c[2:]): table[(name, variant, c)] for (s, v, c) in table if (s, v) == (name, variant)
            }
            seeds = sorted(configs[0])
            values = {
                m: {k: np.array([runs_[s][k] for s in seeds], dtype=float) for k in ERRORS + EXTRAS}
                for m, runs_ in configs.items()
            }
            base = values[0]
            m0 = base["mean_position"]
            cell: dict[str, Any] = {
                "title": titles[variant],
                "seeds": len(seeds),
                "means": {f"m={m}": {k: float(v[k].mean()) for k in v} for m, v in sorted(values.items())},
                # The share of m = 0's mean-position error before the transient's end (the paper's
                # -5.3 % and -21 % imply 75 % if m does not change the first 4 s).
                "transient_share": float(1 - base["mean_position_after_transient"].mean() / m0.mean()),
                "changes": {},
            }
            for error in ERRORS:
                change = paired_change(values[paper_m][error], base[error])
                entry = {
                    "m": paper_m,
                    "kind": change.kind,
                    "value": change.value,
                    "low": change.low,
                    "high": change.high,
                    "wins": change.wins,
                }
                if error in paper:
                    entry["paper"] = paper[error]
                    entry["verdict"] = verdict(change.value, change.low, change.high, paper[error])
                if len(values) == 9:
                    best = min(range(1, 9), key=lambda m: values[m][error].mean())
                    b = paired_change(values[best][error], base[error])
                    entry["best_m"] = {"m": best, "value": b.value, "low": b.low, "high": b.high}
                    if error in paper:
                        entry["best_m"]["verdict"] = verdict(b.value, b.low, b.high, paper[error])
                cell["changes"][error] = entry
            out.setdefault(name, {})[variant] = cell
    return out


def _pct(entry: dict[str, Any]) -> str:
    return f"{entry['value']:+.1f} [{entry['low']:+.1f}, {entry['high']:+.1f}]"


def table(results: dict[str, Any]) -> str:
    """A markdown table per scenario: each variant's changes at the paper's m with intervals, a
    check mark where ``paper.verdict`` says same direction and same order of size."""
    lines = []
    for name, variants in results.items():
        paper = PAPER_RESULTS[name]["changes"]
        errors = [e for e in ERRORS if e in paper]
        m = PAPER_ITERATIONS[name]
        lines += [
            f"### {name}: m = {m} against m = 0, % [95 % interval]",
            "",
            "| variant | m=0 mean pos. (m s) | transient share | "
            + " | ".join(f"{e} (paper {paper[e]:+.1f})" for e in errors)
            + " | gear flips m=0 / m |",
            "|---" * (len(errors) + 4) + "|",
        ]
        for variant, cell in variants.items():
            row = []
            for error in errors:
                entry = cell["changes"][error]
                mark = " ✓" if entry["verdict"].startswith("direction yes; same order") else ""
                row.append(_pct(entry) + mark)
            means, share = cell["means"], 100 * cell["transient_share"]
            lines.append(
                f"| {variant} | {means['m=0']['mean_position']:.2f} | {share:.0f} % | "
                + " | ".join(row)
                + f" | {means['m=0']['gear_flips']:.0f} / {means[f'm={m}']['gear_flips']:.0f} |"
            )
        best = [(v, c) for v, c in variants.items() if "best_m" in c["changes"][errors[0]]]
        if best:
            lines += ["", f"Best m of 1..8 per error (picked on these seeds), against m = 0 ({name}):", ""]
            lines += ["| variant | " + " | ".join(errors) + " |", "|---" * (len(errors) + 1) + "|"]
            for variant, cell in best:
                row = [
                    f"m={cell['changes'][e]['best_m']['m']}: {_pct(cell['changes'][e]['best_m'])}"
                    for e in errors
                ]
                lines.append(f"| {variant} | " + " | ".join(row) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=200)
    parser.add_argument(
        "--best-m", action="store_true", help="also m = 1..8 on " + ", ".join(BEST_M_VARIANTS)
    )
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--runs", help="keep finished runs here (a rerun resumes)")
    parser.add_argument("--json", default=str(DEFAULT_JSON))
    args = parser.parse_args(argv)
    seeds = seeds_range(args.seeds)
    start = time.perf_counter()
    todo = specs(seeds, args.best_m)
    with Progress(len(todo), "paper magnitudes", stream=sys.stderr) as progress:
        runs = run_specs(todo, get_allocator, runs_dir=args.runs, workers=args.workers, progress=progress)
    wall = time.perf_counter() - start
    results = cells(runs)
    fell_back = sum(1 for run in runs if run["first_fallback"])
    meta = {
        "seeds": args.seeds,
        "runs": len(runs),
        "runs_with_a_fallback": fell_back,
        "wall_time_s": round(wall, 1),
        "workers": args.workers,
        "machine": f"{platform.machine()}, {platform.system()}, {os.cpu_count()} CPUs",
        "variants": {v.name: {k: val for k, val in vars(v).items() if val is not None} for v in VARIANTS},
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"meta": meta, "results": results}, indent=1) + "\n")
    print(table(results))
    print(f"{len(runs)} runs ({fell_back} with a fallback step) in {wall:.0f} s; written to {args.json}")


if __name__ == "__main__":
    main()
