"""Record the golden trajectories: ``python -m tests.golden.record`` (about a minute).

The closed loop of today's model (vehicles, unit controller, gear rule, task, avoidance, problem
build, allocators), kept so that a rewrite of the model (the compiled engine of the JAX issue) can
be held to it: both paper scenarios, seeds 0-2, four allocators, the first 2 s, every step's
positions, headings, steering angles and gears. ``test_golden.py`` checks the model against them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers.registry import get_allocator

FOLDER = Path(__file__).resolve().parent
SCENARIOS = ("paper_no_obstacles", "paper_obstacles")
SEEDS = (0, 1, 2)
# label -> (allocator, options)
ALLOCATORS = {
    "m=0": ("iterative", {"max_iterations": 0}),
    "m=4": ("iterative", {"max_iterations": 4}),
    "qp-projection": ("qp-projection", {}),
    "cone": ("cone", {}),
}
DURATION = 2.0
FIELDS = ("x", "y", "theta", "alpha", "gear")


def path_of(scenario: str, label: str, seed: int) -> Path:
    """The fixture file of one run."""
    return FOLDER / f"{scenario}-{label}-seed{seed}.npz"


def run(scenario: str, label: str, seed: int, compiled: bool | None = None) -> dict[str, np.ndarray]:
    """Every step's state of one run (arrays of shape (steps + 1, n)); ``compiled`` as ``simulate``."""
    name, options = ALLOCATORS[label]
    allocator = get_allocator(name, **options)
    trajectory = simulate(load_scenario(scenario), allocator, seed=seed, duration=DURATION, compiled=compiled)
    return {field: getattr(trajectory, field) for field in FIELDS}


def main() -> None:
    for scenario in SCENARIOS:
        for label in ALLOCATORS:
            for seed in SEEDS:
                np.savez_compressed(path_of(scenario, label, seed), **run(scenario, label, seed))
                print(path_of(scenario, label, seed).name)


if __name__ == "__main__":
    main()
