"""The closed-loop part: the paper scenario (no obstacles) with n units, in the compiled engine
(the paper's iteration with m = 4, and the dual in each of its programs), one platoon and batches
of platoons, and on the host with Clarabel (``qp``) beside them: simulated seconds per wall second
per platoon, the compile time and the memory of the compiled call.

A platoon of n units starts on the paper's ring with its variances scaled by (n / 8)^2, so that
neighbours stay as far apart as in the paper's eight. Each measurement runs ``steps`` steps, fewer
for large platoons and batches (about ``WORK`` unit-steps), twice: the first call compiles, the
second is timed. The host loop runs a quarter of those steps.

Contract: one record of kind "closed_loop" per (allocator, n, batch) measured, and one of kind
"closed_loop_skipped" per combination left out (with the reason).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax

from platoon_opt import load_scenario, simulate
from platoon_opt.engine import Plant, batch_memory, compiled_step, run_batch
from platoon_opt.scenarios import Scenario
from platoon_opt.solvers import get_allocator
from platoon_opt.study.bench import cases
from platoon_opt.study.bench.timing import Records, clock, since

SIZES = (3, 8, 64, 512, 4096)
BATCHES = (1, 64, 1024)
# Large platoons, one at a time: the whole control step at n = 32,768 and the memory at 100,000.
LARGE = (32_768, 100_000)
# Unit-steps per measurement (n x batch x steps), within [MIN_STEPS, MAX_STEPS] steps: at most a
# whole run of the paper scenario (45 s), as a study runs it (a shorter one would count the call's
# fixed cost, about 0.3 ms, against fewer steps).
WORK = 4e6
MIN_STEPS, MAX_STEPS = 10, 4500
# Batches whose compiled call would hold more than this are left out (bytes).
MEMORY_LIMIT = 6e9
# The host loop with Clarabel: platoons up to this size (a step at n = 4,096 takes a second).
HOST_SIZES = (3, 8, 64, 512)

# label -> (allocator name, options) run in the engine
COMPILED: dict[str, tuple[str, dict[str, Any]]] = {
    "iterative m=4": ("iterative", {"max_iterations": 4}),
    "dual": ("dual", {}),
    "dual cone": ("dual", {"speed": "cone"}),
    "dual task-exact": ("dual", {"reading": "task-exact"}),
    "dual task-exact cone": ("dual", {"reading": "task-exact", "speed": "cone"}),
}
# The allocators measured at the sizes of LARGE.
LARGE_ALLOCATORS = ("iterative m=4", "dual")


def scenario_of(n: int) -> Scenario:
    """The benchmark's scenario with n units (see the module docstring)."""
    base = load_scenario(cases.SCENARIO)
    return dataclasses.replace(base, n=n, variance=base.variance * (n / base.n) ** 2)


def steps_for(n: int, batch: int) -> int:
    """Steps of a measurement of ``batch`` platoons of n units."""
    return int(min(MAX_STEPS, max(MIN_STEPS, WORK / (n * batch))))


def run_closed_loop(
    records: Records,
    sizes: Sequence[int] = SIZES,
    batches: Sequence[int] = BATCHES,
    large: Sequence[int] = LARGE,
) -> None:
    """Simulated seconds per wall second per platoon for every allocator of ``COMPILED`` at every
    size and batch, and for ``qp`` on the host (one platoon, ``HOST_SIZES``); the sizes of
    ``large`` one platoon at a time, with the iteration and the (achievable-first) dual only."""
    for n in (*sizes, *large):
        scenario = scenario_of(n)
        allocators = COMPILED if n in sizes else {k: COMPILED[k] for k in LARGE_ALLOCATORS}
        for label, (name, options) in allocators.items():
            step = compiled_step(get_allocator(name, **options), scenario)
            for batch in batches if n in sizes else (1,):
                record = _compiled(scenario, label, step, n, batch) if step is not None else None
                if record is None:
                    reason = "no kernel" if step is None else f"more than {MEMORY_LIMIT / 1e9:g} GB"
                    records.add(kind="closed_loop_skipped", allocator=label, n=n, batch=batch, reason=reason)
                    records.log(f"  {label:<22} n={n:<5} batch={batch:<5} skipped: {reason}")
                    continue
                records.add(**record)
                records.log(
                    f"  {label:<22} n={n:<5} batch={batch:<5} x{record['speed']:,.0f} real time per platoon "
                    f"({record['step_time'] * 1e6:,.1f} us/platoon-step; compile {record['compile']:.1f} s)"
                )
        # The programs of this size are not run again: their machine code is released (a process
        # may hold 65,530 memory mappings; see platoon_opt.engine.PROGRAMS_KEPT).
        jax.clear_caches()
        if n in HOST_SIZES:
            record = _host(scenario, n)
            records.add(**record)
            records.log(
                f"  {'qp (Clarabel, host)':<22} n={n:<5} batch=1     x{record['speed']:,.1f} real time "
                f"({record['step_time'] * 1e3:.2f} ms/step, allocation {record['allocation'] * 1e3:.2f} ms)"
            )


def _compiled(scenario: Scenario, label: str, step: Any, n: int, batch: int) -> dict[str, Any] | None:
    """One measurement in the engine, or None if it would not fit ``MEMORY_LIMIT``."""
    starts = [scenario.initial(seed) for seed in range(batch)]
    arguments = (
        step,
        Plant.of(scenario),
        [s for s, _ in starts],
        [o for _, o in starts],
        steps_for(n, batch),
    )
    start = clock()
    memory = batch_memory(*arguments)
    if memory > MEMORY_LIMIT:
        return None
    run_batch(*arguments)
    first, _ = since(start)
    start = clock()
    run_batch(*arguments)
    wall, cpu = since(start)
    steps = arguments[-1]
    return {
        "kind": "closed_loop",
        "allocator": label,
        "path": "compiled",
        "scenario": scenario.name,
        "n": n,
        "batch": batch,
        "steps": steps,
        "wall": wall,
        "cpu": cpu,
        "speed": steps * scenario.dt * batch / wall,
        "step_time": wall / (steps * batch),
        "compile": max(first - wall, 0.0),
        "memory": memory,
    }


def _host(scenario: Scenario, n: int) -> dict[str, Any]:
    """One platoon in the host loop under ``qp`` (Clarabel)."""
    allocator = get_allocator("qp", backend="clarabel")
    steps = steps_for(n, 1) // 4
    simulate(scenario, allocator, duration=MIN_STEPS * scenario.dt)  # first calls compile the kernels
    start = clock()
    trajectory = simulate(scenario, allocator, duration=steps * scenario.dt)
    wall, cpu = since(start)
    return {
        "kind": "closed_loop",
        "allocator": "qp (Clarabel, host)",
        "path": "host",
        "scenario": scenario.name,
        "n": n,
        "batch": 1,
        "steps": trajectory.steps,
        "wall": wall,
        "cpu": cpu,
        "speed": trajectory.steps * scenario.dt / wall,
        "step_time": wall / trajectory.steps,
        "allocation": float(sorted(trajectory.solve_time)[trajectory.steps // 2]),
        "compile": 0.0,
        "memory": 0,
    }
