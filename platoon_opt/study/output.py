"""Writing results: every file goes through a temporary file and a rename, so a reader
never sees half a file and an interrupted run leaves only complete ones."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from platoon_opt.trajectory import Trajectory


def write_atomic(path: str | Path, data: str | bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file in the same folder and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as handle:
            handle.write(data)
        os.chmod(temporary, 0o644)  # mkstemp creates 0600; results are meant to be shared
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.integer, np.bool_)):
        return value.item()
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else str(value)  # JSON has no inf/nan
    return value


def write_json(path: str | Path, value: Any) -> Path:
    """Atomically write ``value`` as indented JSON (numpy values converted, inf as "inf")."""
    return write_atomic(path, json.dumps(_jsonable(value), indent=2) + "\n")


def write_csv(path: str | Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> Path:
    """Atomically write a CSV file."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(header)
    writer.writerows(rows)
    return write_atomic(path, buffer.getvalue())


def write_timeseries(path: str | Path, trajectory: Trajectory) -> Path:
    """One row per instant: time, target, task values and desired values, the allocation of
    the step that starts there (status, residual, deviation, solve time: empty for a run of the
    compiled engine, which does not time its allocation apart from the step), each unit's state."""
    n = trajectory.x.shape[1]
    header = ["t", "target_x", "target_y"]
    header += [f"f_{k}" for k in trajectory.task_names] + [f"fd_{k}" for k in trajectory.task_names]
    header += ["status", "iterations", "task_residual", "deviation", "solve_time"]
    for i in range(n):
        header += [f"x_{i}", f"y_{i}", f"theta_{i}", f"alpha_{i}", f"gear_{i}"]
    rows = []
    for k in range(trajectory.steps + 1):
        step = k if k < trajectory.steps else None
        row: list[Any] = [f"{trajectory.t[k]:.6g}", *trajectory.target[k], *trajectory.task_value[k]]
        row += list(trajectory.desired[k])
        row += (
            [
                trajectory.status[step],
                int(trajectory.iterations[step]),
                trajectory.task_residual[step],
                trajectory.deviation[step],
                trajectory.solve_time[step] if np.isfinite(trajectory.solve_time[step]) else "",
            ]
            if step is not None
            else ["", "", "", "", ""]
        )
        units = np.stack(
            (trajectory.x[k], trajectory.y[k], trajectory.theta[k], trajectory.alpha[k], trajectory.gear[k]),
            axis=1,
        )
        row += units.ravel().tolist()
        rows.append(row)
    return write_csv(path, header, rows)
