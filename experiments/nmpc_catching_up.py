"""Why does `nmpc` catch up more slowly than the paper's iteration in `units_50`?

Runs the first seconds of a scenario (default: `units_50`, seed 0, 4 s) under the given
configurations and prints, for each, the integrated mean-position error (m s) in windows of one
second, the variances' integrated error (m^2 s), the share of unit-steps in reverse, the CPU time
and the fallback steps; with ``--trace``, every 0.1 s of the first two configurations side by side:
the mean's distance to the target, its velocity toward the target and the units in reverse.
What it found: experiments/battery.md, section "`nmpc` at n = 50: the catching up".

    python experiments/nmpc_catching_up.py m=8 m=0 nmpc nmpc:intervals=20
    python experiments/nmpc_catching_up.py --trace m=8 nmpc
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from platoon_opt.metrics import sample_trajectory
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.study.config import parse_config
from platoon_opt.trajectory import Trajectory


def run(scenario: str, config: str, seed: int, duration: float) -> tuple[Trajectory, float]:
    """One run and its CPU time (s)."""
    start = time.process_time()
    allocator = parse_config(config).build(get_allocator)
    trajectory = simulate(load_scenario(scenario), allocator, seed=seed, duration=duration)
    return trajectory, time.process_time() - start


def distance(trajectory: Trajectory) -> np.ndarray:
    """The platoon mean's distance to the target at each instant (m)."""
    return sample_trajectory(trajectory).mean_distance


def progress(trajectory: Trajectory, k: int) -> float:
    """The platoon mean's velocity toward the target over step k (m/s)."""
    x, y = trajectory.x, trajectory.y
    velocity = np.array([x[k + 1] - x[k], y[k + 1] - y[k]]).mean(axis=1) / trajectory.dt
    error = trajectory.target[k] - np.array([trajectory.x[k].mean(), trajectory.y[k].mean()])
    return float(velocity @ error / np.linalg.norm(error))


def summary(config: str, trajectory: Trajectory, cpu: float) -> str:
    d, t, dt = distance(trajectory)[:-1], trajectory.t[:-1], trajectory.dt
    windows = " ".join(
        f"{d[(t >= a - 1e-9) & (t < a + 1 - 1e-9)].sum() * dt:.5f}" for a in range(int(round(t[-1] + dt)))
    )
    variance = sample_trajectory(trajectory).errors[:-1].sum() * dt
    reverse = float((trajectory.gear[:-1] < 0).mean())
    fallbacks = int(trajectory.fell_back.sum())
    return (
        f"{config:24s} mean error by second {windows} | total {d.sum() * dt:.5f} m s, variances"
        f" {variance:.4f} m^2 s, in reverse {reverse:.3f}, cpu {cpu:.0f} s, fallbacks {fallbacks}"
    )


def instant(label: str, trajectory: Trajectory, k: int) -> str:
    """The mean's distance, its velocity toward the target and the units in reverse at step k."""
    reverse = int((trajectory.gear[k] < 0).sum())
    return f"{label} {distance(trajectory)[k]:.4f} m, {progress(trajectory, k):.4f} m/s, {reverse} in reverse"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("configs", nargs="+")
    parser.add_argument("--scenario", default="units_50")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=4.0)
    parser.add_argument("--trace", action="store_true")
    args = parser.parse_args()
    runs = {config: run(args.scenario, config, args.seed, args.duration) for config in args.configs}
    for config, (trajectory, cpu) in runs.items():
        print(summary(config, trajectory, cpu), flush=True)
    if args.trace:
        (first, (a, _)), (second, (b, _)) = list(runs.items())[:2]
        for k in range(0, len(a.t) - 1, 10):
            print(f"t = {a.t[k]:.1f} s: {instant(first, a, k)}; {instant(second, b, k)}")


if __name__ == "__main__":
    main()
