"""Does the rate-aware steering sector help the task-exact programs in closed loop?

The convex programs hand each unit a velocity inside its steering sector over the whole steering
range (``rate_aware=False``, their default) or inside the part its steering reaches within one
step, measured from the nominal velocities as the units drive them (``rate_aware=True``,
docs/programs.md section 3). This runs both readings of ``qp-projection`` and ``cone-projection``
(through the compiled dual) beside the paper's iteration at m = 1 and m = 4 on seeds that no
reported study uses (100-107), on every shipped scenario, and writes the mean of each error per
scenario and configuration to experiments/results/rate_aware.json. What it found:
experiments/battery.md.

    python experiments/rate_aware.py [scenario ...]

Two readings between the two, tried and not kept, replace the dual's sets for the run (no option
of the library has them): ``--steps H`` narrows each sector to what the steering reaches within
H steps; ``--within F`` narrows the sector of a unit only where its nominal direction (clipped to
the steering range) lies within F one-step reaches of its steering. They print the change of
each error of the rate-aware configurations against the default reading and the better of
m = 1 and m = 4 in the json (run the script without options first).

    python experiments/rate_aware.py --steps 3 figure_eight paper_obstacles
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from platoon_opt.limits import AchievableSets, inner_projection
from platoon_opt.scenarios import SCENARIO_DIR, load_scenario
from platoon_opt.simulation import simulate_batch
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.dual import kernel
from platoon_opt.solvers.dual.sets import make_sets
from platoon_opt.vehicle import wrap_angle

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


def between(steps: float, within: float) -> Callable[..., Any]:
    """The dual's sets with the sector of a rate-aware program narrowed to ``steps`` one-step
    reaches, only for the units whose nominal direction lies within ``within`` reaches."""

    def dual_sets(static: Any, problem: Any, safe: Any) -> tuple[Any, Any]:
        """``kernel.dual_sets`` without barriers (``safe`` is None here)."""
        limits, state = problem.limits, problem.state
        full = AchievableSets.for_gear(state, problem.gear, limits)
        model = full
        if static.rate_aware:
            reach = limits.max_steering_rate * problem.dt
            nominal = problem.nominal
            wanted = jnp.clip(
                wrap_angle(jnp.arctan2(nominal[:, 1], nominal[:, 0]) - full.axis),
                -limits.max_steering,
                limits.max_steering,
            )
            near = (jnp.abs(wanted - state.alpha) <= within * reach) | ~jnp.any(nominal != 0, axis=1)
            lower = jnp.where(near, jnp.maximum(full.lower, state.alpha - steps * reach), full.lower)
            upper = jnp.where(near, jnp.minimum(full.upper, state.alpha + steps * reach), full.upper)
            model = AchievableSets(full.axis, lower, upper, full.max_speed)
        sets = make_sets(model, static.speed, static.sides)
        return sets, inner_projection(problem.nominal, model, static.speed, static.sides)

    return dual_sets


def compare(names: list[str], steps: float, within: float) -> None:
    """The rate-aware configurations under ``between(steps, within)`` against the json's."""
    kernel.dual_sets = between(steps, within)
    reference = json.loads(OUT.read_text())
    for name in names:
        scenario, means = load_scenario(name), reference[name]["means"]
        for label in ("qp-projection", "cone-projection"):
            allocator, options = CONFIGS[f"{label}:rate_aware=True"]
            scores = simulate_batch(scenario, get_allocator(allocator, **options), seeds=SEEDS)
            row = {error: float(np.mean([s[error] for s in scores])) for error in ERRORS[:4]}
            best = {error: min(means["m=1"][error], means["m=4"][error]) for error in row}
            print(
                f"steps {steps} within {within} {name} {label}: against the default "
                + " ".join(f"{row[e] / means[label][e] - 1:+.0%}" for e in row)
                + "; against the better of m=1, m=4 "
                + " ".join(f"{row[e] / best[e] - 1:+.0%}" for e in row),
                flush=True,
            )


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
    parser = argparse.ArgumentParser()
    parser.add_argument("scenarios", nargs="*")
    parser.add_argument("--steps", type=float, default=None)
    parser.add_argument("--within", type=float, default=None)
    args = parser.parse_args()
    if args.steps is None and args.within is None:
        main(args.scenarios)
    else:
        steps = 1.0 if args.steps is None else args.steps
        compare(args.scenarios, steps, float("inf") if args.within is None else args.within)
