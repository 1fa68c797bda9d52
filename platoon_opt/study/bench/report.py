"""A bench run (bench.json) as markdown tables (``markdown``) and as a log-log plot of time
against n (``plot``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402

from platoon_opt.study.figures import save, styled  # noqa: E402


def ratio_text(value: float) -> str:
    """A ratio with two significant digits below 10, else a whole number."""
    return f"{value:.2g}" if value < 10 else f"{value:,.0f}"


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.3g}" if seconds < 1 else f"{seconds * 1e3:,.0f}"


def _threads(result: dict[str, Any]) -> str:
    threads = result.get("arguments", {}).get("threads")
    return "JAX's pool: one thread per core" if threads is None else f"JAX's pool: {threads} thread(s)"


def _time(record: dict[str, Any]) -> str:
    ratio = f" (x{ratio_text(record['ratio_to_dual'])})" if "ratio_to_dual" in record else ""
    return _ms(record["time"]) + ratio


def _per_size(scale: list[dict[str, Any]], title: str, cell: Callable[[dict[str, Any]], str]) -> list[str]:
    """A table of the scale part's records: an allocator per row, a size per column, ``cell`` of
    each record (empty where it was not measured)."""
    sizes = sorted({r["n"] for r in scale})
    by = {(r["allocator"], r["n"]): r for r in scale}
    lines = [f"**{title}**", "", "| allocator | " + " | ".join(f"n = {n:,}" for n in sizes) + " |"]
    lines.append("|---|" + "---|" * len(sizes))
    for label in dict.fromkeys(r["allocator"] for r in scale):
        cells = ["" if (label, n) not in by else cell(by[(label, n)]) for n in sizes]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def markdown(result: dict[str, Any]) -> str:
    """The tables of a run (bench.json) in markdown."""
    records = result["records"]
    info = result["machine"]
    lines = [
        f"Machine: {info['cpu']}, {info['cores']} cores; load average {result['load_before']:.1f} before, "
        f"{result['load_after']:.1f} after; Python {info['python']}, numpy {info['numpy']}, "
        f"Clarabel {info['clarabel']}, OSQP {info['osqp']}; {_threads(result)}. Times are wall-clock "
        "medians (ms).",
        "",
    ]
    scale = [r for r in records if r["kind"] == "scale" and "time" in r]
    if scale:  # the scale part ran
        lines += _per_size(scale, "Time per allocation (ms) and ratio to the dual on the same program", _time)
        lines += [""]
        lines += _per_size(
            scale,
            "Build / bare solve (ms) and peak traced memory (MB) per allocation",
            lambda r: f"{_ms(r['build'])} / {_ms(r['solve'])}, {r['peak_memory_mb']:.1f} MB",
        )
    steps = [r for r in records if r["kind"] == "step"]
    if steps:
        lines += ["", "**Whole control step with the dual, consecutive steps (ms)**", ""]
        lines.append(
            "| n | problem (nominal, repulsion) | allocation | vehicles | step | floor (1 pass) | peak MB |"
        )
        lines.append("|---|---|---|---|---|---|---|")
        for r in steps:
            lines.append(
                f"| {r['n']:,} | {_ms(r['problem'])} | {_ms(r['allocate'])} | {_ms(r['vehicles'])} | "
                f"{_ms(r['time'])} | {r['floor'] * 1e3:.4f} | {r['peak_memory_mb']:.1f} |"
            )
    small = [r for r in records if r["kind"] == "small"]
    if small:
        lines += [
            "",
            f"**n = 8 along the closed loop ({small[0]['steps']} steps): "
            "dual vs Clarabel's bare solve (us)**",
            "",
        ]
        lines.append(
            "| dual allocator | Clarabel solve() of | dual (median) | solve() (median) | ratio | CPU ratio "
            "| passes |"
        )
        lines.append("|---|---|---|---|---|---|---|")
        for r in small:
            lines.append(
                f"| {r['allocator']} | {r['reference']} | {r['time'] * 1e6:.0f} | "
                f"{r['clarabel_solve'] * 1e6:.0f} | {r['ratio']:.2f} | {r['cpu_ratio']:.2f} | "
                f"{r['evaluations']:.2f} |"
            )
    loops = [r for r in records if r["kind"] == "closed_loop"]
    if loops:
        lines += [
            "",
            f"**Closed loop, {loops[0]['scenario']} with n units: simulated seconds per wall second per "
            "platoon (x real time), us per platoon-step, compile time, memory of the compiled call**",
            "",
            "| allocator | path | n | batch | steps | x real time | us per platoon-step | compile (s) "
            "| memory (MB) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in loops:
            lines.append(
                f"| {r['allocator']} | {r['path']} | {r['n']:,} | {r['batch']:,} | {r['steps']} | "
                f"{r['speed']:,.0f} | {r['step_time'] * 1e6:,.1f} | {r['compile']:.1f} | "
                f"{r['memory'] / 1e6:,.0f} |"
            )
        skipped = [r for r in records if r["kind"] == "closed_loop_skipped"]
        if skipped:
            lines.append("")
            lines += [
                f"Left out: {r['allocator']} at n = {r['n']:,}, batch {r['batch']:,} ({r['reason']})."
                for r in skipped
            ]
    return "\n".join(lines) + "\n"


@styled
def plot(result: dict[str, Any], path: Path) -> None:
    """Log-log time per allocation against n, with the control step and the floor."""
    records = result["records"]
    figure, axes = plt.subplots(figsize=(8, 5.5))
    scale = [r for r in records if r["kind"] == "scale" and "time" in r]
    for label in dict.fromkeys(r["allocator"] for r in scale):
        points = sorted((r["n"], r["time"]) for r in scale if r["allocator"] == label)
        style = "-" if label.startswith("dual") else "--"
        axes.loglog(*zip(*points), style, marker="o", markersize=3, label=label)
    steps = sorted((r["n"], r["time"], r["floor"]) for r in records if r["kind"] == "step")
    if steps:
        n, step, floor = zip(*steps)
        axes.loglog(n, step, "k-", linewidth=2, label="control step (dual)")
        axes.loglog(n, floor, "k:", label="floor: one pass over the state")
    axes.set_xlabel("units n")
    axes.set_ylabel("time (s)")
    axes.set_title(
        f"Allocation time against n ({result['machine']['cpu']}, {result['machine']['cores']} cores)"
    )
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7, ncol=2)
    figure.tight_layout()
    save(figure, path)
