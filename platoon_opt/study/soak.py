"""The soak: every allocator on many seeded random allocation problems (``study.problems``),
counting exceptions, non-finite output, limit violations (``promised_excess`` above
``LIMIT_TOLERANCE``), fallbacks, statuses and times. ``platoon-opt soak`` runs it; what is
measured and how is in docs/benchmarks.md.

Contract: problems are solved in chunks of ``problems.CHUNK``, one fresh allocator per chunk, so a
chunk's record depends only on the allocator, the chunk and the settings (``settings``), not on
the process or the chunks before it. Each finished chunk is stored at once in a ``ResultCache``
under ``<out>/soak-chunks/<name>/<chunk>.json`` with the fingerprint of those settings; a later
run with the same settings reuses it, so an interruption loses only the chunks under way.
``soak.json`` and ``soak.md`` (``soak_report``) are rewritten as allocators complete, at most
``SUMMARY_INTERVAL`` apart in between, and at the end.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import inspect
import math
import re
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from platoon_opt.arrays import one_blas_thread
from platoon_opt.solvers import available_allocators, get_allocator
from platoon_opt.solvers.registry import PromisingAllocator
from platoon_opt.study import problems as family
from platoon_opt.study.arguments import CASES, SEED, fraction, integer
from platoon_opt.study.cache import ResultCache, fingerprint
from platoon_opt.study.executor import Progress, execute
from platoon_opt.study.exits import stopped
from platoon_opt.study.machine import load_average, machine
from platoon_opt.study.output import write_atomic, write_json
from platoon_opt.study.problems import DEGENERATE_RATE, KINDS, LIMIT_TOLERANCE
from platoon_opt.study.runs import code_version
from platoon_opt.study.soak_report import EXAMPLES, markdown, merge

DEFAULT_PROBLEMS = 100_000
# While an allocator is unfinished, soak.json and soak.md are rewritten at most this often (s).
SUMMARY_INTERVAL = 60.0
# Exit status of the command when something went wrong in some allocator.
FAILURES = 1


def normalise_status(status: str) -> str:
    """A status with its numbers replaced by ``#`` (e.g. "violated by 1.2e-07" -> "violated by #")."""
    return re.sub(r"[-+]?\d+(\.\d+)?([eE][-+]?\d+)?", "#", status)


@dataclass
class Tally:
    """The counts of one allocator over one chunk of problems."""

    problems: int = 0
    build_errors: int = 0
    exceptions: Counter = field(default_factory=Counter)
    non_finite: int = 0
    violations: int = 0
    worst_excess: float = 0.0
    worst_excess_index: int | None = None
    fallbacks: int = 0
    program_changes: int = 0
    statuses: Counter = field(default_factory=Counter)
    by_kind: dict[str, Counter] = field(default_factory=lambda: {kind: Counter() for kind in KINDS})
    examples: dict[str, list[dict[str, Any]]] = field(
        default_factory=lambda: {
            key: [] for key in ("build", "exception", "non_finite", "violation", "fallback", "program_change")
        }
    )

    def example(self, category: str, **details: Any) -> None:
        if len(self.examples[category]) < EXAMPLES:
            self.examples[category].append(details)


def soak_chunk(
    name: str,
    factory: Callable[[str], PromisingAllocator],
    seed: int,
    chunk: int,
    count: int,
    degenerate_rate: float = DEGENERATE_RATE,
) -> dict[str, Any]:
    """Allocator ``name`` on the problems of chunk ``chunk`` of seed ``seed`` below ``count``
    (problems chunk CHUNK .. min(count, (chunk + 1) CHUNK) - 1); returns the chunk's record.

    One fresh instance (``factory(name)``) solves the chunk's problems in order, as in a closed
    loop: warm starts and solver workspaces carry over from one problem to the next. A chunk's
    record therefore does not depend on which process ran it or on the chunks before it.
    """
    allocator = factory(name)
    first = chunk * family.CHUNK
    batch = family.chunk_specs(seed, chunk, degenerate_rate)[: count - first]
    size = len(batch)
    tally = Tally()
    times, cpu_times = np.zeros(size), np.zeros(size)
    sizes, kinds = np.array([spec.n for spec in batch], dtype=int), [spec.kind for spec in batch]
    started = time.perf_counter()
    building = 0.0
    for offset, spec in enumerate(batch):
        index = first + offset
        kind_counts = tally.by_kind[spec.kind]
        kind_counts["problems"] += 1
        tally.problems += 1
        where = {"index": index, "kind": spec.kind, "n": spec.n, "obstacles": int(len(spec.radii))}
        before = time.perf_counter()
        try:
            problem = spec.build()
        except Exception as error:  # the model refused the inputs: not the allocator's doing
            tally.build_errors += 1
            tally.example("build", **where, error=f"{type(error).__name__}: {error}"[:300])
            continue
        start = time.perf_counter()
        building += start - before
        cpu = time.process_time()
        try:
            allocation = allocator.allocate(problem)
        except Exception as error:  # counted, never fatal: that is what a soak is for
            times[offset], cpu_times[offset] = time.perf_counter() - start, time.process_time() - cpu
            tally.exceptions[type(error).__name__] += 1
            kind_counts["exceptions"] += 1
            tally.example("exception", **where, error=f"{type(error).__name__}: {error}"[:300])
            continue
        times[offset], cpu_times[offset] = time.perf_counter() - start, time.process_time() - cpu
        tally.statuses[normalise_status(allocation.status)] += 1
        if allocation.fell_back:
            tally.fallbacks += 1
            kind_counts["fallbacks"] += 1
            tally.example("fallback", **where, status=allocation.status[:300])
        if allocation.program_changed:  # answered by another program than the one asked for
            tally.program_changes += 1
            kind_counts["program_changes"] += 1
            tally.example("program_change", **where, status=allocation.status[:300])
        if not np.all(np.isfinite(allocation.velocities)):
            tally.non_finite += 1
            kind_counts["non_finite"] += 1
            tally.example("non_finite", **where, status=allocation.status[:300])
            continue
        excess = allocator.promised_excess(problem, allocation)
        if excess is not None and excess > LIMIT_TOLERANCE:
            tally.violations += 1
            kind_counts["violations"] += 1
            tally.example("violation", **where, excess=excess, status=allocation.status[:300])
        if excess is not None and excess > tally.worst_excess:
            tally.worst_excess, tally.worst_excess_index = excess, index
    micro, cpu_micro = times * 1e6, cpu_times * 1e6
    return {
        "name": name,
        "allocator": allocator.name,
        "promise": allocator.promise,
        "chunk": chunk,
        "problems": tally.problems,
        "build_errors": tally.build_errors,
        "exception_types": dict(tally.exceptions),
        "non_finite": tally.non_finite,
        "limit_violations": tally.violations,
        "worst_excess": tally.worst_excess,
        "worst_excess_index": tally.worst_excess_index,
        "fallbacks": tally.fallbacks,
        "program_changes": tally.program_changes,
        "statuses": dict(tally.statuses),
        "by_kind": {kind: dict(counts) for kind, counts in tally.by_kind.items() if counts},
        "examples": {key: value for key, value in tally.examples.items() if value},
        "time_us": np.round(micro, 1).tolist(),
        "cpu_time_us": np.round(cpu_micro, 1).tolist(),
        "slowest": [
            {
                "index": first + int(i),
                "kind": kinds[i],
                "n": int(sizes[i]),
                "time_us": float(micro[i]),
                "cpu_time_us": float(cpu_micro[i]),
            }
            for i in np.argsort(-micro, kind="stable")[:EXAMPLES]
        ],
        "wall_time": time.perf_counter() - started,
        "build_time": building,
    }


def _chunk_job(
    job: tuple[str, int],
    *,
    factory: Callable[[str], PromisingAllocator],
    seed: int,
    count: int,
    degenerate_rate: float,
) -> dict[str, Any]:
    """A worker's job: the record of chunk ``job = (name, chunk)``, with one BLAS thread (the
    matrices are tiny; as in a simulation, ``platoon_opt.simulation.simulate``)."""
    name, chunk = job
    with one_blas_thread():
        return soak_chunk(name, factory, seed, chunk, count, degenerate_rate)


def settings(seed: int, degenerate_rate: float) -> dict[str, Any]:
    """What a chunk's record depends on besides the allocator and the chunk: the seed and the
    degenerate rate, the model's and the allocators' code (``runs.code_version``), the problem
    family (``problems.family_version``) and the checks of this module."""
    checks = "".join(inspect.getsource(part) for part in (normalise_status, Tally, soak_chunk))
    return {
        "seed": seed,
        "degenerate_rate": degenerate_rate,
        "code": code_version(),
        "family": family.family_version(),
        "checks": fingerprint([checks, LIMIT_TOLERANCE, EXAMPLES]),
    }


def chunk_key(name: str, chunk: int) -> str:
    """The cache key of allocator ``name``'s chunk ``chunk``."""
    return f"soak-chunks/{name}/{chunk:05d}"


def _chunk_fingerprint(shared: dict[str, Any], problems: int) -> str:
    # A chunk cut short by a smaller --problems holds fewer problems: not the same record.
    return fingerprint({**shared, "problems": problems})


def run(
    out_dir: str | Path,
    *,
    problems: int = DEFAULT_PROBLEMS,
    allocators: Sequence[str] | None = None,
    seed: int = 0,
    degenerate_rate: float = DEGENERATE_RATE,
    fresh: bool = False,
    jobs: int = 1,
    factory: Callable[[str], PromisingAllocator] | None = None,
    stream: TextIO | None = None,
    command: str = "",
) -> dict[str, Any]:
    """Soak every allocator in ``allocators`` (default: every registered one) on problems
    0 .. problems - 1 of ``seed`` and write ``out_dir/soak.json`` and ``soak.md``.

    Args:
        jobs: worker processes (``executor.execute``), each solving whole chunks; 1 solves here.
        factory: builds an allocator from its name (default ``solvers.get_allocator``); with
            ``jobs`` > 1 it is pickled to the workers (a module-level function).
        fresh: recompute chunks that an earlier run finished.
        stream: where the progress bar and the reuse notes go (default stderr).
        command: the command as typed, recorded in soak.json.

    Returns:
        The results, as written to soak.json.
    """
    factory = factory or get_allocator
    stream = stream if stream is not None else sys.stderr
    names = list(allocators) if allocators else available_allocators()
    out = Path(out_dir)
    cache = ResultCache(out, fresh=fresh)
    shared = settings(seed, degenerate_rate)
    chunks = range(math.ceil(problems / family.CHUNK))
    sizes = {chunk: min(family.CHUNK, problems - chunk * family.CHUNK) for chunk in chunks}
    done: dict[str, dict[int, dict[str, Any]]] = {name: {} for name in names}
    todo: list[tuple[str, int]] = []
    for name in names:
        for chunk in chunks:
            record = cache.load(chunk_key(name, chunk), _chunk_fingerprint(shared, sizes[chunk]))
            if record is None:
                todo.append((name, chunk))
            else:
                done[name][chunk] = record
        if done[name]:
            kept = sum(record["problems"] for record in done[name].values())
            print(
                f"soak {name}: kept {kept:,} problems ({len(done[name])} chunks) from an earlier run",
                file=stream,
            )
    result: dict[str, Any] = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "load_before": load_average(),
        "command": command,
        **shared,
        "chunk": family.CHUNK,
        "jobs": jobs,
        "counts": {name: problems for name in names},
        "limit_tolerance": LIMIT_TOLERANCE,
        "allocators": {},
    }

    def write_summary() -> None:
        result["load_after"] = load_average()
        result["allocators"] = {
            name: merge(list(done[name].values()), problems) for name in names if done[name]
        }
        write_json(out / "soak.json", result)
        write_atomic(out / "soak.md", markdown(result))

    job = functools.partial(
        _chunk_job, factory=factory, seed=seed, count=problems, degenerate_rate=degenerate_rate
    )
    last_write = time.perf_counter()
    with Progress(problems * len(names), "soak", unit="problems", stream=stream) as progress:
        progress.reuse(sum(sizes[chunk] for name in names for chunk in done[name]))
        for position, record in execute(job, todo, workers=jobs):
            name, chunk = todo[position]
            cache.store(chunk_key(name, chunk), _chunk_fingerprint(shared, sizes[chunk]), record)
            done[name][chunk] = record
            progress.advance(record["problems"])
            if len(done[name]) == len(sizes) or time.perf_counter() - last_write >= SUMMARY_INTERVAL:
                write_summary()
                last_write = time.perf_counter()
    write_summary()
    return result


def show(
    index: int, seed: int = 0, degenerate_rate: float = DEGENERATE_RATE, allocators: Sequence[str] = ()
) -> str:
    """Problem ``index`` of ``seed`` in words, and what each allocator in ``allocators`` makes of
    it (a fresh allocator, warmed on problem ``index - 1`` as in the soak)."""
    spec = family.spec_at(seed, index, degenerate_rate)
    problem = spec.build()
    lines = [f"problem {index} of seed {seed}: kind {spec.kind}, n = {spec.n}"]
    # Every digit, so that the problem can be rebuilt by hand.
    with np.printoptions(precision=17, linewidth=110):
        lines.append(repr(spec))
        lines.append(f"exempt: {problem.exempt.astype(int)}, gear: {problem.gear}")
        lines.append(f"nominal:\n{problem.nominal}")
        for name in allocators:
            allocator = get_allocator(name)
            if index > 0:
                try:
                    allocator.allocate(family.spec_at(seed, index - 1, degenerate_rate).build())
                except Exception:  # the warm-up's failure is not this problem's: counted elsewhere
                    pass
            try:
                allocation = allocator.allocate(problem)
            except Exception as error:
                lines.append(f"{name}: raised {type(error).__name__}: {error}")
                continue
            excess = allocator.promised_excess(problem, allocation)
            lines.append(
                f"{name}: status {allocation.status!r}, fell_back {allocation.fell_back}, "
                f"residual {allocation.task_residual:.3e}, promised excess {excess}\n{allocation.velocities}"
            )
    return "\n".join(lines)


# --- the command line ---------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser, default_out: Path) -> None:
    """The options of ``platoon-opt soak``."""
    parser.add_argument(
        "--problems",
        type=CASES,
        default=DEFAULT_PROBLEMS,
        help=f"problems per allocator (default {DEFAULT_PROBLEMS:,})",
    )
    parser.add_argument("--allocators", help="comma-separated registry names (default: every registered one)")
    parser.add_argument(
        "--jobs", type=integer(1), default=1, help="worker processes, each solving whole chunks (default 1)"
    )
    parser.add_argument("--out", default=str(default_out), help=f"output folder (default {default_out})")
    parser.add_argument("--seed", type=SEED, default=0, help="problem seed (default 0)")
    parser.add_argument(
        "--degenerate-rate",
        type=fraction,
        default=DEGENERATE_RATE,
        help=f"fraction of degenerate problems (default {DEGENERATE_RATE})",
    )
    parser.add_argument("--fresh", action="store_true", help="recompute the chunks an earlier run finished")
    parser.add_argument(
        "--show", type=SEED, metavar="INDEX", help="print problem INDEX (and run --allocators on it)"
    )


def _names(args: argparse.Namespace) -> list[str]:
    return [name for name in (args.allocators or "").split(",") if name]


def check_arguments(args: argparse.Namespace) -> str | None:
    """What is wrong with the parsed options, in one line, or None."""
    unknown = [name for name in _names(args) if name not in available_allocators()]
    if unknown:
        return f"--allocators: unknown {', '.join(unknown)}; known: {', '.join(available_allocators())}"
    if args.problems < 1:
        return f"--problems must be >= 1, got {args.problems}"
    if args.jobs < 1:
        return f"--jobs must be >= 1, got {args.jobs}"
    if not 0.0 <= args.degenerate_rate <= 1.0:
        return f"--degenerate-rate must lie in [0, 1], got {args.degenerate_rate}"
    if args.show is not None and args.show < 0:
        return f"--show must be >= 0, got {args.show}"
    return None


def command(args: argparse.Namespace, typed: str) -> int:
    """Run ``platoon-opt soak`` with checked options (``check_arguments``); ``typed`` is the
    command line as typed. Returns the exit status: 0, ``FAILURES`` if an allocator raised,
    returned non-finite velocities or left its sets (or the model refused a problem), or
    ``exits.stopped``'s status."""
    names = _names(args)
    if args.show is not None:
        print(show(args.show, args.seed, args.degenerate_rate, names))
        return 0
    try:
        result = run(
            args.out,
            problems=args.problems,
            allocators=names or None,
            seed=args.seed,
            degenerate_rate=args.degenerate_rate,
            fresh=args.fresh,
            jobs=args.jobs,
            command=typed,
        )
    except KeyboardInterrupt as stop:
        what, status = stopped(stop)
        print(
            f"\n{what}: finished chunks are in {args.out}/soak-chunks (the same command resumes)",
            file=sys.stderr,
        )
        return status
    for name, entry in result["allocators"].items():
        print(
            f"{name}: {entry['problems']:,} problems, {entry['exceptions']} exceptions, "
            f"{entry['non_finite']} non-finite, {entry['limit_violations']} limit violations, "
            f"{entry['fallbacks']} fallbacks ({entry['program_changes']} answered by another program), "
            f"{entry['build_errors']} refused by the model"
        )
    bad = [
        name
        for name, entry in result["allocators"].items()
        if entry["exceptions"] or entry["non_finite"] or entry["limit_violations"] or entry["build_errors"]
    ]
    print(
        f"wrote {args.out}/soak.json and soak.md; "
        + (f"problems in: {', '.join(bad)}" if bad else "no failures")
    )
    return FAILURES if bad else 0
