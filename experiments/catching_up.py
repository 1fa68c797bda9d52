"""When is a platoon catching up? The steps on which ``gears="catching-up"`` poses the nearer gear.

``AllocationProblem.catching_up`` says a platoon is catching up when the task velocity's feedback
part, spread over the units at least norm, moves their centroid faster than the top speed. This
runs each shipped scenario under the rate-aware ``qp-projection`` in that gear choice (the dual, in
the host loop, so that every step's problem can be looked at) and prints, per scenario and seed,
the share of steps on which the platoon was catching up, the first and last such time and the
number of separate stretches. Writes experiments/results/catching_up.json; what it found:
experiments/battery.md, section "The nearer gear while the platoon catches up".

    python experiments/catching_up.py [scenario ...] [--seeds 100 101]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.study.battery import BATTERY

OUT = Path(__file__).with_name("results") / "catching_up.json"


class Recording:
    """The allocator, with whether each step's platoon was catching up (``flags``)."""

    def __init__(self) -> None:
        self.inner = get_allocator("qp-projection", backend="dual", rate_aware=True, gears="catching-up")
        self.flags: list[bool] = []

    def allocate(self, problem):
        self.flags.append(bool(problem.catching_up()))
        return self.inner.allocate(problem)

    def __getattr__(self, name: str):
        return getattr(self.inner, name)


def stretches(flags: np.ndarray) -> int:
    """The number of runs of consecutive True."""
    return int(np.sum(flags[1:] & ~flags[:-1]) + (flags[0] if flags.size else 0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="*", default=list(BATTERY))
    parser.add_argument("--seeds", nargs="+", type=int, default=[100])
    args = parser.parse_args()
    results = {}
    for name in args.scenarios:
        scenario = load_scenario(name)
        for seed in args.seeds:
            allocator = Recording()
            simulate(scenario, allocator, seed=seed, compiled=False)
            flags = np.array(allocator.flags)
            times = np.flatnonzero(flags) * scenario.dt
            row = {
                "share": float(flags.mean()),
                "first": float(times[0]) if times.size else None,
                "last": float(times[-1]) if times.size else None,
                "stretches": stretches(flags),
                "steps": int(flags.size),
            }
            results[f"{name}/seed-{seed}"] = row
            span = f"{row['first']:.2f}-{row['last']:.2f} s" if times.size else "never"
            share = f"{100 * row['share']:5.1f} % of steps"
            print(f"{name:28s} seed {seed}: {share}, {span}, {row['stretches']} stretches")
    OUT.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
