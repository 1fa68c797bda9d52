"""The ``platoon-opt`` command: simulate, reproduce, compare, bench, soak, allocators.

Bad input prints one line naming what was wrong and exits 2; a ``--strict`` run whose allocation
failed prints one line and exits 3. Outputs go under ``./platoon-opt-results/<command>`` unless
``--out`` says otherwise, so that no default overwrites a file of the repository.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import platoon_opt
from platoon_opt.allocation import check_allocator
from platoon_opt.errors import AllocationError, OptionError, PlatoonOptError
from platoon_opt.metrics import integrated_errors
from platoon_opt.scenarios import PAPER_SCENARIOS, Scenario, load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import available_allocators, get_allocator
from platoon_opt.solvers.registry import registered
from platoon_opt.study import bench, catalog, fuzz, soak
from platoon_opt.study.arguments import COUNT, SEED, SIZE, Parser, UsageError, integer, output_folder, seconds
from platoon_opt.study.battery import BATTERY, battery_configs, battery_study
from platoon_opt.study.compile_cache import enable_compilation_cache
from platoon_opt.study.config import AllocatorConfig, default_configs, parse_config, parse_options
from platoon_opt.study.executor import Progress, share_cores
from platoon_opt.study.exits import (
    ALLOCATION_FAILED,
    BROKEN_PIPE,
    allocation_failed,
    bad_input,
    stopped,
    terminate_on_sigterm,
)
from platoon_opt.study.fallbacks import run_count
from platoon_opt.study.figures import plot_errors, plot_trajectories
from platoon_opt.study.harness import Study, run_study, seeds_range
from platoon_opt.study.markdown import duration_text
from platoon_opt.study.output import write_json, write_timeseries
from platoon_opt.study.paper import (
    DEFAULT,
    PAPER_ITERATIONS,
    QUICK,
    paper_study,
    reproduce_configs,
)
from platoon_opt.study.report import paper_tables, write_report
from platoon_opt.study.runs import scenario_source
from platoon_opt.study.variants import ABLATION_VARIANTS

# Where the commands write when --out is not given (under the working directory).
RESULTS = Path("platoon-opt-results")


def _options(pairs: list[str]) -> dict[str, Any]:
    try:
        return parse_options(pairs)
    except ValueError as error:
        raise UsageError(str(error)) from None


def _steps(scenario: Scenario, duration: float | None) -> int:
    """Steps of a run of ``--duration`` (None: the scenario's); ``UsageError`` naming the flag."""
    try:
        return scenario.run_steps(duration, name="--duration")
    except ValueError as error:
        raise UsageError(str(error)) from None


def _warn_transient(scenario: Scenario, steps: int) -> None:
    """One warning line if a run of ``steps`` ends within the scenario's transient: its
    after-transient errors integrate at most one instant, so they read 0."""
    if (steps - 1) * scenario.dt < scenario.transient - 1e-12:
        print(
            f"platoon-opt: warning: a run of {steps * scenario.dt:g} s ends within the "
            f"{scenario.transient:g} s transient of {scenario.name}: its after-transient errors are 0",
            file=sys.stderr,
        )


def _check_task(allocator: Any, scenario: Scenario, what: str) -> None:
    """The allocator's check of the scenario's task (``TaskChecked``), before any step."""
    try:
        check_allocator(allocator, tuple(scenario.task().names))
    except OptionError as error:
        raise UsageError(f"{what}: {error}") from None


def cmd_simulate(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    options = _options(args.option)
    if args.solver == "iterative" and args.iterations is not None:
        options["max_iterations"] = args.iterations
    elif args.iterations is not None:
        raise UsageError(f"--iterations applies to --solver iterative, got --solver {args.solver}")
    try:
        allocator = get_allocator(args.solver, **options)
    except OptionError as error:
        raise UsageError(f"--solver {args.solver}: {error}") from None
    steps = _steps(scenario, args.duration)
    _check_task(allocator, scenario, f"--solver {args.solver}")
    out = output_folder(args.out)
    start = time.perf_counter()
    try:
        with Progress(steps, scenario.name, unit="steps") as progress:
            trajectory = simulate(
                scenario,
                allocator,
                seed=args.seed,
                duration=args.duration,
                strict=args.strict,
                progress=lambda step, total: progress.advance(step - progress.done),
            )
    except AllocationError as error:
        return allocation_failed(error.within(scenario=scenario.name, seed=args.seed))
    wall = time.perf_counter() - start
    metrics = integrated_errors(trajectory, scenario.transient)
    write_timeseries(out / "timeseries.csv", trajectory)
    written = ["metrics.json", "timeseries.csv"]
    if not args.no_figures:
        plot_trajectories([trajectory], out / "trajectory.png")
        plot_errors([trajectory], out / "errors.png")
        written += ["trajectory.png", "errors.png"]
    write_json(
        out / "metrics.json",
        {
            **metrics,
            "scenario": scenario.name,
            "scenario_file": scenario_source(scenario, out),
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
    print(f"wrote {out}/{', '.join(written)}")
    _warn_transient(scenario, steps)
    fallbacks = run_count(trajectory, allocator.name)
    if fallbacks.too_many:
        print(fallbacks.warning(), file=sys.stderr)
    return 0


def _study_configs(texts: list[str] | None, default: list[AllocatorConfig]) -> list[AllocatorConfig]:
    """--solvers items as validated allocator configurations (``default`` when none given)."""
    if not texts:
        return default
    configs = []
    for text in texts:
        if text == "all":
            configs += default_configs(available_allocators())
            continue
        try:
            configs.append(parse_config(text))
        except ValueError as error:
            raise UsageError(f"--solvers: {error}") from None
    for config in configs:
        try:
            config.build(get_allocator)  # an unknown name or a bad option fails here, before any run
        except OptionError as error:
            raise UsageError(f"--solvers {config.label}: {error}") from None
    labels = [c.label for c in configs]
    if len(set(labels)) != len(labels):
        raise UsageError(f"--solvers: each configuration once, got {' '.join(labels)}")
    return configs


def _run_study(args: argparse.Namespace, study: Study, out: Path, label: str) -> int:
    if args.scheduler is not None and importlib.util.find_spec("distributed") is None:
        raise UsageError("--scheduler needs dask.distributed: pip install 'platoon-opt[dask]'")
    try:
        result = run_study(
            study,
            get_allocator,
            out,
            workers=args.workers,
            scheduler=args.scheduler,
            fresh=args.fresh,
            label=label,
        )
    except KeyboardInterrupt as stop:
        what, status = stopped(stop)
        print(
            f"\n{what}: finished runs are kept in {out}/runs; rerun the same command to resume",
            file=sys.stderr,
        )
        return status
    except AllocationError as error:
        return allocation_failed(error, f"; finished runs are kept in {out}/runs")
    except OSError as error:
        if args.scheduler is None:
            raise
        raise UsageError(f"--scheduler {args.scheduler}: {error}") from None
    for scenario in study.scenarios:
        _warn_transient(scenario, scenario.run_steps(study.duration))
    command = " ".join(["platoon-opt", *args.argv])
    write_report(result, out, command=command, figures=not args.no_figures)
    print(paper_tables(result), end="")
    print(
        f"{len(result.runs)} runs ({result.computed} computed, {len(result.runs) - result.computed} reused) "
        f"in {duration_text(result.wall_time)}; wrote {out}/report.md, results.csv, results.json"
        + ("" if args.no_figures else ", figures/")
    )
    return 0


def _study_duration(duration: float | None, scenarios: Sequence[Scenario]) -> None:
    """``--duration`` checked against every scenario's step (``UsageError`` naming the flag)."""
    for scenario in scenarios:
        _steps(scenario, duration)


def cmd_reproduce(args: argparse.Namespace) -> int:
    defaults = QUICK if args.quick else DEFAULT
    seeds = args.seeds if args.seeds is not None else defaults.seeds
    ablation_seeds = args.ablation_seeds if args.ablation_seeds is not None else defaults.ablation_seeds
    duration = args.duration if args.duration is not None else defaults.duration
    check_seeds = args.check_seeds if args.check_seeds is not None else defaults.check_seeds
    names = BATTERY if args.battery else PAPER_SCENARIOS
    _study_duration(duration, [load_scenario(name) for name in names])
    available = available_allocators()
    shipped = battery_configs if args.battery else reproduce_configs
    configs = _study_configs(args.solvers, shipped(available))
    common: dict[str, Any] = dict(
        seeds=seeds, duration=duration, configs=configs, strict=args.strict, check_seeds=check_seeds
    )
    if args.battery:
        study = battery_study(available, **common)
        folder = "battery-quick" if args.quick else "battery"
    else:
        variants = () if ablation_seeds == 0 else ABLATION_VARIANTS
        study = paper_study(available, ablation_seeds=max(ablation_seeds, 1), variants=variants, **common)
        folder = "quick" if args.quick else "reproduce"
    out = args.out if args.out is not None else str(RESULTS / folder)
    return _run_study(args, study, output_folder(out), "reproduce")


def cmd_compare(args: argparse.Namespace) -> int:
    scenarios = tuple(load_scenario(name) for name in args.scenario)
    _study_duration(args.duration, scenarios)
    configs = _study_configs(args.solvers, default_configs(available_allocators()))
    try:
        study = Study(
            scenarios,
            tuple(configs),
            seeds_range(args.seeds, args.first_seed),
            args.duration,
            paper_iterations=PAPER_ITERATIONS,
            strict=args.strict,
        )
    except ValueError as error:
        raise UsageError(str(error)) from None
    return _run_study(args, study, output_folder(args.out), "compare")


def cmd_bench(args: argparse.Namespace) -> int:
    if args.threads is not None:
        share_cores(args.threads)
    output_folder(args.out)
    options: dict[str, Any] = dict(bench.QUICK) if args.quick else {}
    if args.sizes is not None:
        options["sizes"] = tuple(args.sizes)
    if args.closed_loop_only:
        options["parts"] = ("closed_loop",)
    bench.run(args.out, **options, threads=args.threads, command=" ".join(["platoon-opt", *args.argv]))
    return 0


def cmd_soak(args: argparse.Namespace) -> int:
    problem = soak.check_arguments(args)
    if problem is not None:
        raise UsageError(problem)
    output_folder(args.out)
    return soak.command(args, " ".join(["platoon-opt", *args.argv]))


def cmd_fuzz(args: argparse.Namespace) -> int:
    output_folder(args.out)
    return fuzz.command(args, " ".join(["platoon-opt", *args.argv]), main)


def cmd_allocators(args: argparse.Namespace) -> int:
    if args.name:
        registered(args.name)  # an unknown name is an error, with --markdown too
    if args.markdown:
        print(catalog.markdown(), end="")
    elif args.name:
        print(catalog.describe(args.name))
    else:
        print(catalog.summary())
        print("\nplatoon-opt allocators NAME lists one allocator's options.")
    return 0


def _run_options(parser: argparse.ArgumentParser) -> None:
    """The options of every command that runs closed loops: ``--no-figures`` and ``--strict``."""
    parser.add_argument(
        "--no-figures", action="store_true", help="write no figures (the slow part of a short run)"
    )
    parser.add_argument(
        "--strict",
        action="store_true",
        help="stop at the first step whose allocation fails or falls back: one line naming the allocator, "
        f"scenario and seed, exit status {ALLOCATION_FAILED} (default: carry on with the fallback)",
    )


def _study_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--solvers",
        nargs="+",
        metavar="CONFIG",
        help="configurations, the first is the baseline: m=M (the paper's iteration), NAME, "
        "NAME:key=value,... or all (default: m=0..8 and every registered allocator)",
    )
    parser.add_argument("--duration", type=seconds, help="override each scenario's duration (s)")
    parser.add_argument("--workers", type=integer(1), help="worker processes (default: one per CPU)")
    parser.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (needs platoon-opt[dask])"
    )
    parser.add_argument("--fresh", action="store_true", help="recompute runs finished by an earlier call")
    _run_options(parser)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="platoon-opt", description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"platoon-opt {platoon_opt.__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    sim = commands.add_parser(
        "simulate",
        help="run one scenario under one allocator",
        description="Run one scenario under one allocator; write metrics.json, timeseries.csv and figures.",
    )
    sim.add_argument("scenario", help="a scenario file, or the name of a shipped one (paper_obstacles, ...)")
    sim.add_argument("--solver", default="iterative", help="allocator name (default: iterative)")
    sim.add_argument("--iterations", type=integer(0), help="the paper's m for --solver iterative")
    sim.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="allocator option, repeatable (e.g. --option rho=100); platoon-opt allocators NAME lists them",
    )
    sim.add_argument("--seed", type=SEED, default=0, help="scenario seed, an integer >= 0 (default 0)")
    sim.add_argument("--duration", type=seconds, help="override the scenario's duration (s)")
    sim.add_argument(
        "--out", default=str(RESULTS / "simulate"), help=f"output folder (default {RESULTS}/simulate)"
    )
    _run_options(sim)
    sim.set_defaults(run=cmd_simulate)
    rep = commands.add_parser(
        "reproduce",
        help="the paper's tables and figures: every allocator, many seeds, the ablation",
        description="Run both paper scenarios under m = 0..8 and every registered allocator (but the "
        "slow nmpc and the casadi-qp and dual cross-checks of qp) over many seeds, plus the ablation of "
        "the modelling choices; write report.md, results.csv, results.json and figures/. "
        "Resumable: rerun after an interruption to finish.",
    )
    rep.add_argument(
        "--out", help=f"output folder (default {RESULTS}/reproduce, or {RESULTS}/quick with --quick)"
    )
    rep.add_argument(
        "--seeds",
        type=COUNT,
        help=f"seeds per configuration (default {DEFAULT.seeds}; --quick: {QUICK.seeds})",
    )
    rep.add_argument(
        "--ablation-seeds",
        type=integer(0, 1_000_000),
        help=f"ablation seeds (default {DEFAULT.ablation_seeds}; --quick: {QUICK.ablation_seeds}; 0: none)",
    )
    rep.add_argument(
        "--quick", action="store_true", help="2 seeds of 8 s: a check of the pipeline, not a result"
    )
    rep.add_argument(
        "--check-seeds",
        type=integer(0, 1_000_000),
        help="seeds on which the convex programs, solved by the compiled dual, are solved again by "
        f"Clarabel on the host and must agree (default {DEFAULT.check_seeds}; --quick: "
        f"{QUICK.check_seeds}; 0: none)",
    )
    rep.add_argument(
        "--battery",
        action="store_true",
        help="every shipped scenario (the paper's and the battery beyond them), no ablation; "
        f"output by default in {RESULTS}/battery",
    )
    _study_options(rep)
    rep.set_defaults(run=cmd_reproduce)
    cmp = commands.add_parser(
        "compare",
        help="compare allocator configurations on scenario files over many seeds",
        description="Run every configuration on every scenario and seed; write report.md, "
        "results.csv, results.json and figures/. Resumable.",
    )
    cmp.add_argument("scenario", nargs="+", help="scenario files, or names of shipped ones")
    cmp.add_argument("--seeds", type=COUNT, default=10, help="seeds per configuration (default 10)")
    cmp.add_argument(
        "--first-seed", type=SEED, default=0, help="the first seed (default 0; a later one gives fresh seeds)"
    )
    cmp.add_argument(
        "--out", default=str(RESULTS / "compare"), help=f"output folder (default {RESULTS}/compare)"
    )
    _study_options(cmp)
    cmp.set_defaults(run=cmd_compare)
    ben = commands.add_parser(
        "bench",
        help="speed and scale of the allocators and of the control step",
        description="Time every allocator from 8 to 32,768 units (the dual to 100,000), the whole "
        "control step, n = 8 against Clarabel's bare solve, and the closed loop; write bench.json, "
        "bench.md and bench.png. Takes about 50 minutes (--quick: two).",
    )
    ben.add_argument("--out", default=str(RESULTS / "bench"), help=f"output folder (default {RESULTS}/bench)")
    ben.add_argument("--sizes", type=SIZE, nargs="+", help="problem sizes (default 8 64 512 4096 32768)")
    ben.add_argument("--quick", action="store_true", help="n = 8, 64, 512 and short closed loops (~1 min)")
    ben.add_argument("--threads", type=integer(1), help="threads of JAX's pool (default: one per core)")
    ben.add_argument("--closed-loop-only", action="store_true", help="the closed-loop part alone")
    ben.set_defaults(run=cmd_bench)
    sok = commands.add_parser(
        "soak",
        help="every allocator on many random problems, counting what goes wrong",
        description="Solve seeded random allocation problems (a fifth of them degenerate) with every "
        "allocator, in chunks of 1,000, counting exceptions, non-finite output, limit violations, "
        "fallbacks, statuses and times; write soak.json and soak.md. Resumable: the same command "
        "keeps the chunks an earlier run finished.",
    )
    soak.add_arguments(sok, RESULTS / "soak")
    sok.set_defaults(run=cmd_soak)
    fz = commands.add_parser(
        "fuzz",
        help="mutated scenario files and argument lists through this command line, judging each exit",
        description=fuzz.__doc__.split("\n\n")[0] if fuzz.__doc__ else None,
    )
    fuzz.add_arguments(fz, RESULTS / "fuzz")
    fz.set_defaults(run=cmd_fuzz)
    cat = commands.add_parser(
        "allocators", help="list the allocators, or one allocator's options", description=catalog.__doc__
    )
    cat.add_argument("name", nargs="?", help="an allocator: list its options")
    cat.add_argument(
        "--markdown", action="store_true", help="every allocator and option as docs/allocators.md"
    )
    cat.set_defaults(run=cmd_allocators)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``platoon-opt`` with ``argv`` (default ``sys.argv[1:]``) and return its exit status:
    0, 2 for bad input (one line ``platoon-opt: error: ...`` on stderr), 3 for a ``--strict`` run
    whose allocation failed, 130 when interrupted, 143 after SIGTERM, 141 when stdout was closed
    (``| head``); ``--help`` and ``--version`` return 0."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as done:  # --help, --version: printed, nothing else to do
        return done.code if isinstance(done.code, int) else 0
    except UsageError as error:
        return bad_input(error)
    args.argv = argv
    enable_compilation_cache()
    try:
        with terminate_on_sigterm():
            return args.run(args)
    except AllocationError as error:
        return allocation_failed(error)
    except PlatoonOptError as error:
        return bad_input(error)
    except KeyboardInterrupt as stop:
        what, status = stopped(stop)
        print(f"\nplatoon-opt: {what}", file=sys.stderr)
        return status
    except BrokenPipeError:  # stdout closed by its reader (``| head``): nobody left to tell
        with contextlib.suppress(OSError, ValueError):  # no second error when Python flushes at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return BROKEN_PIPE


if __name__ == "__main__":
    sys.exit(main())
