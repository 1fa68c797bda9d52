"""Scores of a run: the paper's integrated absolute errors, gear flips, obstacle clearance,
compute time."""

from __future__ import annotations

import math

import numpy as np

from platoon_opt.avoidance import BRUTE_FORCE_UNITS, nearest_unit
from platoon_opt.simulation import Trajectory

# Metrics where smaller is better (the harness compares allocators on these).
ERROR_METRICS = ("mean_position", "mean_position_after_transient", "var_x", "var_y")
# Pairwise distances held at once by the minimum unit distance.
_PAIRS = 1 << 18


def _integrate(values: np.ndarray, dt: float) -> float:
    """Trapezoidal integral of samples spaced ``dt`` apart."""
    if values.shape[0] < 2:
        return 0.0
    return float(dt * (values.sum() - 0.5 * (values[0] + values[-1])))


def integrated_errors(trajectory: Trajectory, transient: float = 4.0) -> dict[str, float]:
    """Integrated absolute errors of a run (the paper's metric), whole run and after ``transient`` s.

    Keys:
        mean_position, mean_position_after_transient: integral of the Euclidean distance of
            the platoon mean from the target (m s).
        <component>, <component>_after_transient: integral of |f_k - f_d,k| for every task
            component other than the means (e.g. var_x, var_y in m^2 s).
        gear_flips: total number of forward/backing switches over all units.
        time_inside_obstacles: unit-seconds spent inside an obstacle (s).
        min_clearance: smallest distance of any unit from any obstacle surface (m; negative
            inside; inf without obstacles).
        min_unit_distance: smallest distance between two units (m).
        solve_time_median, solve_time_p95: allocation wall time per step (s), over every step,
            those that reused an earlier solve (``nmpc`` handing its plan, about 0 s) included.
        solve_steps: steps whose allocation ran a solve (``Trajectory.solved``): every step
            for every allocator but ``nmpc``, whose plan steps reuse its last solve.
        solve_time_per_solve_median, solve_time_per_solve_p95: allocation wall time per solve
            (s), over the ``solve_steps`` alone; nan if there is none.
        fallback_steps: steps whose allocation fell back (the allocator's own fallback, e.g.
            ``nmpc``'s to ``qp``, or the controller's projection when the allocator raised).
        program_changes: steps whose allocation answered another program than its allocator
            poses (``Allocation.program_changed``: a cone variant on the polygon, strict
            priority's stage 1 alone, a projection); a fallback to another exact solver of the
            same program is a fallback step but no program change.
        slack_steps: steps on which some unit's barrier rows had to be relaxed (it started the
            step unsafe: inside an inflated obstacle or closer than the safety distance; 0
            without barriers).
    """
    dt = trajectory.dt
    after = trajectory.t >= transient - 1e-12
    mean = np.column_stack((trajectory.x.mean(axis=1), trajectory.y.mean(axis=1)))
    distance = np.linalg.norm(mean - trajectory.target, axis=1)
    result = {
        "mean_position": _integrate(distance, dt),
        "mean_position_after_transient": _integrate(distance[after], dt),
    }
    for k, name in enumerate(trajectory.task_names):
        if name in ("mean_x", "mean_y"):
            continue
        error = np.abs(trajectory.task_value[:, k] - trajectory.desired[:, k])
        result[name] = _integrate(error, dt)
        result[f"{name}_after_transient"] = _integrate(error[after], dt)
    result["gear_flips"] = int(np.count_nonzero(np.diff(trajectory.gear, axis=0)))
    positions = np.stack((trajectory.x.ravel(), trajectory.y.ravel()), axis=1)
    if len(trajectory.obstacles):
        clearance = trajectory.obstacles.nearest(positions)[0]
        result["time_inside_obstacles"] = float(
            np.count_nonzero(clearance[: -trajectory.x.shape[1]] < 0) * dt
        )
        result["min_clearance"] = float(clearance.min())
    else:
        result["time_inside_obstacles"] = 0.0
        result["min_clearance"] = float("inf")
    result["min_unit_distance"] = _min_unit_distance(trajectory)
    result.update(_solve_times(trajectory))
    result["fallback_steps"] = int(np.count_nonzero(trajectory.fell_back))
    changed = trajectory.program_changed
    result["program_changes"] = 0 if changed is None else int(np.count_nonzero(changed))
    result["slack_steps"] = 0 if trajectory.slack is None else int(np.count_nonzero(trajectory.slack))
    return result


def _solve_times(trajectory: Trajectory) -> dict[str, float]:
    """The allocation time per step (0 without steps) and per solve (nan without solves), s."""
    times = trajectory.solve_time
    solved = np.ones(times.shape[0], dtype=bool) if trajectory.solved is None else trajectory.solved
    solves = times[solved]
    return {
        "solve_time_median": float(np.median(times)) if times.size else 0.0,
        "solve_time_p95": float(np.percentile(times, 95)) if times.size else 0.0,
        "solve_steps": int(solves.size),
        "solve_time_per_solve_median": float(np.median(solves)) if solves.size else math.nan,
        "solve_time_per_solve_p95": float(np.percentile(solves, 95)) if solves.size else math.nan,
    }


def _min_unit_distance(trajectory: Trajectory) -> float:
    """Smallest pairwise distance over the run: all pairs of a block of instants at once for a
    small platoon (at most ``_PAIRS`` distances in memory), else one k-d tree per instant."""
    n = trajectory.x.shape[1]
    if n > BRUTE_FORCE_UNITS:
        return min(
            float(nearest_unit(np.column_stack((x, y)), np.inf)[0].min())
            for x, y in zip(trajectory.x, trajectory.y)
        )
    best = np.inf
    block = max(1, _PAIRS // (n * n))
    units = np.arange(n)
    for start in range(0, trajectory.x.shape[0], block):
        x, y = trajectory.x[start : start + block], trajectory.y[start : start + block]
        distance = np.hypot(x[:, :, None] - x[:, None, :], y[:, :, None] - y[:, None, :])
        distance[:, units, units] = np.inf
        best = min(best, float(distance.min()))
    return best
