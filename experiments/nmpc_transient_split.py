"""Where in time ``nmpc`` loses a scenario's errors: each error integrated over windows of the run,
for m = 0, the rate-aware ``cone-projection`` and ``nmpc`` at its defaults (and further m's if
asked). By default ``curved_field_16``'s var_y (+127 % against m = 0 in the 20-seed battery),
seeds 0 and 1 (about 70 s of CPU per ``nmpc`` run). Writes
experiments/results/nmpc_transient_split[_SCENARIO].json; what it found: experiments/battery.md,
sections "`nmpc`'s var_y at n = 16: the catching up" and "`paper_covariance`'s variances, split
over time".

    python experiments/nmpc_transient_split.py
    python experiments/nmpc_transient_split.py paper_covariance --seeds 0 1 --m 1 5
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from platoon_opt.metrics import MEANS, sample_trajectory
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator

SCENARIO = "curved_field_16"
CONFIGS = {
    "m=0": ("iterative", {"max_iterations": 0}),
    "cone-projection:rate_aware": ("cone-projection", {"backend": "dual", "rate_aware": True}),
    "nmpc": ("nmpc", {}),
}
RESULTS = Path(__file__).with_name("results")


def split_run(
    name: str, family: str, options: dict, seed: int, edges: list[float]
) -> tuple[list[list[float]], list[str]]:
    """Per window: the mean-position error (m s), var_x and var_y errors (m^2 s), gear flips, and
    the errors of further task components (m^2 s); and the further components' names."""
    scenario = load_scenario(name)
    trajectory = simulate(scenario, get_allocator(family, **options), seed=seed)
    samples = sample_trajectory(trajectory)
    t = trajectory.t[:-1]
    variances = np.abs(samples.errors[:-1])
    flips = np.abs(np.diff(trajectory.gear, axis=0)).sum(axis=1) / 2
    further = [task for task in trajectory.task_names if task not in MEANS][2:]
    rows = []
    for start, end in zip(edges, edges[1:]):
        inside = (t >= start) & (t < end)
        mean = samples.mean_distance[:-1][inside].sum() * scenario.dt
        components = [float(v) for v in variances[inside].sum(axis=0) * scenario.dt]
        rows.append([float(mean), *components[:2], float(flips[inside].sum()), *components[2:]])
    return rows, further


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenario", nargs="?", default=SCENARIO)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--m", type=int, nargs="*", default=[], help="further sweeps of the iteration")
    args = parser.parse_args()
    configs = {**CONFIGS, **{f"m={m}": ("iterative", {"max_iterations": m}) for m in args.m}}
    edges = [0.0, 2.0, 4.0, 8.0, 16.0, 32.0, load_scenario(args.scenario).duration + 1.0]
    results = {}
    for seed in args.seeds:
        for name, (family, options) in configs.items():
            start = time.process_time()
            rows, further = split_run(args.scenario, family, options, seed, edges)
            results[f"{name}|{seed}"] = rows
            print(f"seed {seed} {name} ({time.process_time() - start:.0f} s of CPU)", flush=True)
            for (low, high), (mean, var_x, var_y, flips, *more) in zip(zip(edges, edges[1:]), rows):
                window = f"{low:4.0f}-{high:4.0f} s"
                errors = f"mean {mean:.5f}  var_x {var_x:.5f}  var_y {var_y:.5f}"
                errors += "".join(f"  {task} {value:.5f}" for task, value in zip(further, more))
                print(f"  {window}  {errors}  flips {flips:.0f}")
    suffix = "" if args.scenario == SCENARIO else f"_{args.scenario}"
    out = RESULTS / f"nmpc_transient_split{suffix}.json"
    out.write_text(json.dumps({"edges": edges, "runs": results}, indent=1))


if __name__ == "__main__":
    main()
