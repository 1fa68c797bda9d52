"""How often does each offered QP backend answer the convex programs itself?

Runs ``qp`` and ``qp-projection`` with every backend this install offers
(``backends.known_backends``: the native OSQP and Clarabel, qpsolvers' solvers, CasADi's conic
plugins) on the first second of three shipped scenarios (seed 1, 100 steps each), and counts the
steps on which the backend's answer was refused or it failed, so that the allocator fell back
(to Clarabel, or OSQP after Clarabel), with the most common reasons. Writes
experiments/results/backends.json and prints a table; docs/programs.md, section 5, quotes it.

    python experiments/backends.py
"""

from __future__ import annotations

import collections
import json
import warnings
from pathlib import Path

import numpy as np

from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex.backends import known_backends

SCENARIOS = ("paper_no_obstacles", "paper_obstacles", "field_dense")
ALLOCATORS = ("qp", "qp-projection")
OUT = Path(__file__).with_name("results") / "backends.json"


def fallbacks(scenario: str, allocator: str, backend: str) -> dict[str, object]:
    """Steps that fell back in one second of ``scenario``, and the two most common reasons."""
    chosen = get_allocator(allocator, backend=backend)
    trajectory = simulate(load_scenario(scenario), chosen, seed=1, duration=1.0)
    reasons = collections.Counter(str(status) for status in trajectory.status if status != "optimal")
    return {
        "steps": len(trajectory.fell_back),
        "fell_back": int(np.count_nonzero(trajectory.fell_back)),
        "reasons": reasons.most_common(2),
    }


def main() -> None:
    warnings.simplefilter("ignore")  # qpsolvers' and CasADi's notices
    results = {}
    print("| backend | " + " | ".join(f"{a} on {s}" for a in ALLOCATORS for s in SCENARIOS) + " |")
    for backend in known_backends():
        row = []
        for allocator in ALLOCATORS:
            for scenario in SCENARIOS:
                counts = fallbacks(scenario, allocator, backend)
                results[f"{backend}|{allocator}|{scenario}"] = counts
                row.append(f"{counts['fell_back']}/{counts['steps']}")
        print(f"| `{backend}` | " + " | ".join(row) + " |", flush=True)
    OUT.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
