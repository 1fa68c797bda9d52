"""The closed-loop part: the paper scenario (no obstacles) simulated under each allocator of
``cases.entries`` (and the paper's iteration, m = 4): simulated seconds per wall second.

Contract: one record of kind "closed_loop" per allocator.
"""

from __future__ import annotations

import numpy as np

from platoon_opt import load_scenario, simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.study.bench import cases
from platoon_opt.study.bench.timing import Records, clock, since


def run_closed_loop(records: Records, duration: float) -> None:
    """Simulated seconds per wall second of the paper scenario (no obstacles) per allocator."""
    scenario = load_scenario(cases.SCENARIO)
    configs = [(entry.label, entry.build) for entry in cases.entries() if entry.label != "qp-projection osqp"]
    configs.append(("iterative m=4", lambda: get_allocator("iterative", max_iterations=4)))
    for label, build in configs:
        allocator = build()
        start = clock()
        trajectory = simulate(scenario, allocator, duration=duration)
        wall, cpu = since(start)
        record = {
            "kind": "closed_loop",
            "allocator": label,
            "scenario": scenario.name,
            "n": scenario.n,
            "simulated": duration,
            "wall": wall,
            "cpu": cpu,
            "speed": duration / wall,
            "cpu_speed": duration / cpu,
            "allocation_median": float(np.median(trajectory.solve_time)),
            "fell_back": int(np.count_nonzero(trajectory.fell_back)),
        }
        records.add(**record)
        records.log(f"  {label:<26} {record['speed']:6.1f} x real time (CPU: {record['cpu_speed']:.1f} x)")
