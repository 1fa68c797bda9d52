"""The receding horizon's least squares: the residuals r(Z, U; p) and their parameter vector p.

``residuals`` builds r in CasADi symbols for one problem structure; ``parameters`` assembles p
for one problem, in the order ``residuals`` declares it. The rows, their scalings and the row
scaling W are docs/nmpc.md, section 2; the obstacle shadows, section 3.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from platoon_opt.errors import OptionError
from platoon_opt.problem import AllocationProblem

# Task, obstacle, clearance and shadow errors are measured in units of this length (m).
ERROR_SCALE = 0.01
# Floor of a row norm ||J_r|| in the row scaling W (a vanishing variance row).
_ROW_NORM_FLOOR = 1e-3
# Added to a squared distance (m^2) under its square root: the obstacle and clearance rows stay
# differentiable where a tip meets a centre or another tip.
DISTANCE_EPSILON = 1e-12
# A mean nominal speed (m/s) at or below this gives the platoon no direction of travel.
_STILL_SPEED = 1e-9


@dataclass(frozen=True)
class Formulation:
    """The options that define the least-squares problem: the allocator's fields of the same
    names (``RecedingHorizon``, where each is described). With the backend it keys the
    horizons (``compiled.horizon_for``)."""

    intervals: int
    resolve_every: int
    gain_weights: bool
    fade_gains: bool
    task_weights: tuple[float, ...] | None
    speed_smoothness: float
    steering_smoothness: float
    nominal_weight: float
    precedence_weight: float
    penalty_margin: float
    obstacle_weight: float
    shadow_weight: float
    shadow_length: float
    unit_clearance: float
    clearance_weight: float
    preview: bool
    steering: str
    task_samples: str

    def sample_every(self) -> int:
        """Every how many simulation steps the task rows sample the horizon (Eq. 2.1): each
        step (``task_samples`` "steps") or each node ("nodes")."""
        return 1 if self.task_samples == "steps" else self.resolve_every

    def task_times(self, dt: float) -> np.ndarray:
        """The times after the solve (s) at which the task rows compare f with f_d (Eq. 2.1),
        for a simulation step of ``dt`` s."""
        every = self.sample_every()
        return every * dt * np.arange(1, self.intervals * self.resolve_every // every + 1)


def residuals(
    formulation: Formulation,
    n: int,
    m: int,
    n_obstacles: int,
    dt: float,
    steps: Callable[..., Sequence[tuple[Any, Any, Any, Any]]],
    expression: Callable[..., Any] | None,
    clearance_rows: bool = True,
) -> tuple[ca.SX, ca.SX, ca.SX, ca.SX]:
    """The residual vector r (docs/nmpc.md, Eqs. 2.1-2.7) and its symbols: (r, Z, U, p).

    Z (4, N n) holds the node states and U (2, N n) the inputs, column k n + i for node or
    interval k and unit i; dt is the simulation step (s). ``steps(start, speed, end_angle)``
    moves the units through one interval's simulation steps, (x, y, theta, alpha) after each
    (``kinematics.interval_states`` with the units' numbers): it places the task's samples
    between the nodes. ``expression`` is f(x, y, t) in CasADi symbols, or None for a task
    linearized at each solve (its value, Jacobian and positions then join p).
    ``clearance_rows`` False leaves the clearance rows (2.7) out, for a solver that adds the rows
    of the pairs that can meet itself (``clearance.Clearance``).
    """
    form, N, S = formulation, formulation.intervals, formulation.resolve_every
    every, times = form.sample_every(), form.task_times(dt)
    samples = times.size
    margin = form.penalty_margin
    Z, U = ca.SX.sym("z", 4, N * n), ca.SX.sym("u", 2, N * n)
    previous_speed, alpha0, theta0, x0, y0 = (
        ca.SX.sym("s_prev", n),
        ca.SX.sym("alpha0", n),
        ca.SX.sym("theta0", n),
        ca.SX.sym("x0", n),
        ca.SX.sym("y0", n),
    )
    nominal, nominal_scale = ca.SX.sym("nominal", n, 2), ca.SX.sym("nominal_scale", n)
    targets, weights = ca.SX.sym("fd", m, samples), ca.SX.sym("w", m)
    t0 = ca.SX.sym("t0")
    centers, radii = ca.SX.sym("centers", 2, n_obstacles), ca.SX.sym("radii", n_obstacles)
    travel = ca.SX.sym("travel", 2)
    # The order of p: ``parameters`` follows it.
    symbols = [previous_speed, alpha0, theta0, x0, y0, ca.vec(nominal), nominal_scale]
    symbols += [ca.vec(targets), weights, t0]
    symbols += [ca.vec(centers), radii, travel]
    if expression is None:
        # A task without a symbolic form: its first-order model around the current state.
        value0, rows, q0 = ca.SX.sym("f0", m), ca.SX.sym("J", m, 2 * n), ca.SX.sym("q0", 2 * n)
        symbols += [value0, ca.vec(rows), q0]

        def task_at(x: ca.SX, y: ca.SX, t: ca.SX) -> ca.SX:
            return value0 + ca.mtimes(rows, ca.vertcat(x, y) - q0)

    else:

        def task_at(x: ca.SX, y: ca.SX, t: ca.SX) -> ca.SX:
            value = expression(x, y, t)
            return ca.vec(ca.vertcat(*value) if isinstance(value, (list, tuple)) else ca.SX(value))

    p = ca.vertcat(*symbols)
    task_rows, speed_rows, steering_rows, nominal_rows, obstacle_rows, pair_rows = [], [], [], [], [], []
    shadow_rows = []
    paired = clearance_rows and form.clearance_weight > 0
    first = [i for i in range(n) for _ in range(i + 1, n)] if paired else []
    second = [j for i in range(n) for j in range(i + 1, n)] if paired else []
    speed_before, steering_before = previous_speed, alpha0
    start = (x0, y0, theta0, alpha0)
    for k in range(N):
        columns = slice(k * n, (k + 1) * n)
        x, y = Z[0, columns].T, Z[1, columns].T
        speed, steering = U[0, columns].T, U[1, columns].T
        # The tip's velocity over interval k, at its start heading and end steering.
        direction = start[2] + steering
        velocity = ca.horzcat(speed * ca.cos(direction), speed * ca.sin(direction))
        deviation = ca.repmat(nominal_scale, 1, 2) * (velocity - nominal)
        nominal_rows.append(math.sqrt(form.nominal_weight / (N * n)) * ca.vec(deviation))
        # The task's samples within interval k: the last is its end node, the others lie on the
        # way there, moved from the interval's start by the same steps (Eq. 2.1).
        on_the_way = steps(start, speed, steering) if every < S else []
        for j in range(every, S + 1, every):
            x_j, y_j = (x, y) if j == S else on_the_way[j - 1][:2]
            sample = (k * S + j) // every - 1
            error = task_at(x_j, y_j, t0 + float(times[sample])) - targets[:, sample]
            task_rows.append(weights * error / (ERROR_SCALE * math.sqrt(samples)))
        start = (x, y, Z[2, columns].T, Z[3, columns].T)
        speed_rows.append(math.sqrt(form.speed_smoothness / (N * n)) * (speed - speed_before))
        steering_rows.append(math.sqrt(form.steering_smoothness / (N * n)) * (steering - steering_before))
        speed_before, steering_before = speed, steering
        for o in range(n_obstacles):
            distance = ca.sqrt((x - centers[0, o]) ** 2 + (y - centers[1, o]) ** 2 + DISTANCE_EPSILON)
            intrusion = ca.fmax(0, radii[o] + margin - distance)
            obstacle_rows.append(math.sqrt(form.obstacle_weight / N) * intrusion / ERROR_SCALE)
            if form.shadow_weight > 0:
                depth = shadow(x, y, centers[:, o], radii[o], travel, margin, form.shadow_length)
                shadow_rows.append(math.sqrt(form.shadow_weight / N) * depth)
        if first:
            distance = ca.sqrt((x[first] - x[second]) ** 2 + (y[first] - y[second]) ** 2 + DISTANCE_EPSILON)
            intrusion = ca.fmax(0, form.unit_clearance - distance)
            pair_rows.append(math.sqrt(form.clearance_weight / N) * intrusion / ERROR_SCALE)
    residual = ca.vertcat(
        *task_rows, *speed_rows, *steering_rows, *nominal_rows, *obstacle_rows, *pair_rows, *shadow_rows
    )
    return residual, Z, U, p


def shadow(
    x: ca.SX, y: ca.SX, center: ca.SX, radius: ca.SX, travel: ca.SX, margin: float, length: float
) -> ca.SX:
    """Each unit's depth (in ``ERROR_SCALE``) inside the shadow of one obstacle (docs/nmpc.md,
    section 3): the strip of half-width ``radius + margin`` behind its ``center`` along
    ``travel`` (the unit direction of the platoon's nominal motion, or 0 for none), reaching
    ``length`` (m) back and weighted from 0 there to 1 at the centre (and back to 0 at the
    strip's half-width beyond it). x, y: the units' tip positions (n, 1), m.
    """
    dx, dy = x - center[0], y - center[1]
    along = dx * travel[0] + dy * travel[1]
    lateral = ca.sqrt((dx * travel[1] - dy * travel[0]) ** 2 + 1e-12)
    width = radius + margin
    gate = ca.fmax(0, ca.fmin(1 + along / length, 1 - along / width))
    return ca.sumsqr(travel) * gate * ca.fmax(0, width - lateral) / ERROR_SCALE


def check_task_weights(task_weights: tuple[float, ...] | None, names: Sequence[str]) -> None:
    """``OptionError`` unless ``task_weights`` is None or holds one weight per task component
    (``names``): a configuration error, which no fallback answers."""
    if task_weights is not None and len(task_weights) != len(names):
        raise OptionError(
            f"option task_weights of nmpc must be a tuple of {len(names)} numbers >= 0, one per task "
            f"component ({', '.join(names)}), got {task_weights!r}"
        )


def gain_weights(gains: np.ndarray) -> np.ndarray:
    """Each task row's weight from the tracking gains (Eq. 2.9): K_r over the smallest positive
    K_r, (m,); K's diagonal for a whole K (m, m); all 1 if no gain is positive.

    The law's response to an error, e_r' = -K_r e_r, is the optimal one for the cost
    integral of (K_r e_r)^2 + (e_r')^2 (docs/nmpc.md, section 2), so the rows weigh K_r e_r."""
    diagonal = np.diagonal(gains) if np.ndim(gains) == 2 else np.asarray(gains, dtype=float)
    positive = diagonal[diagonal > 0]
    return diagonal / positive.min() if positive.size else np.ones_like(diagonal)


def saturation(problem: AllocationProblem) -> float:
    """How far the platoon's catching up is out of the units' reach: the speed the tracking law's
    feedback asks of the units' centroid (``problem.feedback_speed``) over the top speed, at
    least 1 (docs/nmpc.md, Eq. 2.9')."""
    return max(1.0, float(problem.feedback_speed()) / problem.limits.max_speed)


def faded(weights: np.ndarray, saturation: float) -> np.ndarray:
    """Gain weights (m,) faded under ``saturation`` s >= 1 (Eq. 2.9'): 1 + (w - 1) / s, so
    ``weights`` at s = 1 and every row toward 1 as s grows; a zero weight (a gain of 0, an error
    the law leaves alone) stays 0."""
    return np.where(weights > 0, 1.0 + (weights - 1.0) / saturation, 0.0)


def parameters(
    problem: AllocationProblem, formulation: Formulation, linearized: bool, previous_speed: np.ndarray
) -> np.ndarray:
    """The parameter vector p of ``residuals`` for ``problem``: ``previous_speed`` (n,) is the
    speed handed before this solve (m/s), s_{-1} of the speed smoothness rows; ``linearized``
    as the horizon's (the task's value, Jacobian and positions join p)."""
    n = problem.n
    rows = problem.jacobian.rows
    row_norm = np.sqrt(np.einsum("kij,kij->k", rows, rows))
    weights = 1.0 / (math.sqrt(n) * np.maximum(row_norm, _ROW_NORM_FLOOR))
    if formulation.gain_weights:
        gain = gain_weights(problem.gains)
        if formulation.fade_gains:
            gain = faded(gain, saturation(problem))
        weights = weights * gain
    task_weights = formulation.task_weights
    if task_weights is not None:
        check_task_weights(task_weights, problem.task.names)
        weights = weights * np.asarray(task_weights)
    values = [
        previous_speed,
        problem.state.alpha,
        problem.state.theta,
        problem.state.x,
        problem.state.y,
        problem.nominal.reshape(-1, order="F"),
        precedence_scale(problem, formulation.precedence_weight, formulation.penalty_margin),
        sample_targets(problem, formulation).reshape(-1),  # sample by sample: ca.vec of (m, K)
        weights,
        [problem.t],
        problem.obstacles.centers.reshape(-1),
        problem.obstacles.radii,
        direction_of_travel(problem),
    ]
    if linearized:
        dense = np.concatenate((rows[:, :, 0], rows[:, :, 1]), axis=1)  # (m, 2n): O(m n)
        positions = problem.state.positions
        values += [problem.task_value, dense.reshape(-1, order="F"), positions.T.reshape(-1)]
    return np.concatenate([np.asarray(v, dtype=float).reshape(-1) for v in values])


def sample_targets(problem: AllocationProblem, formulation: Formulation) -> np.ndarray:
    """f_d at the task's samples t + tau_k (``Formulation.task_times``), (K, m) (docs/nmpc.md,
    Eq. 1.7): the previewed reference (``problem.desired_ahead``) with ``preview`` when the
    problem carries it, else f_d extrapolated at its rate."""
    tau = formulation.task_times(problem.dt)
    if formulation.preview and problem.desired_ahead is not None:
        ahead = np.asarray(problem.desired_ahead)
        if ahead.shape != (tau.size, problem.desired.size):
            raise ValueError(
                f"desired_ahead must hold f_d at the {tau.size} task samples of the horizon, "
                f"shape ({tau.size}, {problem.desired.size}), got shape {ahead.shape}"
            )
        return ahead
    return problem.desired[None, :] + tau[:, None] * problem.desired_rate[None, :]


def direction_of_travel(problem: AllocationProblem) -> np.ndarray:
    """The unit direction (2,) of the platoon's nominal motion (the mean of the units' nominal
    velocities), or 0 when the platoon is to hold still."""
    motion = problem.nominal.mean(axis=0)
    speed = float(np.hypot(*motion))
    return motion / speed if speed > _STILL_SPEED else np.zeros(2)


def precedence_scale(problem: AllocationProblem, precedence_weight: float, margin: float) -> np.ndarray:
    """Factor (n,) of each unit's nominal-velocity rows (docs/nmpc.md, Eq. 2.4):
    sqrt(precedence_weight) for the units under the precedence rule within 2 ``margin`` (m) of
    an obstacle's surface, else 1."""
    if precedence_weight == 1:
        return np.ones(problem.n)  # the rule is off: no obstacle distances needed
    clearance, _ = problem.obstacles.nearest(problem.state.positions)
    near = problem.exempt & (clearance < 2 * margin)
    return np.where(near, math.sqrt(precedence_weight), 1.0)
