"""Held units with barriers: does a second solve, with them anchored at their safe velocity, win
back the task the hand-out loses? (experiments/safety.md, "Held units".)

The task-exact program with barriers hands a unit near an obstacle its safe achievable part c_i
instead of a_i (``solvers/safety.safe_handout``); the program chose the other units' a for the
held units' a, so J v = u is lost by sum_i J_i (c_i - a_i). This probe solves once more, with the
held units anchored (the precedence rule's anchor) at c_i, so that the others make up for them,
and compares the integrated errors over seeds. A probe, not the product: the allocator is wrapped.

    python experiments/held_units.py paper_obstacles --seeds 100-119 [--workers 2]
"""

from __future__ import annotations

import argparse
import dataclasses
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from platoon_opt.metrics import integrated_errors
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.safety import clear_of_obstacles, keeps_barriers

# name: (anchor weight, second solve)
VARIANTS = {
    "one solve, anchor 1 (shipped)": (1.0, False),
    "second solve, anchor 1": (1.0, True),
    "one solve, anchor 10": (10.0, False),
    "second solve, anchor 10": (10.0, True),
}
ERRORS = ("mean_position", "var_x", "var_y")


class HeldAnchored:
    """The dual's task-exact program with barriers, solved again with its held units anchored."""

    def __init__(self, anchor_weight: float, second: bool) -> None:
        self.inner = get_allocator(
            "dual", reading="task-exact", safety="barrier", anchor_weight=anchor_weight
        )
        self.second = second

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def allocate(self, problem):
        first = self.inner.allocate(problem)
        if not self.second or not first.info.get("held_units"):
            return first
        params = self.inner.safety_for(problem)
        safe = problem.safe_sets(params, speed="polygon")
        wanted, achievable = first.info["task_exact_velocity"], np.asarray(first.info["achievable"])
        held = ~(clear_of_obstacles(problem, params) & keeps_barriers(problem, safe, wanted))
        anchored = dataclasses.replace(
            problem,
            nominal=np.where(held[:, None], achievable, problem.nominal),
            exempt=np.asarray(problem.exempt) | held,
        )
        return self.inner.allocate(anchored)


def run(job: tuple[str, int, str]) -> tuple[str, int, dict[str, float]]:
    scenario, seed, variant = job
    trajectory = simulate(
        load_scenario(scenario), HeldAnchored(*VARIANTS[variant]), seed=seed, compiled=False
    )
    errors = integrated_errors(trajectory)
    obstacles = trajectory.obstacles
    clearance = (
        np.hypot(
            trajectory.x[..., None] - obstacles.centers[:, 0],
            trajectory.y[..., None] - obstacles.centers[:, 1],
        )
        - obstacles.radii
    )
    errors["min_clearance"] = float(clearance.min()) if obstacles.radii.size else float("inf")
    return variant, seed, errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--seeds", default="0-19", help="first-last")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    first, last = (int(part) for part in args.seeds.split("-"))
    jobs = [(args.scenario, seed, variant) for seed in range(first, last + 1) for variant in VARIANTS]
    results: dict[str, dict[int, dict[str, float]]] = {variant: {} for variant in VARIANTS}
    with ProcessPoolExecutor(args.workers) as pool:
        for variant, seed, errors in pool.map(run, jobs):
            results[variant][seed] = errors
    seeds = sorted(results[next(iter(VARIANTS))])
    base = results[next(iter(VARIANTS))]
    print(
        f"{args.scenario}, seeds {first}-{last}: mean over seeds; ratio to the shipped handout with a 95 % "
        "paired bootstrap interval; runaway = seeds with mean_position > 1 m s"
    )
    print("| variant | " + " | ".join(ERRORS) + " | runaway | min clearance |")
    print("|---|" + "---|" * (len(ERRORS) + 2))
    rng = np.random.default_rng(0)
    draws = rng.integers(0, len(seeds), size=(2000, len(seeds)))
    for variant, per_seed in results.items():
        cells = []
        for error in ERRORS:
            mine = np.array([per_seed[s][error] for s in seeds])
            theirs = np.array([base[s][error] for s in seeds])
            ratios = mine[draws].mean(axis=1) / theirs[draws].mean(axis=1)
            low, high = np.percentile(ratios, [2.5, 97.5])
            cells.append(f"{mine.mean():.3g}; x{mine.mean() / theirs.mean():.2f} [{low:.2f}, {high:.2f}]")
        runaway = sum(per_seed[s]["mean_position"] > 1.0 for s in seeds)
        clearance = min(per_seed[s]["min_clearance"] for s in seeds)
        print(f"| {variant} | " + " | ".join(cells) + f" | {runaway} | {clearance:.3f} |")


if __name__ == "__main__":
    main()
