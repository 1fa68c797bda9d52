"""Thinned trajectories kept beside a run's result for the figures (every ``TRACK_STRIDE``-th
instant, compressed ``.npz``)."""

from __future__ import annotations

import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.trajectory import Trajectory

# Figures need a run's trajectory, not every step of it: keep every TRACK_STRIDE-th instant.
TRACK_STRIDE = 5


_TRACK_ARRAYS = (
    "t", "x", "y", "theta", "alpha", "gear", "task_value", "desired", "target",
    "status", "iterations", "task_residual", "deviation", "solve_time", "fell_back", "exempt", "solved",
    "program_changed", "slack",
)  # fmt: skip
# The arrays of steps (T,), the others of instants (T + 1,).
_PER_STEP = {
    "status", "iterations", "task_residual", "deviation", "solve_time", "fell_back", "exempt", "solved",
    "program_changed", "slack",
}  # fmt: skip


def thin(trajectory: Trajectory, stride: int) -> Trajectory:
    """Every ``stride``-th instant of ``trajectory`` (and the steps starting there), as a
    trajectory with time step ``stride * dt``; trailing steps that do not fill a stride are
    dropped."""
    steps = trajectory.steps // stride
    instants, starts = slice(0, steps * stride + 1, stride), slice(0, steps * stride, stride)
    arrays = {
        name: getattr(trajectory, name)[starts if name in _PER_STEP else instants] for name in _TRACK_ARRAYS
    }
    return replace(trajectory, **arrays, dt=trajectory.dt * stride)


def track_bytes(trajectory: Trajectory) -> bytes:
    """``trajectory`` thinned to every ``TRACK_STRIDE``-th instant, as compressed ``.npz`` bytes."""
    thinned = thin(trajectory, TRACK_STRIDE)
    meta = {k: getattr(thinned, k) for k in ("task_names", "scenario", "allocator", "seed", "dt")}
    arrays = {name: getattr(thinned, name) for name in _TRACK_ARRAYS}
    arrays["status"] = arrays["status"].astype(str)
    buffer = io.BytesIO()
    np.savez_compressed(
        buffer,
        **arrays,
        obstacle_centers=thinned.obstacles.centers,
        obstacle_radii=thinned.obstacles.radii,
        meta=np.array(json.dumps(meta)),
    )
    return buffer.getvalue()


def load_track(path: str | Path) -> Trajectory:
    """A thinned trajectory kept by a run with ``keep_track`` (every ``TRACK_STRIDE``-th instant)."""
    with np.load(path) as data:
        meta = json.loads(str(data["meta"]))
        # A track kept before ``solved`` (``program_changed``, ``slack``) was recorded has none:
        # every step solved (none changed the program, none needed a slack).
        arrays = {name: data[name] for name in _TRACK_ARRAYS if name in data}
        obstacles = CircularObstacles(data["obstacle_centers"].reshape(-1, 2), data["obstacle_radii"])
    arrays["status"] = arrays["status"].astype(object)
    return Trajectory(**arrays, obstacles=obstacles, **{**meta, "task_names": tuple(meta["task_names"])})
