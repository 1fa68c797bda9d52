"""Statistics and runs as markdown text: numbers, means with intervals, changes, tables."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any


def number(value: float, digits: int = 4) -> str:
    """``value`` to ``digits`` significant digits, "—" if not finite."""
    return f"{value:.{digits}g}" if math.isfinite(value) else "—"


def mean_text(row: Mapping[str, Any] | None) -> str:
    """A statistics row's mean ± the half-width of its 95 % interval."""
    if row is None or not math.isfinite(row["mean"]):
        return "—"
    if not math.isfinite(row["ci_low"]):
        return number(row["mean"])
    return f"{number(row['mean'])} ± {number((row['ci_high'] - row['ci_low']) / 2, 2)}"


def change_text(row: Mapping[str, Any] | None) -> str:
    """A statistics row's percent change with its 95 % interval."""
    if row is None or not math.isfinite(row["change"]):
        return "—"
    if not math.isfinite(row["change_low"]):
        return f"{row['change']:+.1f} %"
    return f"{row['change']:+.1f} % [{row['change_low']:+.1f}, {row['change_high']:+.1f}]"


def percent(value: float) -> str:
    """A fraction in [0, 1] as a whole percentage."""
    return f"{100 * value:.0f} %" if math.isfinite(value) else "—"


def table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def duration_text(seconds: float) -> str:
    """ "42 s" or "3.5 min"."""
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def cpu_minutes(runs: Iterable[Mapping[str, Any]]) -> float:
    """The CPU time of ``runs`` in minutes."""
    return sum(float(r.get("cpu_time", math.nan)) for r in runs) / 60


def seeds_text(seeds: Sequence[int]) -> str:
    """``0..19`` for a range, else the seeds listed."""
    seeds = list(seeds)
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))) and len(seeds) > 2:
        return f"{seeds[0]}..{seeds[-1]}"
    return ", ".join(map(str, seeds))
