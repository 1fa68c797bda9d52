"""The soak's summary: one allocator's entry of soak.json merged from its chunk records
(``merge``), and soak.json as markdown tables (``markdown``).

Contract: ``merge`` takes any subset of an allocator's chunk records in any order and gives the
same entry for the same records; counts are sums, times are pooled over every call.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from platoon_opt.study.problems import DEGENERATE_KINDS, KINDS, LIMIT_TOLERANCE, MAX_OBSTACLES, MAX_UNITS

# Failure examples kept per category (per chunk, and in the merged entry).
EXAMPLES = 5


def merge(records: Sequence[dict[str, Any]], target: int) -> dict[str, Any]:
    """One allocator's entry of soak.json from its chunk records (any subset, in any order):
    counts summed, times pooled (median, p95, max, mean per call), the first ``EXAMPLES``
    examples per category in problem order. ``wall_time`` is the sum over chunks (one core's
    time), so ``problems_per_second`` is per core whatever ``--jobs`` was."""
    records = sorted(records, key=lambda record: record["chunk"])
    last = records[-1]
    exceptions: Counter[str] = Counter()
    statuses: Counter[str] = Counter()
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
        key: sum(record.get(key, 0) for record in records)
        for key in ("build_errors", "non_finite", "limit_violations", "fallbacks", "program_changes")
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


def _problems(entry: dict[str, Any]) -> str:
    done = f"{entry['problems']:,}"
    return done if entry["complete"] else f"{done} of {entry['target']:,} (partial)"


def markdown(result: dict[str, Any]) -> str:
    """soak.json as tables."""
    info = result["machine"]
    tolerance = result.get("limit_tolerance", LIMIT_TOLERANCE)
    lines = [
        f"# Soak: every allocator on random allocation problems (seed {result['seed']})",
        "",
        f"{result['date']}; {info['cpu']}, {info['cores']} cores, {info['platform']}; "
        f"Python {info['python']}, numpy {info['numpy']}. Problems: 2-{MAX_UNITS} units, "
        f"0-{MAX_OBSTACLES} obstacles, {result['degenerate_rate']:.0%} degenerate "
        f"({', '.join(DEGENERATE_KINDS)}). A limit violation is a unit outside the set its allocator "
        f"promises by more than {tolerance:g} m/s. A program change is a fallback answered by another "
        "program than the allocator's (a cone variant on the polygon, strict priority's stage 1 "
        "alone, a projection; `Allocation.program_changed`). Times: per allocate call, wall clock (CPU: "
        "the process's CPU time, threads included; on a shared machine the wall time includes waiting); "
        f"problems/s per worker process ({result.get('jobs', 1)} ran in parallel, one BLAS thread each).",
        "",
        "| allocator | problems | exceptions | non-finite | limit violations | worst excess (m/s) "
        "| fallbacks | program changes | median (µs) | p95 (µs) | median CPU (µs) | problems/s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    entries = result["allocators"]
    for name, entry in entries.items():
        lines.append(
            f"| {name} | {_problems(entry)} | {entry['exceptions']} | {entry['non_finite']} | "
            f"{entry['limit_violations']} | {entry['worst_excess']:.1e} | {entry['fallbacks']} | "
            f"{entry.get('program_changes', 0)} | "
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
            triple = " / ".join(str(counts.get(key, 0)) for key in ("fallbacks", "violations", "exceptions"))
            cells.append(f"{triple} of {counts.get('problems', 0):,}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    failing = {name: entry["examples"] for name, entry in entries.items() if entry["examples"]}
    if failing:
        lines += ["", "## Examples (rebuild one with `platoon-opt soak --show INDEX`)", ""]
        for name, examples in failing.items():
            for category, items in examples.items():
                for item in items:
                    lines.append(f"- {name}, {category}: " + ", ".join(f"{k} = {v}" for k, v in item.items()))
    return "\n".join(lines) + "\n"
