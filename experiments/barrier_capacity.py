"""How many barrier rows a unit holds along closed-loop runs with barriers: the capacity per unit
that a compiled builder of the safe sets (fixed shapes) would need. See barrier_capacity.md.

Runs each scenario's first 20 s in the host loop under ``qp-projection`` with barriers and
``rate_aware=True``, seeds 0 and 1, and counts each unit's non-zero barrier rows at every build
of the safe sets (a step builds them once, and again for the other gear of a blocked unit).

    python experiments/barrier_capacity.py [SCENARIO ...]   # default: every shipped scenario
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from platoon_opt import safe_sets
from platoon_opt.scenarios import SCENARIO_DIR, load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.study.executor import share_cores

OUT = Path(__file__).parent / "results" / "barrier_capacity.json"
SEEDS = (0, 1)
DURATION = 20.0


def main(names: list[str]) -> None:
    share_cores(1)
    builds: list[np.ndarray] = []
    barriers = safe_sets.barriers

    def counting(*args, **kwargs):
        rows = barriers(*args, **kwargs)
        builds.append(np.count_nonzero(np.any(rows.normals != 0, axis=2), axis=1))
        return rows

    safe_sets.barriers = counting
    allocator = get_allocator("qp-projection", safety="barrier", rate_aware=True)
    results = json.loads(OUT.read_text()) if OUT.exists() else {}
    for name in names:
        scenario = load_scenario(name)
        for seed in SEEDS:
            builds.clear()
            start = time.perf_counter()
            trajectory = simulate(scenario, allocator, seed=seed, duration=min(scenario.duration, DURATION))
            rows = np.stack(builds)
            results[f"{name}:{seed}"] = {
                "n": scenario.n,
                "obstacles": len(trajectory.obstacles.radii),
                "steps": trajectory.steps,
                "builds": rows.shape[0],
                "most_rows": int(rows.max()),
                "units_with_rows": float(np.mean(rows > 0)),
                "mean_rows": float(rows.mean()),
                "seconds": round(time.perf_counter() - start, 1),
            }
            print(name, seed, results[f"{name}:{seed}"], flush=True)
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:] or sorted(p.stem for p in SCENARIO_DIR.glob("*.toml")))
