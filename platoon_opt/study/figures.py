"""Figures of runs (matplotlib, Agg backend): trajectories (paper Figs. 2, 5) and task
errors over time (Fig. 3)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from platoon_opt.simulation import Trajectory  # noqa: E402


def draw_trajectory(ax: Axes, trajectory: Trajectory, snapshots: int = 8) -> None:
    """Unit paths, units as triangles oriented by heading and the target as diamonds at
    ``snapshots`` instants, obstacles as circles."""
    for center, radius in zip(trajectory.obstacles.centers, trajectory.obstacles.radii):
        ax.add_patch(Circle(center, radius, facecolor="0.85", edgecolor="0.3"))
    ax.plot(trajectory.x, trajectory.y, lw=0.6, color="tab:blue", alpha=0.5)
    ax.plot(trajectory.target[:, 0], trajectory.target[:, 1], ":", color="tab:red", lw=1)
    for k in np.linspace(0, trajectory.steps, snapshots).astype(int):
        for x, y, theta in zip(trajectory.x[k], trajectory.y[k], trajectory.theta[k]):
            # marker (3, 0, angle): a triangle whose apex points at angle + 90 degrees.
            ax.plot(x, y, marker=(3, 0, np.degrees(theta) - 90), ms=7, color="tab:blue", ls="")
        ax.plot(*trajectory.target[k], marker="D", ms=6, color="tab:red", ls="")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(trajectory.allocator)


def plot_trajectories(trajectories: Sequence[Trajectory], path: str | Path) -> Path:
    """Side-by-side trajectory panels, one per run; saved as PNG at ``path``."""
    fig, axes = plt.subplots(1, len(trajectories), figsize=(6 * len(trajectories), 5), squeeze=False)
    for ax, trajectory in zip(axes[0], trajectories):
        draw_trajectory(ax, trajectory)
    fig.suptitle(f"{trajectories[0].scenario}, seed {trajectories[0].seed}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


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
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
