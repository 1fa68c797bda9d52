"""Scores of a run: the paper's integrated absolute errors, gear flips, obstacle clearance,
compute time.

A run is scored from samples at its instants (``Instant``: the mean's distance from the target,
the task errors, the clearance, the units inside obstacles, the least distance between units),
taken by ``instant`` inside the compiled engine or from a recorded ``Trajectory``, and from its
per-step records (``score``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from platoon_opt.arrays import namespace, pytree
from platoon_opt.avoidance import CircularObstacles
from platoon_opt.neighbours import min_pair_distance
from platoon_opt.trajectory import Trajectory

# Metrics where smaller is better (the harness compares allocators on these).
ERROR_METRICS = ("mean_position", "mean_position_after_transient", "var_x", "var_y")
# Task components that follow the target: their error is the mean's distance from it.
MEANS = ("mean_x", "mean_y")
# Where the search for the least distance between units starts (m; it doubles until it finds a
# pair, so this sets only its speed).
UNIT_SEARCH = 1.0


@pytree(data=("mean_distance", "errors", "clearance", "inside", "unit_distance"))
@dataclass(frozen=True)
class Instant:
    """Samples of one instant (or, stacked, of many: a leading axis).

    Attributes:
        mean_distance: distance of the platoon mean from the target (m).
        errors: |f_k - f_d,k| of each task component other than the means (c,).
        clearance: least distance of a unit from an obstacle surface (m; negative inside; inf
            without obstacles).
        inside: units inside an obstacle.
        unit_distance: least distance between two units (m).
    """

    mean_distance: Any
    errors: Any
    clearance: Any
    inside: Any
    unit_distance: Any


def instant(
    positions: Any,
    task_value: Any,
    desired: Any,
    target: Any,
    names: tuple[str, ...],
    obstacles: CircularObstacles,
    measured: tuple[Any, Any] | None = None,
) -> Instant:
    """The samples of one instant: tip positions (n, 2) m, f (m,), f_d (m,), the target (2,) m.

    ``measured``: the distances the step's problem holds (``AllocationProblem.obstacle_distance``
    and ``unit_distance``), the same numbers, not measured again: each unit's clearance, and the
    least distance between units wherever one pair lies within d_minr (else it is searched for).
    """
    xp = namespace(positions, task_value)
    mean = positions.mean(axis=0)
    errors = [xp.abs(task_value[k] - desired[k]) for k, name in enumerate(names) if name not in MEANS]
    if len(obstacles):
        clearance = obstacles.nearest(positions)[0] if measured is None else measured[0]
        least, inside = clearance.min(), (clearance < 0).sum()
    else:
        least, inside = xp.asarray(xp.inf), xp.asarray(0)
    known = None if measured is None else measured[1].min()
    return Instant(
        mean_distance=xp.hypot(mean[0] - target[0], mean[1] - target[1]),
        errors=xp.stack(errors) if errors else xp.zeros(0),
        clearance=least,
        inside=inside,
        unit_distance=min_pair_distance(positions, UNIT_SEARCH, known=known),
    )


def _integrate(values: np.ndarray, dt: float) -> float:
    """Trapezoidal integral of samples spaced ``dt`` apart."""
    if values.shape[0] < 2:
        return 0.0
    return float(dt * (values.sum() - 0.5 * (values[0] + values[-1])))


def score(
    samples: Instant,
    *,
    dt: float,
    transient: float,
    names: tuple[str, ...],
    gear_flips: int,
    fell_back: np.ndarray,
    program_changed: np.ndarray,
    slack: np.ndarray,
    solved: np.ndarray,
    solve_time: np.ndarray,
) -> dict[str, float]:
    """The scores of a run of T steps from the samples of its T + 1 instants (numpy, a leading
    axis) and its per-step records (each (T,)): see ``integrated_errors``."""
    after = np.arange(samples.mean_distance.shape[0]) * dt >= transient - 1e-12
    result = {
        "mean_position": _integrate(samples.mean_distance, dt),
        "mean_position_after_transient": _integrate(samples.mean_distance[after], dt),
    }
    for k, name in enumerate(name for name in names if name not in MEANS):
        result[name] = _integrate(samples.errors[:, k], dt)
        result[f"{name}_after_transient"] = _integrate(samples.errors[after, k], dt)
    result["gear_flips"] = int(gear_flips)
    # Unit-seconds inside: the units inside at each instant but the last, one step each.
    result["time_inside_obstacles"] = float(np.sum(samples.inside[:-1]) * dt)
    result["min_clearance"] = float(np.min(samples.clearance))
    result["min_unit_distance"] = float(np.min(samples.unit_distance))
    times = np.asarray(solve_time, dtype=float)
    solves = times[np.asarray(solved, dtype=bool)]
    result.update(
        solve_time_median=float(np.median(times)) if times.size else 0.0,
        solve_time_p95=float(np.percentile(times, 95)) if times.size else 0.0,
        solve_steps=int(solves.size),
        solve_time_per_solve_median=float(np.median(solves)) if solves.size else math.nan,
        solve_time_per_solve_p95=float(np.percentile(solves, 95)) if solves.size else math.nan,
        fallback_steps=int(np.count_nonzero(fell_back)),
        program_changes=int(np.count_nonzero(program_changed)),
        slack_steps=int(np.count_nonzero(slack)),
    )
    return result


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
            those that reused an earlier solve (``nmpc`` handing its plan, about 0 s) included;
            nan for a run of the compiled engine, whose allocation is not timed apart from the
            step.
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
    samples = sample_trajectory(trajectory)
    return score(
        samples,
        dt=trajectory.dt,
        transient=transient,
        names=trajectory.task_names,
        gear_flips=int(np.count_nonzero(np.diff(trajectory.gear, axis=0))),
        fell_back=trajectory.fell_back,
        # Never None once built (``Trajectory.__post_init__`` fills them).
        program_changed=np.asarray(trajectory.program_changed),
        slack=np.asarray(trajectory.slack),
        solved=np.asarray(trajectory.solved),
        solve_time=trajectory.solve_time,
    )


def _sample_instants(
    x: Any, y: Any, task_value: Any, desired: Any, target: Any, names: tuple[str, ...], obstacles: Any
) -> Instant:
    positions = namespace(x).stack((x, y), axis=-1)
    return jax.vmap(instant, in_axes=(0, 0, 0, 0, None, None))(
        positions, task_value, desired, target, names, obstacles
    )


_sample_compiled = jax.jit(_sample_instants, static_argnames=("names",))


def sample_trajectory(trajectory: Trajectory) -> Instant:
    """The samples (``Instant``, a leading axis of T + 1) of a recorded trajectory, numpy."""
    return jax.device_get(
        _sample_compiled(
            trajectory.x,
            trajectory.y,
            trajectory.task_value,
            trajectory.desired,
            trajectory.target,
            tuple(trajectory.task_names),
            trajectory.obstacles,
        )
    )
