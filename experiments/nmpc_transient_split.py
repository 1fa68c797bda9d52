"""Where in time ``nmpc`` loses ``curved_field_16``'s var_y (+127 % against m = 0 in the 20-seed
battery): each error integrated over windows of the run, for m = 0, the rate-aware
``cone-projection`` and ``nmpc`` at its defaults, seeds 0 and 1 (about 70 s of CPU per ``nmpc``
run). Writes experiments/results/nmpc_transient_split.json; what it found: experiments/battery.md,
section "`nmpc`'s var_y at n = 16: the catching up".

    python experiments/nmpc_transient_split.py
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from platoon_opt.metrics import sample_trajectory
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator

SCENARIO = "curved_field_16"
SEEDS = (0, 1)
CONFIGS = {
    "m=0": ("iterative", {"max_iterations": 0}),
    "cone-projection:rate_aware": ("cone-projection", {"backend": "dual", "rate_aware": True}),
    "nmpc": ("nmpc", {}),
}
OUT = Path(__file__).with_name("results") / "nmpc_transient_split.json"


def split_run(family: str, options: dict, seed: int, edges: list[float]) -> list[list[float]]:
    """Per window: the mean-position error (m s), var_x and var_y errors (m^2 s), gear flips."""
    scenario = load_scenario(SCENARIO)
    trajectory = simulate(scenario, get_allocator(family, **options), seed=seed)
    samples = sample_trajectory(trajectory)
    t = trajectory.t[:-1]
    variances = np.abs(samples.errors[:-1])
    flips = np.abs(np.diff(trajectory.gear, axis=0)).sum(axis=1) / 2
    rows = []
    for start, end in zip(edges, edges[1:]):
        inside = (t >= start) & (t < end)
        mean = samples.mean_distance[:-1][inside].sum() * scenario.dt
        var_x, var_y = variances[inside].sum(axis=0) * scenario.dt
        rows.append([float(mean), float(var_x), float(var_y), float(flips[inside].sum())])
    return rows


def main() -> None:
    edges = [0.0, 2.0, 4.0, 8.0, 16.0, 32.0, load_scenario(SCENARIO).duration + 1.0]
    results = {}
    for seed in SEEDS:
        for name, (family, options) in CONFIGS.items():
            start = time.process_time()
            rows = split_run(family, options, seed, edges)
            results[f"{name}|{seed}"] = rows
            print(f"seed {seed} {name} ({time.process_time() - start:.0f} s of CPU)", flush=True)
            for (low, high), (mean, var_x, var_y, flips) in zip(zip(edges, edges[1:]), rows):
                window = f"{low:4.0f}-{high:4.0f} s"
                print(f"  {window}  mean {mean:.5f}  var_x {var_x:.5f}  var_y {var_y:.5f}  flips {flips:.0f}")
    OUT.write_text(json.dumps({"edges": edges, "runs": results}, indent=1))


if __name__ == "__main__":
    main()
