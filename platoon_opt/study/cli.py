"""The ``platoon-opt`` command."""

from __future__ import annotations

import argparse
import ast
import importlib.util
import sys
import time
from pathlib import Path
from typing import Any

from platoon_opt.errors import AllocationError, ScenarioError
from platoon_opt.metrics import integrated_errors
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.study.output import write_json, write_timeseries


class UsageError(ValueError):
    """Bad command-line input: printed as one line, exit status 2."""


# Exit status of a --strict run whose allocation failed or fell back (one line on stderr).
ALLOCATION_FAILED = 3


def _allocation_failed(error: AllocationError, note: str = "") -> int:
    """Print a strict run's failure as one line (after any progress line) and return its status."""
    start = "\n" if sys.stderr.isatty() else ""
    print(f"{start}platoon-opt: error: {error}{note}", file=sys.stderr)
    return ALLOCATION_FAILED


def parse_options(pairs: list[str]) -> dict[str, Any]:
    """``["rho=100", "backend=osqp"]`` -> ``{"rho": 100, "backend": "osqp"}`` (Python literals,
    else strings)."""
    options: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key.isidentifier():
            raise UsageError(f"--option must look like name=value, got {pair!r}")
        try:
            options[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            options[key] = text
    return options


def _progress(label: str):
    def report(step: int, total: int) -> None:
        if sys.stderr.isatty() or step == total:
            print(f"\r{label}: step {step}/{total}", end="" if step < total else "\n", file=sys.stderr)

    return report


def cmd_simulate(args: argparse.Namespace) -> int:
    from platoon_opt.solvers import get_allocator
    from platoon_opt.study.figures import plot_errors, plot_trajectories

    scenario = load_scenario(args.scenario)
    options = parse_options(args.option)
    if args.solver == "iterative" and args.iterations is not None:
        options["max_iterations"] = args.iterations
    elif args.iterations is not None:
        raise UsageError(f"--iterations applies to --solver iterative, got --solver {args.solver}")
    try:
        allocator = get_allocator(args.solver, **options)
    except (TypeError, ValueError) as error:
        raise UsageError(f"--solver {args.solver}: {error}") from None
    start = time.perf_counter()
    try:
        trajectory = simulate(
            scenario,
            allocator,
            seed=args.seed,
            duration=args.duration,
            strict=args.strict,
            progress=_progress(scenario.name),
        )
    except AllocationError as error:
        return _allocation_failed(error.within(scenario=scenario.name, seed=args.seed))
    wall = time.perf_counter() - start
    metrics = integrated_errors(trajectory, scenario.transient)
    out = Path(args.out)
    write_timeseries(out / "timeseries.csv", trajectory)
    plot_trajectories([trajectory], out / "trajectory.png")
    plot_errors([trajectory], out / "errors.png")
    write_json(
        out / "metrics.json",
        {
            **metrics,
            "scenario": scenario.name,
            "scenario_file": scenario.source,
            "solver": args.solver,
            "allocator": allocator.name,
            "options": options,
            "seed": args.seed,
            "dt": scenario.dt,
            "steps": trajectory.steps,
            "wall_time": wall,
        },
    )
    keys = ("mean_position", "mean_position_after_transient", "var_x", "var_y", "gear_flips")
    print(
        f"{allocator.name} on {scenario.name} (seed {args.seed}): "
        + ", ".join(f"{k} = {metrics[k]:.4g}" for k in keys if k in metrics)
    )
    print(f"wrote {out}/metrics.json, timeseries.csv, trajectory.png, errors.png")
    return 0


def _study_configs(texts: list[str] | None, default: list[Any]) -> list[Any]:
    """--solvers items as validated allocator configurations (``default`` when none given)."""
    from platoon_opt.solvers import available_allocators, get_allocator
    from platoon_opt.study.harness import parse_config

    if not texts:
        return default
    configs = []
    for text in texts:
        if text == "all":
            configs += default_configs_of(available_allocators())
            continue
        try:
            config = parse_config(text)
        except ValueError as error:
            raise UsageError(f"--solvers: {error}") from None
        if config.name not in available_allocators():
            raise UsageError(
                f"--solvers: unknown allocator {config.name!r}; known: {', '.join(available_allocators())}"
            )
        configs.append(config)
    for config in configs:
        try:
            config.build(get_allocator)
        except (TypeError, ValueError) as error:
            raise UsageError(f"--solvers {config.label}: {error}") from None
    labels = [c.label for c in configs]
    if len(set(labels)) != len(labels):
        raise UsageError(f"--solvers: each configuration once, got {' '.join(labels)}")
    return configs


def default_configs_of(available: list[str]) -> list[Any]:
    """m = 0..8 and every other registered allocator."""
    from platoon_opt.study.harness import default_configs

    return default_configs(available)


def _run_study(args: argparse.Namespace, study: Any, out: Path, label: str) -> int:
    from platoon_opt.solvers import get_allocator
    from platoon_opt.study.harness import run_study
    from platoon_opt.study.report import duration_text, paper_tables

    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    if args.scheduler is not None and importlib.util.find_spec("distributed") is None:
        raise UsageError("--scheduler needs dask.distributed: pip install 'platoon-opt[dask]'")
    command = " ".join(["platoon-opt", *args.argv])
    try:
        result = run_study(
            study,
            get_allocator,
            out,
            workers=args.workers,
            scheduler=args.scheduler,
            fresh=args.fresh,
            label=label,
            command=command,
        )
    except KeyboardInterrupt:
        print(
            f"\ninterrupted: finished runs are kept in {out}/runs; rerun the same command to resume",
            file=sys.stderr,
        )
        return 130
    except AllocationError as error:
        return _allocation_failed(error, f"; finished runs are kept in {out}/runs")
    except OSError as error:
        if args.scheduler is None:
            raise
        raise UsageError(f"--scheduler {args.scheduler}: {error}") from None
    print(paper_tables(result), end="")
    print(
        f"{len(result.runs)} runs ({result.computed} computed, {len(result.runs) - result.computed} reused) "
        f"in {duration_text(result.wall_time)}; wrote {out}/report.md, results.csv, results.json, figures/"
    )
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    from platoon_opt.solvers import available_allocators
    from platoon_opt.study.harness import (
        ABLATION_VARIANTS,
        DEFAULT_ABLATION_SEEDS,
        DEFAULT_SEEDS,
        QUICK,
        paper_study,
        reproduce_configs,
    )

    defaults = QUICK if args.quick else {"seeds": DEFAULT_SEEDS, "ablation_seeds": DEFAULT_ABLATION_SEEDS}
    seeds = args.seeds if args.seeds is not None else defaults["seeds"]
    ablation_seeds = args.ablation_seeds if args.ablation_seeds is not None else defaults["ablation_seeds"]
    duration = args.duration if args.duration is not None else defaults.get("duration")
    if seeds < 1 or ablation_seeds < 0:
        raise UsageError(f"--seeds must be >= 1 and --ablation-seeds >= 0, got {seeds}, {ablation_seeds}")
    if duration is not None and duration <= 0:
        raise UsageError(f"--duration must be > 0, got {duration}")
    configs = _study_configs(args.solvers, reproduce_configs(available_allocators()))
    study = paper_study(
        available_allocators(),
        seeds=seeds,
        ablation_seeds=max(ablation_seeds, 1),
        duration=duration,
        configs=configs,
        variants=() if ablation_seeds == 0 else ABLATION_VARIANTS,
        strict=args.strict,
    )
    out = Path(args.out if args.out is not None else ("results/quick" if args.quick else "results"))
    return _run_study(args, study, out, "reproduce")


def cmd_compare(args: argparse.Namespace) -> int:
    from platoon_opt.solvers import available_allocators
    from platoon_opt.study.harness import PAPER_ITERATIONS, Study, seeds_range

    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    if args.duration is not None and args.duration <= 0:
        raise UsageError(f"--duration must be > 0, got {args.duration}")
    scenarios = tuple(load_scenario(name) for name in args.scenario)
    configs = _study_configs(args.solvers, default_configs_of(available_allocators()))
    try:
        study = Study(
            scenarios,
            tuple(configs),
            seeds_range(args.seeds),
            args.duration,
            paper_iterations=PAPER_ITERATIONS,
            strict=args.strict,
        )
    except ValueError as error:
        raise UsageError(str(error)) from None
    return _run_study(args, study, Path(args.out), "compare")


def _study_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--solvers",
        nargs="+",
        metavar="CONFIG",
        help="configurations, the first is the baseline: m=M (the paper's iteration), NAME, "
        "NAME:key=value,... or all (default: m=0..8 and every registered allocator)",
    )
    parser.add_argument("--duration", type=float, help="override each scenario's duration (s)")
    parser.add_argument("--workers", type=int, help="worker processes (default: one per CPU)")
    parser.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (needs platoon-opt[dask])"
    )
    parser.add_argument("--fresh", action="store_true", help="recompute runs finished by an earlier call")
    _strict_option(parser)


def _strict_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--strict",
        action="store_true",
        help="stop at the first step whose allocation fails or falls back: one line naming the allocator, "
        f"scenario and seed, exit status {ALLOCATION_FAILED} (default: carry on with the fallback)",
    )


def cmd_bench(args: argparse.Namespace) -> int:
    """Run the speed and scale benchmark (``platoon_opt.study.bench``)."""
    from platoon_opt.study import bench

    if args.sizes is not None and any(n < 2 for n in args.sizes):
        raise UsageError(f"--sizes must be >= 2, got {args.sizes}")
    options: dict[str, Any] = {}
    if args.quick:
        options = {"sizes": (8, 64, 512), "dual_only": (), "small_duration": 2.0, "closed_loop_duration": 2.0}
    if args.sizes is not None:
        options["sizes"] = tuple(args.sizes)
    bench.run(args.out, **options)
    return 0


def build_parser() -> argparse.ArgumentParser:
    from platoon_opt.study.harness import DEFAULT_ABLATION_SEEDS, DEFAULT_SEEDS

    parser = argparse.ArgumentParser(prog="platoon-opt", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    sim = commands.add_parser(
        "simulate",
        help="run one scenario under one allocator",
        description="Run one scenario under one allocator; write metrics.json, timeseries.csv "
        "and figures to --out.",
    )
    sim.add_argument("scenario", help="scenario file, or a name in experiments/scenarios/")
    sim.add_argument("--solver", default="iterative", help="allocator name (default: iterative)")
    sim.add_argument("--iterations", type=int, help="the paper's m for --solver iterative")
    sim.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="allocator option, repeatable (e.g. --option rho=100)",
    )
    sim.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    sim.add_argument("--duration", type=float, help="override the scenario's duration (s)")
    sim.add_argument("--out", default="out", help="output folder (default: out)")
    _strict_option(sim)
    sim.set_defaults(run=cmd_simulate)
    rep = commands.add_parser(
        "reproduce",
        help="the paper's tables and figures: every allocator, many seeds, the ablation",
        description="Run both paper scenarios under m = 0..8 and every registered allocator (but the "
        "slow nmpc and the casadi-qp and dual cross-checks of qp) over many seeds, plus the ablation of "
        "the modelling choices; write report.md, results.csv, results.json and figures/ to --out. "
        "Resumable: rerun after an interruption to finish.",
    )
    rep.add_argument("--out", help="output folder (default: results, or results/quick with --quick)")
    rep.add_argument(
        "--seeds", type=int, help=f"seeds per configuration (default {DEFAULT_SEEDS}; --quick: 2)"
    )
    rep.add_argument(
        "--ablation-seeds",
        type=int,
        help=f"seeds of the ablation runs (default {DEFAULT_ABLATION_SEEDS}; --quick: 1; 0: no ablation)",
    )
    rep.add_argument(
        "--quick", action="store_true", help="2 seeds of 8 s: checks the pipeline in about 2 minutes"
    )
    _study_options(rep)
    rep.set_defaults(run=cmd_reproduce)
    cmp = commands.add_parser(
        "compare",
        help="compare allocator configurations on scenario files over many seeds",
        description="Run every configuration on every scenario and seed; write report.md, "
        "results.csv, results.json and figures/ to --out. Resumable.",
    )
    cmp.add_argument("scenario", nargs="+", help="scenario files, or names in experiments/scenarios/")
    cmp.add_argument("--seeds", type=int, default=10, help="seeds per configuration (default 10)")
    cmp.add_argument("--out", default="results/compare", help="output folder (default: results/compare)")
    _study_options(cmp)
    cmp.set_defaults(run=cmd_compare)
    ben = commands.add_parser(
        "bench",
        help="speed and scale of the allocators and of the control step",
        description="Time every allocator from 8 to 32,768 units (the dual to 100,000), the whole "
        "control step, n = 8 against Clarabel's bare solve, and the closed loop; write bench.json, "
        "bench.md and bench.png to --out. Takes a few minutes.",
    )
    ben.add_argument(
        "--out", default="benchmarks/results", help="output folder (default: benchmarks/results)"
    )
    ben.add_argument("--sizes", type=int, nargs="+", help="problem sizes (default 8 64 512 4096 32768)")
    ben.add_argument("--quick", action="store_true", help="n = 8, 64, 512 and short closed loops (~1 min)")
    ben.set_defaults(run=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else list(argv)
    try:
        return args.run(args)
    except (UsageError, ScenarioError) as error:
        print(f"platoon-opt: error: {error}", file=sys.stderr)
        return 2
    except AllocationError as error:
        return _allocation_failed(error)


if __name__ == "__main__":
    sys.exit(main())
