"""Closed-loop study: the receding-horizon allocator ("nmpc") against the paper's iteration.

Runs every allocator spec on both paper scenarios over many seeds (``multiprocessing``
pool), caches one JSON per run under ``--out`` (re-running skips finished runs), and prints
a table of the integrated errors (mean +- 95 % t-interval over seeds) with, for each error,
the paired difference of every spec against the best iterative m.

    python experiments/nmpc_study.py --seeds 0-19 --specs iterative:max_iterations=0..8
    python experiments/nmpc_study.py --seeds 0-19 --specs nmpc nmpc:horizon=1.0 --table

A spec is ``name`` or ``name:key=value,key=value``; ``key=a..b`` expands to the integers a..b.
"""

from __future__ import annotations

import argparse
import ast
import json
import math
import os
import sys
import time
from multiprocessing import Pool
from pathlib import Path

# One BLAS thread per process: the allocators' matrices are small, and two processes with
# multithreaded BLAS on a shared machine spend most of their time waiting for each other.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from platoon_opt import integrated_errors, load_scenario, simulate  # noqa: E402
from platoon_opt.study.output import write_json  # noqa: E402

SCENARIOS = ("paper_no_obstacles", "paper_obstacles")
ERRORS = ("mean_position", "mean_position_after_transient", "var_x", "var_y")
EXTRA = ("time_inside_obstacles", "inside_steps", "gear_flips", "fallback_steps")


def expand(spec: str) -> list[str]:
    """``iterative:max_iterations=0..2`` -> three specs."""
    name, _, rest = spec.partition(":")
    if not rest:
        return [name]
    specs = [[]]
    for pair in rest.split(","):
        key, _, value = pair.partition("=")
        if ".." in value:
            low, high = (int(v) for v in value.split(".."))
            specs = [s + [f"{key}={v}"] for s in specs for v in range(low, high + 1)]
        else:
            specs = [s + [pair] for s in specs]
    return [f"{name}:{','.join(s)}" for s in specs]


def parse(spec: str) -> tuple[str, dict]:
    name, _, rest = spec.partition(":")
    options = {}
    for pair in filter(None, rest.split(",")):
        key, _, value = pair.partition("=")
        try:
            options[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            options[key] = value
    return name, options


def seeds_of(text: str) -> list[int]:
    seeds: list[int] = []
    for part in text.split(","):
        low, _, high = part.partition("-")
        seeds.extend(range(int(low), int(high or low) + 1))
    return seeds


def run_path(out: Path, scenario: str, spec: str, seed: int) -> Path:
    return out / scenario / spec.replace(":", "__").replace("=", "-").replace(",", "_") / f"seed_{seed}.json"


def run_one(job: tuple[str, str, int, str]) -> str:
    """One closed-loop run; writes its metrics JSON."""
    scenario_name, spec, seed, out = job
    from platoon_opt.solvers import get_allocator

    path = run_path(Path(out), scenario_name, spec, seed)
    if path.exists():
        return f"skip {path}"
    scenario = load_scenario(scenario_name)
    name, options = parse(spec)
    allocator = get_allocator(name, **options)
    start = time.perf_counter()
    trajectory = simulate(scenario, allocator, seed=seed)
    wall = time.perf_counter() - start
    metrics = integrated_errors(trajectory, scenario.transient)
    if len(trajectory.obstacles):
        clearance = trajectory.obstacles.nearest(
            np.column_stack((trajectory.x[:-1].ravel(), trajectory.y[:-1].ravel()))
        )[0]
        inside = int(np.any((clearance < 0).reshape(trajectory.x[:-1].shape), axis=1).sum())
    else:
        inside = 0
    solves = np.array([s for s in trajectory.solve_time])
    # Steps that solved (the receding-horizon allocator hands its stored plan, status "plan",
    # between solves).
    resolved = np.array([str(s) != "plan" for s in trajectory.status])
    statuses: dict[str, int] = {}
    for status in trajectory.status:
        statuses[str(status)] = statuses.get(str(status), 0) + 1
    write_json(
        path,
        {
            **metrics,
            "inside_steps": inside,
            "scenario": scenario_name,
            "spec": spec,
            "allocator": allocator.name,
            "seed": seed,
            "wall_time": wall,
            "solve_time_mean": float(solves.mean()),
            "solve_time_resolve_median": float(np.median(solves[resolved])) if resolved.any() else 0.0,
            "solve_time_resolve_p95": float(np.percentile(solves[resolved], 95)) if resolved.any() else 0.0,
            "statuses": statuses,
        },
    )
    return f"done {path} in {wall:.1f} s"


def interval(values: np.ndarray) -> tuple[float, float]:
    """Mean and half-width of the 95 % t-interval."""
    if values.size < 2:
        return float(values.mean()), math.nan
    return float(values.mean()), float(stats.t.ppf(0.975, values.size - 1) * stats.sem(values))


def load(out: Path, scenario: str, spec: str, seeds: list[int]) -> list[dict] | None:
    runs = []
    for seed in seeds:
        path = run_path(out, scenario, spec, seed)
        if not path.exists():
            return None
        runs.append(json.loads(path.read_text()))
    return runs


def table(out: Path, specs: list[str], seeds: list[int]) -> str:
    """Markdown tables per scenario; the comparison uses the seeds every spec finished."""
    lines = []
    for scenario in SCENARIOS:
        results = {spec: load(out, scenario, spec, seeds) for spec in specs}
        results = {spec: runs for spec, runs in results.items() if runs}
        if not results:
            continue
        lines += [f"\n### {scenario} ({len(seeds)} seeds: {seeds[0]}..{seeds[-1]})\n"]
        header = "| allocator | " + " | ".join(ERRORS + EXTRA) + " | solve median / p95 (ms) |"
        lines += [header, "|" + "---|" * (len(ERRORS) + len(EXTRA) + 2)]
        for spec, runs in results.items():
            cells = []
            for key in ERRORS + EXTRA:
                mean, half = interval(np.array([r[key] for r in runs], dtype=float))
                cells.append(f"{mean:.4g} ± {half:.2g}")
            median = np.median([r["solve_time_resolve_median"] for r in runs]) * 1e3
            p95 = np.median([r["solve_time_resolve_p95"] for r in runs]) * 1e3
            lines.append(f"| {spec} | " + " | ".join(cells) + f" | {median:.2f} / {p95:.2f} |")
        iterative = [s for s in results if s.startswith("iterative")]
        others = [s for s in results if not s.startswith("iterative")]
        if not iterative or not others:
            continue
        lines += [
            "",
            "Paired difference against the best iterative m per error (mean ± 95 %, "
            "relative to that m's mean); `beats` = interval entirely below 0.",
            "",
        ]
        lines += ["| allocator | " + " | ".join(ERRORS) + " | inside_steps |", "|" + "---|" * 6]
        for spec in others:
            cells = []
            for key in ERRORS + ("inside_steps",):
                best = min(iterative, key=lambda s, k=key: np.mean([r[k] for r in results[s]]))
                base = np.array([r[key] for r in results[best]], dtype=float)
                diff = np.array([r[key] for r in results[spec]], dtype=float) - base
                mean, half = interval(diff)
                scale = base.mean() if base.mean() else 1.0
                verdict = "beats" if mean + half < 0 else ("loses" if mean - half > 0 else "tie")
                best_m = best.split("=")[-1]
                cells.append(f"{100 * mean / scale:+.1f} % ± {100 * half / scale:.1f} ({verdict} m={best_m})")
            lines.append(f"| {spec} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--specs", nargs="+", default=["iterative:max_iterations=0..8", "nmpc"])
    parser.add_argument("--seeds", default="0-19")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--out", default=str(ROOT / "results" / "nmpc_study"))
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--table", action="store_true", help="only print the table of finished runs")
    args = parser.parse_args()
    specs = [s for spec in args.specs for s in expand(spec)]
    seeds = seeds_of(args.seeds)
    out = Path(args.out)
    if not args.table:
        jobs = [(sc, spec, seed, str(out)) for spec in specs for sc in args.scenarios for seed in seeds]
        with Pool(args.workers) as pool:
            for message in pool.imap_unordered(run_one, jobs):
                print(message, flush=True)
    print(table(out, specs, seeds))


if __name__ == "__main__":
    main()
