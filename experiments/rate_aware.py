"""Does the rate-aware steering sector help the task-exact programs in closed loop?

The convex programs hand each unit a velocity inside its steering sector over the whole steering
range (``rate_aware=False``, their default) or inside the part its steering reaches within one
step (``rate_aware=True``). This runs both readings of ``qp-projection`` and ``cone-projection``
(through the compiled dual) beside the paper's iteration at m = 1 and m = 4 on seeds that no
reported study uses (100-107), on every shipped scenario, and writes the mean of each error per
scenario and configuration to experiments/results/rate_aware.json. What it found:
experiments/battery.md.

    python experiments/rate_aware.py [scenario ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from platoon_opt.scenarios import SCENARIO_DIR, load_scenario
from platoon_opt.simulation import simulate_batch
from platoon_opt.solvers import get_allocator

SEEDS = list(range(100, 108))
ERRORS = ("mean_position", "mean_position_after_transient", "var_x", "var_y", "gear_flips")
CONFIGS = {
    "m=1": ("iterative", {"max_iterations": 1}),
    "m=4": ("iterative", {"max_iterations": 4}),
    "qp-projection": ("qp-projection", {"backend": "dual"}),
    "qp-projection:rate_aware=True": ("qp-projection", {"backend": "dual", "rate_aware": True}),
    "cone-projection": ("cone-projection", {"backend": "dual"}),
    "cone-projection:rate_aware=True": ("cone-projection", {"backend": "dual", "rate_aware": True}),
}
OUT = Path(__file__).resolve().parent / "results" / "rate_aware.json"


def main(names: list[str]) -> None:
    results = json.loads(OUT.read_text()) if OUT.exists() else {}
    for name in names or sorted(path.stem for path in SCENARIO_DIR.glob("*.toml")):
        scenario, rows = load_scenario(name), {}
        for label, (allocator, options) in CONFIGS.items():
            scores = simulate_batch(scenario, get_allocator(allocator, **options), seeds=SEEDS)
            rows[label] = {error: float(np.mean([s[error] for s in scores])) for error in ERRORS}
        results[name] = {"seeds": SEEDS, "means": rows}
        OUT.write_text(json.dumps(results, indent=1, sort_keys=True))
        base = rows["m=1"]
        for label, row in rows.items():
            changes = " ".join(f"{e}={row[e]:.4g} ({row[e] / base[e] - 1:+.0%})" for e in ERRORS if base[e])
            print(f"{name} {label}: {changes}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
