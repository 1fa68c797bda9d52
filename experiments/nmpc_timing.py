"""Compute time of the receding-horizon allocator per control step (one solve), 8 units.

Runs the first ``--duration`` seconds of each paper scenario in closed loop and reports, over
the steps that solved (``Trajectory.solved``: not the steps handing the stored plan, nor the
first, which also builds the solver), the wall time and the process CPU time per solve
(median, p95, max), the SQP iterations, and the statuses; and, for comparison, the wall time
per step over every step (median, p95), plan steps included: what a run's
``solve_time_median`` reports. CPU time is what the solve costs on an idle core; the wall time
includes waiting for the CPU when the machine is shared.

    python experiments/nmpc_timing.py --duration 10 --option intervals=10 --out FILE

With ``--out`` the lines are appended to FILE (markdown) under a header naming the options,
the machine (``platoon_opt.study.machine``) and the load average before the runs.
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from platoon_opt import load_scenario, simulate  # noqa: E402
from platoon_opt.solvers import get_allocator  # noqa: E402
from platoon_opt.study.machine import machine  # noqa: E402


class CpuTimed:
    """Wraps an allocator, recording the process CPU time of each call."""

    def __init__(self, allocator):
        self.allocator, self.cpu = allocator, []
        self.name = allocator.name

    def allocate(self, problem):
        start = time.process_time()
        result = self.allocator.allocate(problem)
        self.cpu.append(time.process_time() - start)
        return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--out", type=Path, help="append the results to this markdown file")
    args = parser.parse_args()
    options = {k: ast.literal_eval(v) for k, v in (pair.split("=", 1) for pair in args.option)}
    lines = [
        f"## `nmpc` {options or '(defaults)'}, seed {args.seed}, first {args.duration:g} s",
        "",
        f"{time.strftime('%Y-%m-%d %H:%M')}; load average before: {os.getloadavg()[0]:.2f}; "
        f"machine: {machine()}",
        "",
    ]
    for name in ("paper_no_obstacles", "paper_obstacles"):
        allocator = CpuTimed(get_allocator("nmpc", **options))
        trajectory = simulate(load_scenario(name), allocator, seed=args.seed, duration=args.duration)
        names, counts = np.unique(trajectory.status.astype(str), return_counts=True)
        statuses = {str(status): int(count) for status, count in zip(names, counts)}
        # Solves only, and not the first: it also builds the solver.
        solves = np.array(trajectory.solved, dtype=bool)
        solves[0] = False
        solved = np.flatnonzero(solves)
        wall_ms, cpu_ms = trajectory.solve_time[solved] * 1e3, np.array(allocator.cpu)[solved] * 1e3
        step_ms = trajectory.solve_time * 1e3
        iterations = trajectory.iterations[solved]
        line = (
            f"{name}: {allocator.name}, {len(solved)} solves; wall ms median {np.median(wall_ms):.1f}, "
            f"p95 {np.percentile(wall_ms, 95):.1f}, max {wall_ms.max():.1f}; CPU ms median "
            f"{np.median(cpu_ms):.1f}, p95 {np.percentile(cpu_ms, 95):.1f}, max {cpu_ms.max():.1f}; "
            f"per step (all {trajectory.steps}) wall ms median {np.median(step_ms):.3g}, "
            f"p95 {np.percentile(step_ms, 95):.3g}; "
            f"iterations median {np.median(iterations):.0f}; statuses {statuses}"
        )
        print(line, flush=True)
        lines.append(f"- {line}")
    if args.out is not None:
        with args.out.open("a") as out:
            out.write("\n".join(lines) + "\n\n")


if __name__ == "__main__":
    main()
