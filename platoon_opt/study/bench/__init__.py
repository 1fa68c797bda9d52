"""Speed and scale (``platoon-opt bench``): the allocators from 8 to 100,000 units (``scale``),
the whole control step (``step``), n = 8 against Clarabel's bare solve (``small``) and the closed
loop (``closed_loop``); ``run`` runs the parts asked for (all by default) and writes
``bench.json``, ``bench.md`` and, with the scale part, ``bench.png`` (``report``). What each
part measures, and how, is in docs/benchmarks.md.

Contract: every part runs in this one process, one after the other, so that every allocator
meets the same machine state; each figure is a median over repetitions, a wall-clock time with
the process's CPU time beside it, and the load average before and after the run is recorded.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from platoon_opt.study.bench.cases import DUAL_ONLY_SIZES, SIZES
from platoon_opt.study.bench.closed_loop import BATCHES, LARGE, run_closed_loop
from platoon_opt.study.bench.closed_loop import SIZES as CLOSED_LOOP_SIZES
from platoon_opt.study.bench.report import markdown, plot
from platoon_opt.study.bench.scale import run_scale
from platoon_opt.study.bench.small import run_small
from platoon_opt.study.bench.step import run_step
from platoon_opt.study.bench.timing import Records
from platoon_opt.study.machine import load_average, machine
from platoon_opt.study.output import write_atomic, write_json

# The parts, in the order they run.
PARTS = ("scale", "step", "small", "closed_loop")
# The --quick run: a check that every part works, in about a minute (not a result).
QUICK: dict[str, Any] = {
    "sizes": (8, 64, 512),
    "dual_only": (),
    "small_duration": 2.0,
    "closed_loop_sizes": (8,),
    "closed_loop_batches": (1, 4),
    "closed_loop_large": (),
}


def run(
    out_dir: str | Path,
    *,
    sizes: tuple[int, ...] = SIZES,
    dual_only: tuple[int, ...] = DUAL_ONLY_SIZES,
    small_duration: float = 10.0,
    closed_loop_sizes: tuple[int, ...] = CLOSED_LOOP_SIZES,
    closed_loop_batches: tuple[int, ...] = BATCHES,
    closed_loop_large: tuple[int, ...] = LARGE,
    parts: tuple[str, ...] = PARTS,
    threads: int | None = None,
    log: Callable[[str], None] = print,
    command: str = "",
) -> dict[str, Any]:
    """Run every part and write ``bench.json``, ``bench.md`` and ``bench.png`` to ``out_dir``.

    Args:
        sizes: problem sizes of the scale and step parts; ``dual_only``: sizes for the dual alone.
        small_duration: seconds of the paper scenario whose steps are the n = 8 comparison.
        closed_loop_sizes, closed_loop_batches: the platoon sizes and batches of the closed loop;
            ``closed_loop_large``: larger sizes run one platoon at a time.
        parts: which of ``PARTS`` to run.
        threads: the threads of JAX's pool, if the caller sized it (``executor.share_cores``);
            recorded (None: one per core).
        log: where the progress lines go.
        command: the command as typed, recorded in bench.json.

    Returns:
        The run: machine, load, arguments and records (as written to bench.json).
    """
    out = Path(out_dir)
    records = Records(log=log)
    load_before = load_average()
    started = time.perf_counter()
    if "scale" in parts:
        log("scale: allocation time per n")
        run_scale(records, sizes, dual_only)
    if "step" in parts:
        log("step: the whole control step with the dual")
        run_step(records, (*sizes, *dual_only))
    if "small" in parts:
        log("small: n = 8 along the closed loop")
        run_small(records, small_duration)
    if "closed_loop" in parts:
        log("closed loop: the paper scenario with n units, compiled and on the host")
        run_closed_loop(records, closed_loop_sizes, closed_loop_batches, closed_loop_large)
    result = {
        "machine": machine(),
        "load_before": load_before,
        "load_after": load_average(),
        "duration": time.perf_counter() - started,
        "command": command,
        "arguments": {
            "sizes": list(sizes),
            "dual_only": list(dual_only),
            "small_duration": small_duration,
            "closed_loop_sizes": list(closed_loop_sizes),
            "closed_loop_batches": list(closed_loop_batches),
            "closed_loop_large": list(closed_loop_large),
            "parts": list(parts),
            "threads": threads,
        },
        "records": records.records,
    }
    write_json(out / "bench.json", result)
    write_atomic(out / "bench.md", markdown(result))
    written = ["bench.json", "bench.md"]
    if "scale" in parts:  # the figure draws the scale part
        plot(result, out / "bench.png")
        written.append("bench.png")
    log(f"wrote {', '.join(written)} to {out} in {result['duration']:.0f} s")
    return result
