"""Soak test of the allocators (issue 6): every registered allocator on many random allocation
problems, counting what goes wrong.

    python -m benchmarks.soak [--problems N] [--allocators a,b] [--jobs J] [--out DIR] [--seed S] [--fresh]

Every allocator solves the same seeded problems, in chunks of ``CHUNK``: one fresh instance per
chunk, kept across the chunk's problems as in a closed loop (warm starts and solver workspaces
carry over). Counted:

* **exceptions**: ``allocate`` raised (by type; ``Allocation.of`` refuses non-finite
  velocities with a ``FloatingPointError``, so a NaN usually shows up here);
* **non-finite**: an allocation returned with non-finite velocities (bypassing ``Allocation.of``);
* **limit violations**: a unit outside the set its allocator promises (``promised_excess``) by
  more than ``LIMIT_TOLERANCE``;
* **fallbacks**: ``Allocation.fell_back``;
* the distribution of ``status`` (numbers in a status replaced by ``#``);
* time per ``allocate`` call (median, 95th percentile, max; wall clock and CPU, µs).

Problems (``ProblemSpec``, ``platoon_opt.study.problems``, shared with the property tests): 2 to 12 units
scattered over a square, random headings, steering within its limit and gears, a random
target ``f_d`` near ``f`` and rate ``f_d'``, gains around the paper's, 0 to 3 circular
obstacles near the platoon; a fraction ``DEGENERATE_RATE`` of them is made degenerate (one of
``DEGENERATE_KINDS``: coincident units, units on a line, a zero nominal velocity, a unit inside an
obstacle, gains of 1e6, steering at its limit). Problem ``i`` of seed ``s`` is the same for every
allocator and every run: its random numbers come from chunk ``i // CHUNK`` drawn with
``numpy.random.default_rng([s, chunk])`` (vectorised over the chunk), so ``--show i`` rebuilds it.

Each finished chunk is written at once to ``DIR/soak-chunks/NAME/CHUNK.json`` (default ``DIR``:
``benchmarks/results``). The same command run again, after an interruption or in a later
session, keeps the chunks finished with the same seed, code and problem family and solves the
rest (``--fresh`` recomputes them): a run loses at most the chunks under way, and ``--jobs``
spreads chunks over processes. ``DIR/soak.json`` and ``DIR/soak.md``, with the machine, the date
and the load, are rewritten atomically as allocators complete and at least a minute apart.

``nmpc`` (receding horizon) costs about 0.1 s per call on these platoons, so its 100,000
problems take about 3 hours of one core; the cheap allocators take 2-4 minutes each.
"""

from __future__ import annotations

import argparse
import datetime
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
from threadpoolctl import threadpool_limits

from platoon_opt.problem import Allocator
from platoon_opt.study import problems as family
from platoon_opt.study.machine import load_average, machine
from platoon_opt.study.problems import DEGENERATE_KINDS, DEGENERATE_RATE, KINDS, MAX_OBSTACLES, MAX_UNITS

# --- what each allocator promises ------------------------------------------------------------

# A unit this far outside its promised set (m/s) is a limit violation.
LIMIT_TOLERANCE = 1e-7


# --- the soak --------------------------------------------------------------------------------

DEFAULT_PROBLEMS = 100_000
# Failure examples kept per category.
EXAMPLES = 5


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
    statuses: Counter = field(default_factory=Counter)
    by_kind: dict[str, Counter] = field(default_factory=lambda: {kind: Counter() for kind in KINDS})
    examples: dict[str, list[dict[str, Any]]] = field(
        default_factory=lambda: {
            key: [] for key in ("build", "exception", "non_finite", "violation", "fallback")
        }
    )

    def example(self, category: str, **details: Any) -> None:
        if len(self.examples[category]) < EXAMPLES:
            self.examples[category].append(details)


def soak_chunk(
    name: str,
    factory: Callable[..., Allocator],
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


def merge(records: Sequence[dict[str, Any]], target: int) -> dict[str, Any]:
    """One allocator's entry of soak.json from its chunk records (any subset, in any order):
    counts summed, times pooled (median, p95, max, mean per call), the first ``EXAMPLES``
    examples per category in problem order. ``wall_time`` is the sum over chunks (one core's
    time), so ``problems_per_second`` is per core whatever ``--jobs`` was."""
    records = sorted(records, key=lambda record: record["chunk"])
    last = records[-1]
    exceptions, statuses = Counter(), Counter()
    by_kind: dict[str, Counter] = {}
    examples: dict[str, list[dict[str, Any]]] = {}
    for record in records:
        exceptions.update(record["exception_types"])
        statuses.update(record["statuses"])
        for kind, counts in record["by_kind"].items():
            by_kind.setdefault(kind, Counter()).update(counts)
        for category, items in record["examples"].items():
            kept = examples.setdefault(category, [])
            kept.extend(items[: EXAMPLES - len(kept)])
    micro = np.concatenate([record["time_us"] for record in records])
    cpu_micro = np.concatenate([record["cpu_time_us"] for record in records])
    worst = max(records, key=lambda record: record["worst_excess"])
    problems = sum(record["problems"] for record in records)
    wall = sum(record["wall_time"] for record in records)
    slowest = sorted((call for record in records for call in record["slowest"]), key=lambda c: -c["time_us"])
    total = {
        key: sum(record[key] for record in records)
        for key in ("build_errors", "non_finite", "limit_violations", "fallbacks")
    }
    return {
        "name": last["name"],
        "allocator": last["allocator"],
        "promise": last["promise"],
        "problems": problems,
        "target": target,
        "complete": problems == target,
        "chunks": len(records),
        **total,
        "exceptions": sum(exceptions.values()),
        "exception_types": dict(exceptions.most_common()),
        "worst_excess": worst["worst_excess"],
        "worst_excess_index": worst["worst_excess_index"],
        "statuses": dict(statuses.most_common()),
        "by_kind": {kind: dict(by_kind[kind]) for kind in KINDS if kind in by_kind},
        "examples": examples,
        "time_us": {
            "median": float(np.median(micro)),
            "p95": float(np.percentile(micro, 95)),
            "max": float(np.max(micro)),
            "mean": float(np.mean(micro)),
        },
        "cpu_time_us": {
            "median": float(np.median(cpu_micro)),
            "p95": float(np.percentile(cpu_micro, 95)),
            "max": float(np.max(cpu_micro)),
        },
        "slowest": slowest[:EXAMPLES],
        "wall_time": wall,
        "build_time": sum(record["build_time"] for record in records),
        "problems_per_second": problems / wall if wall > 0 else 0.0,
    }


class _Progress:
    """Progress on stderr after each finished chunk: redrawn on a terminal, else a line a minute
    and one when an allocator is complete. The time left assumes each allocator keeps its mean
    time per problem so far (the run's mean for allocators not yet started)."""

    def __init__(
        self, counts: dict[str, int], done: dict[str, dict[int, dict]], jobs: int, stream: TextIO
    ) -> None:
        self.counts, self.done, self.jobs, self.stream = counts, done, jobs, stream
        self.start = self.last = time.perf_counter()
        self.tty = bool(getattr(stream, "isatty", lambda: False)())

    def _line(self, name: str) -> str:
        entry = merge(list(self.done[name].values()), self.counts[name])
        failures = (
            f"{entry['exceptions']} exceptions, {entry['non_finite']} non-finite, "
            f"{entry['limit_violations']} violations, {entry['fallbacks']} fallbacks"
        )
        per_problem = {
            other: sum(r["wall_time"] for r in chunks.values()) / sum(r["problems"] for r in chunks.values())
            for other, chunks in self.done.items()
            if chunks
        }
        typical = float(np.mean(list(per_problem.values())))
        left = sum(
            (self.counts[other] - sum(r["problems"] for r in self.done[other].values()))
            * per_problem.get(other, typical)
            for other in self.counts
        )
        return (
            f"soak {name}: {entry['problems']:,}/{self.counts[name]:,} problems ({failures}); "
            f"{_clock(time.perf_counter() - self.start)} elapsed, ~{_clock(left / self.jobs)} left in all"
        )

    def chunk_done(self, name: str) -> None:
        now = time.perf_counter()
        complete = sum(record["problems"] for record in self.done[name].values()) == self.counts[name]
        if self.tty:
            end = "\n" if complete else ""
            if complete or now - self.last >= 0.5:
                self.last = now
                print("\r" + self._line(name) + "\033[K", end=end, file=self.stream, flush=True)
        elif complete or now - self.last >= 60:
            self.last = now
            print(self._line(name), file=self.stream, flush=True)


def _clock(seconds: float) -> str:
    minutes, seconds = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes}:{seconds:02d}"


def _problems(entry: dict[str, Any]) -> str:
    done = f"{entry['problems']:,}"
    return done if entry["complete"] else f"{done} of {entry['target']:,} (partial)"


def markdown(result: dict[str, Any]) -> str:
    """soak.json as tables."""
    info = result["machine"]
    lines = [
        f"# Soak: every allocator on random allocation problems (seed {result['seed']})",
        "",
        f"{result['date']}; {info['cpu']}, {info['cores']} cores, {info['platform']}; "
        f"Python {info['python']}, numpy {info['numpy']}. Problems: 2-{MAX_UNITS} units, "
        f"0-{MAX_OBSTACLES} obstacles, {result['degenerate_rate']:.0%} degenerate "
        f"({', '.join(DEGENERATE_KINDS)}). A limit violation is a unit outside the set its allocator "
        f"promises by more than {LIMIT_TOLERANCE:g} m/s. Times: per allocate call, wall clock (CPU: "
        "the process's CPU time, threads included; on a shared machine the wall time includes waiting); "
        f"problems/s per worker process ({result.get('jobs', 1)} ran in parallel, one BLAS thread each).",
        "",
        "| allocator | problems | exceptions | non-finite | limit violations | worst excess (m/s) "
        "| fallbacks | median (µs) | p95 (µs) | median CPU (µs) | problems/s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    entries = result["allocators"]
    for name, entry in entries.items():
        lines.append(
            f"| {name} | {_problems(entry)} | {entry['exceptions']} | {entry['non_finite']} | "
            f"{entry['limit_violations']} | {entry['worst_excess']:.1e} | {entry['fallbacks']} | "
            f"{entry['time_us']['median']:,.0f} | {entry['time_us']['p95']:,.0f} | "
            f"{entry['cpu_time_us']['median']:,.0f} | {entry['problems_per_second']:,.0f} |"
        )
    refused = [
        f"- {name}: the model refused {entry['build_errors']:,} problems (see the examples)."
        for name, entry in entries.items()
        if entry.get("build_errors")
    ]
    lines += [""] + refused if refused else []
    partial = [name for name, entry in entries.items() if not entry["complete"]]
    if partial:
        lines += ["", f"Partial (rerun the command to complete them): {', '.join(partial)}."]
    lines += ["", "## What each allocator promises", ""]
    lines += [
        f"- **{name}** (`{entry['allocator']}`): {entry['promise']}." for name, entry in entries.items()
    ]
    lines += ["", "## Statuses", ""]
    for name, entry in entries.items():
        shown = list(entry["statuses"].items())[:8]
        rest = sum(entry["statuses"].values()) - sum(count for _, count in shown)
        text = ", ".join(f"`{status}` {count:,}" for status, count in shown)
        lines.append(f"- **{name}**: {text}" + (f", other {rest:,}" if rest else ""))
    lines += ["", "## Slowest calls (wall / CPU ms; index, kind, n)", ""]
    for name, entry in entries.items():
        text = ", ".join(
            f"{call['time_us'] / 1e3:,.1f} / {call['cpu_time_us'] / 1e3:,.1f} "
            f"(#{call['index']}, {call['kind']}, n = {call['n']})"
            for call in entry["slowest"][:3]
        )
        lines.append(f"- **{name}**: {text}")
    lines += ["", "## Degenerate kinds (fallbacks / violations / exceptions per problems)", ""]
    kinds = [kind for kind in KINDS if any(kind in entry["by_kind"] for entry in entries.values())]
    lines.append("| allocator | " + " | ".join(kinds) + " |")
    lines.append("|---|" + "---|" * len(kinds))
    for name, entry in entries.items():
        cells = []
        for kind in kinds:
            counts = entry["by_kind"].get(kind, {})
            shown = " / ".join(str(counts.get(key, 0)) for key in ("fallbacks", "violations", "exceptions"))
            cells.append(f"{shown} of {counts.get('problems', 0):,}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    failing = {name: entry["examples"] for name, entry in entries.items() if entry["examples"]}
    if failing:
        lines += ["", "## Examples (rebuild one with `python -m benchmarks.soak --show INDEX`)", ""]
        for name, examples in failing.items():
            for category, items in examples.items():
                for item in items:
                    lines.append(f"- {name}, {category}: " + ", ".join(f"{k} = {v}" for k, v in item.items()))
    return "\n".join(lines) + "\n"


def _settings(seed: int, degenerate_rate: float) -> dict[str, Any]:
    """What a chunk's record depends on: the seed and degenerate rate, the model's and the
    allocators' code, the problem family and this module's checks."""
    import hashlib
    import inspect

    from platoon_opt.study.runs import code_version

    checks = hashlib.sha256(
        inspect.getsource(soak_chunk).encode() + repr((LIMIT_TOLERANCE, EXAMPLES)).encode()
    )
    return {
        "seed": seed,
        "degenerate_rate": degenerate_rate,
        "code": code_version(),
        "family": family.family_version() + checks.hexdigest()[:8],
    }


def _chunk_path(out: Path, name: str, chunk: int) -> Path:
    return out / "soak-chunks" / name / f"{chunk:05d}.json"


def _chunk_size(count: int, chunk: int) -> int:
    return min(family.CHUNK, count - chunk * family.CHUNK)


def _load_chunks(out: Path, name: str, count: int, settings: dict[str, Any]) -> dict[int, dict[str, Any]]:
    """The chunk records of ``name`` that an earlier run with ``settings`` finished."""
    import json

    kept = {}
    for chunk in range(math.ceil(count / family.CHUNK)):
        path = _chunk_path(out, name, chunk)
        try:
            saved = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if saved.get("settings") == settings and saved["record"]["problems"] == _chunk_size(count, chunk):
            kept[chunk] = saved["record"]
    return kept


def _soak_chunk_in_worker(
    name: str, seed: int, chunk: int, count: int, degenerate_rate: float
) -> dict[str, Any]:
    from platoon_opt.solvers import get_allocator

    with threadpool_limits(limits=1, user_api="blas"):
        return soak_chunk(name, get_allocator, seed, chunk, count, degenerate_rate)


def run(
    out_dir: str | Path = "benchmarks/results",
    *,
    problems: int = DEFAULT_PROBLEMS,
    allocators: Sequence[str] | None = None,
    seed: int = 0,
    degenerate_rate: float = DEGENERATE_RATE,
    fresh: bool = False,
    jobs: int = 1,
    factory: Callable[..., Allocator] | None = None,
    stream: TextIO | None = None,
    command: str = "",
) -> dict[str, Any]:
    """Soak every allocator in ``allocators`` (default: every registered one) on problems
    0 .. problems - 1 of ``seed``, in chunks of ``CHUNK`` problems.

    Each finished chunk is written at once (atomically) to ``out_dir/soak-chunks/NAME/``; a
    rerun with the same settings (``_settings``) keeps those chunks and solves only the rest,
    so an interruption loses at most the chunks under way. ``soak.json`` and ``soak.md`` are
    rewritten when an allocator is complete, at most a minute apart in between (an unfinished
    allocator is marked partial), and at the end.

    Args:
        jobs: worker processes (each with one BLAS thread); 1 solves in this process.
        factory: ``solvers.get_allocator`` (default); with ``jobs`` > 1 it must be the default.
        fresh: recompute chunks that an earlier run finished.

    Returns:
        The results, as written to soak.json.
    """
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from multiprocessing import get_context

    from platoon_opt.solvers import available_allocators, get_allocator
    from platoon_opt.study.output import write_atomic, write_json

    if jobs > 1 and factory is not None:
        raise ValueError(
            "jobs > 1 runs the registered allocators (solvers.get_allocator); factory must be None"
        )
    factory = factory or get_allocator
    stream = stream if stream is not None else sys.stderr
    names = list(allocators) if allocators else available_allocators()
    counts = {name: problems for name in names}
    out = Path(out_dir)
    settings = _settings(seed, degenerate_rate)
    done = {name: ({} if fresh else _load_chunks(out, name, problems, settings)) for name in names}
    for name, kept in done.items():
        if kept:
            kept_problems = sum(record["problems"] for record in kept.values())
            print(
                f"soak {name}: kept {kept_problems:,} problems ({len(kept)} chunks) from an earlier run",
                file=stream,
            )
    todo = [
        (name, chunk)
        for name in names
        for chunk in range(math.ceil(problems / family.CHUNK))
        if chunk not in done[name]
    ]
    result = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "load_before": load_average(),
        "command": command,
        **settings,
        "chunk": family.CHUNK,
        "jobs": jobs,
        "counts": counts,
        "limit_tolerance": LIMIT_TOLERANCE,
        "allocators": {},
    }
    progress = _Progress(counts, done, jobs, stream)
    last_write = time.perf_counter()

    def write_summary() -> None:
        result["load_after"] = load_average()
        result["allocators"] = {
            name: merge(list(done[name].values()), counts[name]) for name in names if done[name]
        }
        write_json(out / "soak.json", result)
        write_atomic(out / "soak.md", markdown(result))

    def finished(record: dict[str, Any]) -> None:
        nonlocal last_write
        name = record["name"]
        write_json(_chunk_path(out, name, record["chunk"]), {"settings": settings, "record": record})
        done[name][record["chunk"]] = record
        progress.chunk_done(name)
        complete = sum(r["problems"] for r in done[name].values()) == counts[name]
        if complete or time.perf_counter() - last_write >= 60:
            write_summary()
            last_write = time.perf_counter()

    if jobs == 1:
        for name, chunk in todo:
            # One BLAS thread, as in a simulation (platoon_opt.simulation.simulate): the matrices are tiny.
            with threadpool_limits(limits=1, user_api="blas"):
                finished(soak_chunk(name, factory, seed, chunk, problems, degenerate_rate))
    elif todo:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            futures = [
                pool.submit(_soak_chunk_in_worker, name, seed, chunk, problems, degenerate_rate)
                for name, chunk in todo
            ]
            try:
                for future in as_completed(futures):
                    finished(future.result())
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    write_summary()
    return result


def show(
    index: int, seed: int = 0, degenerate_rate: float = DEGENERATE_RATE, allocators: Sequence[str] = ()
) -> str:
    """Problem ``index`` of ``seed`` in words, and what each allocator in ``allocators`` makes of
    it (a fresh allocator, warmed on problem ``index - 1`` as in the soak)."""
    from platoon_opt.solvers import get_allocator

    spec = family.spec_at(seed, index, degenerate_rate)
    problem = spec.build()
    np.set_printoptions(precision=17, linewidth=110)
    lines = [f"problem {index} of seed {seed}: kind {spec.kind}, n = {spec.n}", repr(spec)]
    lines.append(f"exempt: {problem.exempt.astype(int)}, gear: {problem.gear}")
    lines.append(f"nominal:\n{problem.nominal}")
    for name in allocators:
        allocator = get_allocator(name)
        if index > 0:
            try:
                allocator.allocate(family.spec_at(seed, index - 1, degenerate_rate).build())
            except Exception:
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.soak", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--problems",
        type=int,
        default=DEFAULT_PROBLEMS,
        help=f"problems per allocator (default {DEFAULT_PROBLEMS:,})",
    )
    parser.add_argument(
        "--jobs", type=int, default=1, help="worker processes, each solving whole chunks (default 1)"
    )
    parser.add_argument("--allocators", help="comma-separated registry names (default: every registered one)")
    parser.add_argument(
        "--out", default="benchmarks/results", help="output folder (default: benchmarks/results)"
    )
    parser.add_argument("--seed", type=int, default=0, help="problem seed (default 0)")
    parser.add_argument(
        "--degenerate-rate", type=float, default=DEGENERATE_RATE, help="fraction of degenerate problems"
    )
    parser.add_argument("--fresh", action="store_true", help="recompute the chunks an earlier run finished")
    parser.add_argument(
        "--show", type=int, metavar="INDEX", help="print problem INDEX (and run --allocators on it)"
    )
    args = parser.parse_args(argv)
    from platoon_opt.solvers import available_allocators

    names = [name for name in (args.allocators or "").split(",") if name]
    unknown = [name for name in names if name not in available_allocators()]
    if unknown:
        parser.error(f"unknown allocator(s) {', '.join(unknown)}; known: {', '.join(available_allocators())}")
    if args.problems < 1:
        parser.error(f"--problems must be >= 1, got {args.problems}")
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    if not 0.0 <= args.degenerate_rate <= 1.0:
        parser.error(f"--degenerate-rate must lie in [0, 1], got {args.degenerate_rate}")
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
            command=" ".join(["python -m benchmarks.soak", *(sys.argv[1:] if argv is None else argv)]),
        )
    except KeyboardInterrupt:
        print(
            f"\ninterrupted: finished chunks are in {args.out}/soak-chunks (the same command resumes)",
            file=sys.stderr,
        )
        return 130
    bad = {
        name: entry
        for name, entry in result["allocators"].items()
        if entry["exceptions"] or entry["non_finite"] or entry["limit_violations"] or entry["build_errors"]
    }
    print(
        f"wrote {args.out}/soak.json and soak.md; "
        + (f"problems in: {', '.join(bad)}" if bad else "no failures")
    )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
