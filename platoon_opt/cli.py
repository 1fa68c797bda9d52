"""The ``platoon-opt`` command."""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path
from typing import Any

from platoon_opt.metrics import integrated_errors
from platoon_opt.output import write_json, write_timeseries
from platoon_opt.scenarios import ScenarioError, load_scenario
from platoon_opt.simulation import simulate


class UsageError(ValueError):
    """Bad command-line input: printed as one line, exit status 2."""


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
    from platoon_opt.plots import plot_errors, plot_trajectories
    from solvers import get_allocator

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
    trajectory = simulate(
        scenario, allocator, seed=args.seed, duration=args.duration, progress=_progress(scenario.name)
    )
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


def build_parser() -> argparse.ArgumentParser:
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
    sim.set_defaults(run=cmd_simulate)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (UsageError, ScenarioError) as error:
        print(f"platoon-opt: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
