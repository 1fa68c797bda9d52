"""Barrier constraints in the compiled engine (``safety="barrier"``): the dual's four programs
(``backend="dual"``, ``rate_aware=True``) and the paper's iteration with m = 4 through the safety
filter. See barrier_capacity.md, "The compiled engine with barriers".

* What it costs: 10 s of ``paper_obstacles`` and ``field_dense``, one platoon compiled (its
  second call: compiled once), a batch of 32 seeds (``simulate_batch``, its second call) and one
  run in the host loop.
* The same at 50 and 200 units (``units_50``, ``units_200``: the cell list), one platoon and the
  host loop.
* How often the default ``Capacity`` overflows: 32 seeds of every shipped scenario (8 of those
  of more than 32 units), the first 20 s, ``cone``, in the engine: runs and steps with a unit
  beyond it.

    python experiments/barrier_engine.py
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from platoon_opt.engine import BATCH_SIZE, Plant, compiled_step, run_batch
from platoon_opt.scenarios import SCENARIO_DIR, load_scenario
from platoon_opt.simulation import simulate, simulate_batch
from platoon_opt.solvers import get_allocator

OUT = Path(__file__).parent / "results" / "barrier_engine.json"
DURATION = 10.0
BATCH = 32
# Platoons of more units than this count their overflows over LARGE_SEEDS seeds.
LARGE, LARGE_SEEDS = 32, 8


PROGRAMS = ("qp", "cone", "qp-projection", "cone-projection", "iterative")


def barrier(program: str) -> Any:
    """``program`` with barriers: a convex program through the dual with rate-aware sectors, or
    the iteration with m = 4."""
    if program == "iterative":
        return get_allocator(program, max_iterations=4, safety="barrier")
    return get_allocator(program, backend="dual", safety="barrier", rate_aware=True)


def timed(function, *args, **kwargs) -> tuple[float, object]:
    start = time.perf_counter()
    result = function(*args, **kwargs)
    return time.perf_counter() - start, result


def overflow() -> list[dict[str, object]]:
    """Runs and steps beyond the default capacity, per scenario."""
    rows = []
    for path in sorted(SCENARIO_DIR.glob("*.toml")):
        scenario = load_scenario(path.stem)
        step = compiled_step(barrier("cone"), scenario)
        seeds = BATCH_SIZE if scenario.n <= LARGE else LARGE_SEEDS
        starts = [scenario.initial(seed) for seed in range(seeds)]
        steps = scenario.run_steps(min(scenario.duration, 20.0))
        batch = run_batch(step, Plant.of(scenario), [s for s, _ in starts], [o for _, o in starts], steps)
        row = {
            "scenario": scenario.name,
            "seeds": seeds,
            "seconds": steps * scenario.dt,
            "overflow_runs": int(np.any(batch.steps.overflow, axis=1).sum()),
            "overflow_steps": int(batch.steps.overflow.sum()),
            "slack_steps": int(np.sum(batch.steps.slack > 0)),
        }
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def measure(name: str, program: str, *, batch: bool) -> dict[str, object]:
    """Seconds of 10 s of ``name`` under ``program``: one platoon compiled (first and second
    call), with ``batch`` a batch of 32 seeds (first and second call), and the host loop."""
    scenario = load_scenario(name)
    first, _ = timed(simulate, scenario, barrier(program), seed=0, duration=DURATION)
    single, run = timed(simulate, scenario, barrier(program), seed=1, duration=DURATION)
    row: dict[str, object] = {
        "scenario": name,
        "allocator": program,
        "compiled": bool(run.compiled),
        "first_call_s": first,
        "compiled_single_s": single,
    }
    if batch:
        row["batch_first_s"], _ = timed(
            simulate_batch, scenario, barrier(program), range(BATCH), duration=DURATION
        )
        seconds, _ = timed(
            simulate_batch, scenario, barrier(program), range(BATCH, 2 * BATCH), duration=DURATION
        )
        row.update(batch32_s=seconds, batch_x_per_platoon=BATCH * DURATION / seconds)
    host, _ = timed(simulate, scenario, barrier(program), seed=1, duration=DURATION, compiled=False)
    row.update(host_s=host, single_x=DURATION / single, host_x=DURATION / host)
    print(json.dumps(row), flush=True)
    return row


def cost() -> list[dict[str, object]]:
    """One platoon, a batch and the host loop, per scenario and program."""
    return [
        measure(name, program, batch=True)
        for name in ("paper_obstacles", "field_dense")
        for program in PROGRAMS
    ]


def large() -> list[dict[str, object]]:
    """One platoon compiled and the host loop at 50 and 200 units (no batch: a batch of 32
    platoons of 200 units takes minutes)."""
    return [
        measure(name, program, batch=False)
        for name in ("units_50", "units_200")
        for program in ("cone", "cone-projection", "iterative")
    ]


def main() -> None:
    results = {"cost": cost(), "large": large(), "overflow": overflow()}
    OUT.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
