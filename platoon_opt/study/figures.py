"""Figures (matplotlib, Agg backend): trajectories (the paper's Figs. 2 and 5), task errors over
time (Fig. 3), integrated errors against m (Fig. 4) and the ablation; one palette for all."""

from __future__ import annotations

import functools
import io
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from cycler import cycler  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402
from matplotlib.typing import RcKeyType  # noqa: E402

from platoon_opt.metrics import ERROR_METRICS
from platoon_opt.study.output import write_atomic  # noqa: E402
from platoon_opt.study.statistics import METRICS, Comparison, RunTable, interval  # noqa: E402
from platoon_opt.trajectory import Trajectory  # noqa: E402

# One palette for every figure: Okabe and Ito's colours, told apart with any colour vision; units
# are drawn in the first, the target in the second.
PALETTE = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442", "#000000")
UNITS, TARGET = PALETTE[0], PALETTE[1]
STYLE: dict[RcKeyType, Any] = {
    "axes.prop_cycle": cycler(color=PALETTE),
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "axes.grid": True,
    "grid.alpha": 0.3,
}
DPI = 110
# Characters of 9-point legend text across the 11-inch sweep figure.
LEGEND_CHARACTERS = 150

Plot = TypeVar("Plot", bound=Callable[..., Any])


def styled(plot: Plot) -> Plot:
    """Draw ``plot`` in the one style (``STYLE``) without changing matplotlib's global settings."""

    @functools.wraps(plot)
    def draw(*args: Any, **kwargs: Any) -> Any:
        with plt.rc_context(STYLE):
            return plot(*args, **kwargs)

    return draw  # type: ignore[return-value]


def save(figure: Figure, path: str | Path) -> Path:
    """Write ``figure`` as a PNG at ``path`` atomically, and close it."""
    image = io.BytesIO()
    figure.savefig(image, format="png", dpi=DPI)
    plt.close(figure)
    return write_atomic(path, image.getvalue())


def draw_trajectory(ax: Axes, trajectory: Trajectory, snapshots: int = 8) -> None:
    """Unit paths, units as triangles oriented by heading and the target as diamonds at
    ``snapshots`` instants, obstacles as circles."""
    for center, radius in zip(trajectory.obstacles.centers, trajectory.obstacles.radii):
        ax.add_patch(Circle(center, radius, facecolor="0.85", edgecolor="0.3"))
    ax.plot(trajectory.x, trajectory.y, lw=0.6, color=UNITS, alpha=0.5)
    ax.plot(trajectory.target[:, 0], trajectory.target[:, 1], ":", color=TARGET, lw=1)
    for k in np.linspace(0, trajectory.steps, snapshots).astype(int):
        for x, y, theta in zip(trajectory.x[k], trajectory.y[k], trajectory.theta[k]):
            # marker (3, 0, angle): a triangle whose apex points at angle + 90 degrees.
            ax.plot(x, y, marker=(3, 0, np.degrees(theta) - 90), ms=7, color=UNITS, ls="")
        ax.plot(*trajectory.target[k], marker="D", ms=6, color=TARGET, ls="")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(trajectory.allocator)


@styled
def plot_trajectories(trajectories: Sequence[Trajectory], path: str | Path) -> Path:
    """Side-by-side trajectory panels, one per run; saved as PNG at ``path``."""
    fig, axes = plt.subplots(1, len(trajectories), figsize=(6 * len(trajectories), 5), squeeze=False)
    for ax, trajectory in zip(axes[0], trajectories):
        draw_trajectory(ax, trajectory)
    fig.suptitle(f"{trajectories[0].scenario}, seed {trajectories[0].seed}")
    fig.tight_layout()
    return save(fig, path)


@styled
def plot_errors(trajectories: Sequence[Trajectory], path: str | Path, start: float = 0.0) -> Path:
    """Task errors over time from ``start`` s: mean-position distance and each other
    component's error, one line per run; saved as PNG at ``path``."""
    names = [k for k in trajectories[0].task_names if k not in ("mean_x", "mean_y")]
    fig, axes = plt.subplots(1 + len(names), 1, figsize=(8, 2.2 * (1 + len(names))), sharex=True)
    for trajectory in trajectories:
        keep = trajectory.t >= start
        mean = np.column_stack((trajectory.x.mean(axis=1), trajectory.y.mean(axis=1)))
        distance = np.linalg.norm(mean - trajectory.target, axis=1)
        axes[0].plot(trajectory.t[keep], distance[keep], label=trajectory.allocator)
        for ax, name in zip(axes[1:], names):
            value, desired = trajectory.component(name)
            ax.plot(trajectory.t[keep], (value - desired)[keep])
    axes[0].set_ylabel("|mean - target| (m)")
    for ax, name in zip(axes[1:], names):
        ax.set_ylabel(f"{name} error" + (" (m$^2$)" if name.startswith(("var", "cov")) else ""))
    axes[-1].set_xlabel("t (s)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    return save(fig, path)


@styled
def plot_sweep(table: RunTable, study: Comparison, scenario: str, path: str | Path) -> Path:
    """Fig. 4 analog: integrated errors against m (mean over seeds, 95 % intervals), every
    other allocator as a horizontal band (mean line, interval shaded); one panel per error."""
    iterative = [
        c for c in study.configs if c.iteration_count is not None and table.has(scenario, "base", c.label)
    ]
    others = [c for c in study.configs if c.iteration_count is None and table.has(scenario, "base", c.label)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharex=True)
    colors = list(PALETTE[1:])
    for ax, key in zip(axes.ravel(), ERROR_METRICS):
        metric = METRICS[key]
        ms, means, halves = [], [], []
        for config in iterative:
            values = table.values(
                scenario, "base", config.label, key, table.seeds(scenario, "base", config.label)
            )
            low, high = interval(values)
            ms.append(config.iteration_count)
            means.append(values.mean())
            halves.append((high - low) / 2 if math.isfinite(low) else 0.0)
        ax.errorbar(ms, means, yerr=halves, marker="o", color="black", capsize=3, label="iterative, m")
        # Line styles too: allocators solving the same problem (qp and dual) coincide.
        styles = ("-", "--", ":", "-.")
        for k, (color, config) in enumerate(zip(colors * 3, others)):
            values = table.values(
                scenario, "base", config.label, key, table.seeds(scenario, "base", config.label)
            )
            low, high = interval(values)
            ax.axhline(values.mean(), color=color, lw=1.8, ls=styles[k % len(styles)], label=config.label)
            if math.isfinite(low):
                ax.axhspan(low, high, color=color, alpha=0.15, lw=0)
        ax.set_title(metric.title)
        ax.set_ylabel(f"integrated |error| ({metric.unit.replace('^2', '$^2$')})")
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("iterations m of the paper's projection")
        if ms:
            ax.set_xticks(ms)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    # As many columns as the longest label lets fit across the figure, and room below for the rows.
    columns = max(1, min(len(labels), 6, LEGEND_CHARACTERS // (max(map(len, labels)) + 6)))
    fig.legend(handles, labels, loc="lower center", ncol=columns, fontsize=9)
    fig.suptitle(f"{scenario}: integrated errors over {len(study.seeds)} seeds (mean, 95 % interval)")
    fig.tight_layout(rect=(0, 0.01 + 0.03 * math.ceil(len(labels) / columns), 1, 1))
    return save(fig, path)


@styled
def plot_ablation(
    summary: Mapping[tuple[str, str, str, str], Mapping[str, Any]],
    study: Comparison,
    papers: Mapping[str, Mapping[str, Any]],
    path: str | Path,
) -> Path:
    """Percent change against m = 0 at the paper's m under each ablation variant (bars with
    95 % intervals), the paper's numbers (``papers``: scenario -> its ``m``, ``label`` and
    ``changes``) as black diamonds; one panel per paper scenario."""
    scenarios = [s.name for s in study.scenarios if s.name in papers]
    fig, axes = plt.subplots(1, len(scenarios), figsize=(6.5 * len(scenarios), 4.8), squeeze=False)
    variants = ["base"] + [v.name for v in study.variants]
    for ax, scenario in zip(axes[0], scenarios):
        paper = papers[scenario]
        label = f"m={paper['m']}"
        keys = list(paper["changes"])
        shown = [v for v in variants if (scenario, v, label, keys[0]) in summary]
        width = 0.8 / max(len(shown), 1)
        for j, variant in enumerate(shown):
            rows = [summary[(scenario, variant, label, k)] for k in keys]
            x = np.arange(len(keys)) + (j - (len(shown) - 1) / 2) * width
            change = np.array([r["change"] for r in rows])
            error = np.array(
                [[r["change"] - r["change_low"], r["change_high"] - r["change"]] for r in rows]
            ).T
            ax.bar(x, change, width, yerr=np.nan_to_num(error), capsize=2, label=variant)
        ax.plot(np.arange(len(keys)), [paper["changes"][k] for k in keys], "D", color="black", label="paper")
        ax.axhline(0, color="0.3", lw=0.8)
        # A few wide intervals would flatten the rest: clip the axis (the tables have the numbers).
        bottom, top = ax.get_ylim()
        ax.set_ylim(max(bottom, -150.0), min(top, 300.0))
        ax.set_xticks(
            np.arange(len(keys)), [METRICS[k].title.replace(" after transient", "\nafter 4 s") for k in keys]
        )
        ax.set_ylabel(f"change of integrated error at {label} vs m=0 (%, axis clipped)")
        ax.set_title(f"{scenario} ({paper['label']})")
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return save(fig, path)


@styled
def plot_runs(
    panels: Sequence[tuple[str, Trajectory]], scenario: str, transient: float, folder: Path
) -> list[Path]:
    """Fig. 2/5 analog (trajectories side by side, one per (title, trajectory) panel) and
    Fig. 3 analog (task errors over time after the common transient); returns the PNG paths."""
    trajectories = [trajectory for _, trajectory in panels]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.6 * len(panels), 5.4), squeeze=False)
    for ax, (title, trajectory) in zip(axes[0], panels):
        draw_trajectory(ax, trajectory)
        ax.set_title(f"{title}\n{trajectory.allocator}", fontsize=10)
    fig.suptitle(
        f"{scenario}, seed {trajectories[0].seed}: units (triangles, apex = heading), "
        "target (diamonds), obstacles (circles)"
    )
    fig.tight_layout()
    trajectory_path = folder / f"trajectories_{scenario}.png"
    save(fig, trajectory_path)
    errors_path = plot_errors(trajectories, folder / f"errors_{scenario}.png", start=transient)
    return [trajectory_path, errors_path]
