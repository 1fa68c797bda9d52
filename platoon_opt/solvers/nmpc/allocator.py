"""Receding-horizon allocator ("nmpc"): optimal control over the true tricycle kinematics.

Every ``resolve_every`` simulation steps the allocator solves an optimal control problem over
``intervals`` (N) shooting intervals of ``h = resolve_every * dt`` seconds each (default
10 x 0.05 s: a 0.5 s horizon, re-solved at 20 Hz over the 100 Hz simulation; 20 intervals track
better in closed loop on every error, at about three times the cost: experiments/one_step.md,
rounds 4 and 5):

    minimize    sum ||r||^2                               (least squares, residuals below)
    over        inputs U_k = (s_k, a_k) of every unit: speed (m/s, signed) over interval k and
                steering angle (rad) reached at its end; node states Z_{k+1} = (x, y, theta, alpha)
    subject to  Z_{k+1} = F(Z_k, U_k)                     the exact kinematics (Eq. 1): over the
                                                          resolve_every substeps of dt the steering
                                                          moves linearly from alpha_k to a_k, each
                                                          substep steering first, then the arc,
                                                          exactly as ``step_vehicles`` moves a unit
                |s_k| <= v_max (gears="rule": gear_i s_ik >= 0, the gear the model's rule picks)
                |a_k| <= alpha_max                        the steering angle
                |a_k - a_{k-1}| <= alpha_dot_max h        the steering rate (a_{-1} = alpha now)

Residuals (``ERROR_SCALE`` = 1 cm makes them dimensionless):

- task: ``W (f(q_k, t_k) - f_d(t_k)) / (ERROR_SCALE sqrt(N))`` at every node k = 1..N;
- speed smoothness: ``sqrt(speed_smoothness / (N n)) (s_k - s_{k-1})`` (m/s; s_{-1} is the
  speed handed before the solve);
- steering smoothness: ``sqrt(steering_smoothness / (N n)) (a_k - a_{k-1})`` (rad);
- obstacles (soft constraint): ``sqrt(obstacle_weight / N) max(0, r_o + obstacle_margin -
  |p_ik - c_o|) / ERROR_SCALE`` for every unit, node and obstacle;
- obstacle shadows: ``sqrt(shadow_weight / N)`` times each unit's depth (in ``ERROR_SCALE``)
  inside the strip behind each obstacle along the platoon's direction of travel, the strip it
  must leave sideways to pass (``_shadow``): a stand-in for the cost-to-go beyond the horizon,
  without which a unit that meets an obstacle head on can stall against it;
- inter-unit clearance (soft constraint): ``sqrt(clearance_weight / N) max(0, unit_clearance -
  |p_ik - p_jk|) / ERROR_SCALE`` for every pair of units and node;
- nominal velocity: ``sqrt(nominal_weight / (N n)) (v_ik - q'_d,i)`` (m/s), v_ik the tip
  velocity over interval k (speed s_ik along the start heading plus the end steering a_ik) and
  q'_d the nominal velocity of Eq. 5 (task, obstacle and inter-unit repulsion). It settles the
  motion within the task's null space, which the task rows leave free: without it the
  Gauss-Newton Hessian is near singular and the solution flips between the input bounds.
  With ``precedence_weight`` > 1 the rows of a unit under the paper's precedence rule
  (``problem.exempt``) within ``2 obstacle_margin`` of an obstacle's surface are multiplied by
  ``sqrt(precedence_weight)``, so that such a unit follows its nominal velocity (the
  repulsion) first. It is off by default. A unit can stall against the obstacle penalty (the
  short horizon does not see that backing away and around pays), and the rule recovers such
  seeds, but over 20 seeds it cost more of the others than it saved, in the paper's zone
  (d_mino / 4 = 0.75 m) as within 0.3 m (experiments/one_step.md).

A task error of 1 cm held over the horizon costs 1; an obstacle intrusion of 1 cm held over the
horizon costs ``obstacle_weight``.

Row scaling W: row r is divided by ``sqrt(n) ||J_r(q)||``, the RMS displacement per unit (m) of
the smallest platoon motion that corrects that row's error alone. A mean error of 1 cm scores
1 cm; a variance error d var scores about d var / (2 sigma), the change of the standard
deviation in m. ``task_weights`` multiplies the scaled rows (default all 1).

No preview: over the horizon the target is extrapolated at its current velocity,
``f_d(t + tau) = f_d(t) + tau f_d'(t)``, the information every other allocator gets.

Solvers, each built once per problem structure (n, m, obstacles, dt, limits):

- ``solver="sqp"`` (default): Gauss-Newton SQP in the inputs, the node states simulated from
  them (the gaps of the multiple-shooting problem kept closed). Each iteration evaluates the
  intervals' Jacobians (CasADi, per unit) and the residuals' Jacobians (sparse: each obstacle,
  clearance or smoothness row involves one or two units), chains them into the states'
  sensitivities to the inputs (unit by unit: the dynamics do not couple units), and solves the
  QP in the 2 n N input steps: box constraints (speed, steering angle) and the rate rows, which
  are left out when ``alpha_dot_max h >= 2 alpha_max`` makes them redundant, as at the paper's
  values. With box constraints alone (solvers/box_qp.py): the Gauss-Newton Hessian is one
  (2N, 2N) block per unit (the rows that involve one unit) plus the m N task rows and the live
  clearance rows that couple units, and a primal-dual active-set method solves on that split
  (Woodbury; O(n m^2 N^3 + m^3 N^3) per linear solve instead of O(n^3 N^3); up to
  ``box_qp.DENSE_UP_TO`` inputs, as 8 units over 10 intervals, on the dense Hessian, faster
  there), each iteration from the previous iteration's active sets. When its sets cycle, DAQP
  (``casadi.conic``) solves the dense QP, and projected Newton a DAQP failure. With rate rows:
  DAQP. (Times against DAQP alone: experiments/one_step.md, round 5.)
  The step is accepted by Armijo backtracking on the cost of the simulated trajectory: with
  many inputs saturated (a cold start, a sharp turn) full steps oscillate between the bounds.
  Warm-started from the previous plan shifted by one interval (``second_start``: also from the
  base controller's rollout, keeping the better), it stops when no input moves by more than
  ``step_tolerance`` of its range, or after ``max_iterations``. CasADi Functions run on
  preallocated NumPy buffers (``Function.buffer``): no DM conversions.
- ``solver="ipopt"``: the multiple-shooting NLP (inputs and node states as variables, the
  interval gaps as equality constraints) with IPOPT (``casadi.nlpsol``, exact Hessian), from
  the same start; about ten times slower, kept as the reference solution (the tests check that
  both agree).

Limitation: the gear (sign of each speed) is a discrete choice that a local solver keeps from
its start; at sharp turns and reversals the shifted plan can hold units in a gear that a
better plan would change (``second_start``, on by default, helps at twice the work).

Size: dr/dU is held dense, O(n^2 N^2) memory (the task rows couple all units at every node),
and a linear solve costs O(n m^2 N^3 + m^3 N^3); meant for platoons of tens of units.

The first move: the units' controller (Eq. 2) steers toward the direction of the handed
velocity and drives at its length, so the allocator hands ``|s_0| (cos phi, sin phi)`` with
``phi = theta + c (+ pi when s_0 < 0)``, ``c`` the steering target that makes the unit's
``K_alpha (c - alpha) dt`` land on the planned steering angle of the current substep. With the
paper's ``K_alpha dt = 1`` that is the planned angle itself and the unit reproduces the planned
motion exactly. Between solves the stored plan is handed the same way.

A failed solve (QP or NLP failure, non-finite values) falls back to ``get_allocator("qp")`` if
registered, else to the paper's iteration with m = 4; the status is ``"fallback:<why>"``.
"""

from __future__ import annotations

import inspect
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

import casadi as ca
import numpy as np

from platoon_opt.limits import AchievableSets
from platoon_opt.problem import Allocation, AllocationProblem, Allocator
from platoon_opt.solvers.nmpc.box_qp import BlockLowRank, BoxSolution, active_set_newton, projected_newton
from platoon_opt.solvers.options import Choice, Flag, Integer, Number, Numbers, Option, check_options
from platoon_opt.solvers.registry import available_allocators, get_allocator, register
from platoon_opt.symbolic import SymbolicTask, mean_variance_expression
from platoon_opt.tasks import MeanVarianceTask
from platoon_opt.vehicle import VehicleLimits

# Task and clearance errors are measured in units of this length (m).
ERROR_SCALE = 0.01
# A handed velocity this short still carries its direction to the unit controller (which
# holds the steering for a zero velocity) and moves the unit by 1e-11 m per step.
_DIRECTION_ONLY_SPEED = 1e-9
# Floor of a row norm ||J_r|| in the row scaling (a vanishing variance row).
_ROW_NORM_FLOOR = 1e-3
# Levenberg-Marquardt term on the Gauss-Newton Hessian: keeps it positive definite when a
# smoothness weight is 0.
_DAMPING = 1e-8
_IPOPT_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def task_expression(task: Any) -> Callable[..., Any] | None:
    """f(x, y, t) in CasADi symbols for tasks that have one (``SymbolicTask`` defined by an
    expression, ``MeanVarianceTask``), else None: such a task is linearized at each solve."""
    if isinstance(task, SymbolicTask) and not isinstance(task.expression, ca.Function):
        expression = task.expression
        if len(inspect.signature(expression).parameters) >= 3:
            return expression
        return lambda x, y, t: expression(x, y)
    if isinstance(task, MeanVarianceTask):
        return lambda x, y, t: mean_variance_expression(x, y)
    return None


def unit_interval(substeps: int, dt: float, length: float) -> ca.Function:
    """One interval of one unit: (z = (x, y, theta, alpha), u = (s, a)) -> z after ``substeps``
    steps of ``dt`` s at speed s, the steering moving linearly from alpha to a.

    Each substep mirrors ``step_vehicles``: the steering moves first, then the tip follows the
    arc of constant speed and steering; the chord's ``sin(c)/c`` is its Taylor series (the turn
    per step is at most v_max dt / d, 0.04 rad at the paper's values: error < 1e-16).
    """
    z, u = ca.SX.sym("z", 4), ca.SX.sym("u", 2)
    x, y, theta, alpha = z[0], z[1], z[2], z[3]
    speed, increment = u[0], (u[1] - z[3]) / substeps
    for _ in range(substeps):
        alpha = alpha + increment
        turn = speed / length * ca.sin(alpha) * dt
        half = turn / 2
        chord = speed * dt * (1 - half**2 / 6 + half**4 / 120)
        direction = theta + alpha + half
        x = x + chord * ca.cos(direction)
        y = y + chord * ca.sin(direction)
        theta = theta + turn
    return ca.Function("unit_interval", [z, u], [ca.vertcat(x, y, theta, alpha)])


def controller_rollout(intervals: int, substeps: int, dt: float, limits: VehicleLimits) -> ca.Function:
    """One unit under its controller (Eq. 2, ``unit_controller``) holding a desired velocity:
    (state (x, y, theta, alpha, gear), velocity (2,)) -> inputs (2, intervals), column k the
    signed speed of the last substep of interval k and the steering angle at its end.

    It mirrors ``unit_controller`` and ``step_vehicles`` operation by operation (the gear rule
    with hysteresis, the clipped steering rate, ``np.mod``'s wrap and ``np.sinc``'s chord), so
    the Python loop it replaces agrees with it to rounding (tests/test_nmpc.py).
    """
    z, velocity = ca.SX.sym("z", 5), ca.SX.sym("velocity", 2)
    x, y, theta, alpha, gear = (z[i] for i in range(5))

    def wrap(angle: ca.SX) -> ca.SX:
        remainder = ca.fmod(math.pi - angle, 2 * math.pi)
        wrapped = math.pi - ca.if_else(remainder < 0, remainder + 2 * math.pi, remainder)
        return ca.if_else(wrapped == -math.pi, math.pi, wrapped)

    desired_speed = ca.hypot(velocity[0], velocity[1])
    direction = ca.atan2(velocity[1], velocity[0])
    speed = ca.fmin(desired_speed, limits.max_speed)
    columns = []
    for _ in range(intervals):
        for _ in range(substeps):
            axis = wrap(theta + ca.if_else(gear < 0, math.pi, 0))
            error = wrap(direction - axis)
            switch = ca.logic_and(
                desired_speed > 1e-12, ca.fabs(error) > math.pi / 2 + limits.gear_hysteresis
            )
            relative = ca.if_else(switch, error - ca.sign(error) * math.pi, error)
            gear = ca.if_else(switch, -gear, gear)
            target = ca.if_else(
                speed > 0, ca.fmin(ca.fmax(relative, -limits.max_steering), limits.max_steering), alpha
            )
            rate = limits.steering_gain * (target - alpha)
            rate = ca.fmax(rate, ca.fmax(-limits.max_steering_rate, (-limits.max_steering - alpha) / dt))
            rate = ca.fmin(rate, ca.fmin(limits.max_steering_rate, (limits.max_steering - alpha) / dt))
            signed = gear * speed
            alpha = ca.fmin(ca.fmax(alpha + rate * dt, -limits.max_steering), limits.max_steering)
            turn = signed / limits.length * ca.sin(alpha) * dt
            heading = theta + alpha + turn / 2
            half = math.pi * ca.if_else(turn == 0, 1e-20, turn / (2 * math.pi))
            chord = signed * dt * (ca.sin(half) / half)
            x, y, theta = x + chord * ca.cos(heading), y + chord * ca.sin(heading), wrap(theta + turn)
        columns.append(ca.vertcat(signed, alpha))
    return ca.Function("controller_rollout", [z, velocity], [ca.horzcat(*columns)])


class _Evaluator:
    """Calls a ``casadi.Function`` on preallocated NumPy buffers (no DM conversions).

    Arguments are written into ``inputs`` (each the column-major nonzeros of that input);
    ``__call__`` returns the output buffers, reused by the next call.
    """

    def __init__(self, function: ca.Function) -> None:
        self.function = function
        self._buffer, self._evaluate = function.buffer()
        self.inputs = [np.zeros(function.nnz_in(i)) for i in range(function.n_in())]
        self.outputs = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
        for i, array in enumerate(self.inputs):
            self._buffer.set_arg(i, memoryview(array))
        for i, array in enumerate(self.outputs):
            self._buffer.set_res(i, memoryview(array))

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        for target, value in zip(self.inputs, args):
            target[:] = np.asarray(value, dtype=float).reshape(-1, order="F")
        self._evaluate()
        return self.outputs

    def stats(self) -> dict[str, Any]:
        return self._buffer.stats()


@dataclass(frozen=True)
class _Chain:
    """dr/dU = dr/dU|_Z + dr/dZ dZ/dU from the sparse nonzeros of the residual Jacobians, without
    forming dZ/dU (block diagonal by unit, lower block triangular by interval): each nonzero of
    dr/dZ at (row, node k, unit i, coordinate c) adds its value times G[k, :, i, c, :] to row
    ``row`` at unit i's columns. Rows that are zero along with their residual (obstacle and
    clearance hinges out of reach) are left out.

    The columns of dr/dU are unit-major: column i 2N + 2k + side is unit i's input ``side``
    (speed, steering) of interval k, so that each unit's columns are one contiguous block.

    Attributes:
        n, N: units and intervals.
        row_unit: the unit each residual row involves alone, or -1 for a row that couples
            units (task, clearance) or involves none, (rows,).
        u_row, u_column: of dr/dU|_Z's nonzeros (their column-major order; unit-major
            columns), each (nnz_u,).
        z_row, unit, gain_row: of dr/dZ's nonzeros (column-major order), each (nnz_z,):
            row, unit, and the row (k n + i) 4 + c of G laid out as (N n 4, N 2).
    """

    n: int
    N: int
    row_unit: np.ndarray
    u_row: np.ndarray
    u_column: np.ndarray
    z_row: np.ndarray
    unit: np.ndarray
    gain_row: np.ndarray

    @classmethod
    def of(cls, jacobian: ca.Function, N: int, n: int) -> _Chain:
        """From a Function whose outputs 1 and 2 are dr/dvec(Z) and dr/dvec(U)."""

        def entries(index: int) -> tuple[np.ndarray, np.ndarray]:
            pattern = jacobian.sparsity_out(index)
            rows, columns = pattern.get_triplet()
            return np.asarray(rows, dtype=np.intp), np.asarray(columns, dtype=np.intp)

        u_row, u_columns = entries(2)
        interval, u_unit, side = np.unravel_index(u_columns, (N, n, 2))
        z_row, z_columns = entries(1)
        node, unit, coordinate = np.unravel_index(z_columns, (N, n, 4))
        rows, units = np.concatenate((u_row, z_row)), np.concatenate((u_unit, unit))
        lowest, highest = np.full(jacobian.size1_out(0), n), np.full(jacobian.size1_out(0), -1)
        np.minimum.at(lowest, rows, units)
        np.maximum.at(highest, rows, units)
        row_unit = np.where(lowest == highest, lowest, -1)
        u_column = u_unit * 2 * N + 2 * interval + side
        return cls(n, N, row_unit, u_row, u_column, z_row, unit, (node * n + unit) * 4 + coordinate)

    def __call__(
        self, residual: np.ndarray, z_values: np.ndarray, u_values: np.ndarray, G: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The residuals that are nonzero or have a nonzero derivative, their rows of dr/dU and
        their units (``row_unit``), from the nonzeros of dr/dZ and dr/dU|_Z and G (N, N, n, 4, 2)."""
        n, block = self.n, 2 * self.N
        width = n * block
        z_live, u_live = np.flatnonzero(z_values), np.flatnonzero(u_values)
        keep = residual != 0
        keep[self.z_row[z_live]] = True
        keep[self.u_row[u_live]] = True
        compact = np.cumsum(keep) - 1
        kept = int(compact[-1]) + 1 if keep.size else 0
        gains = G.transpose(0, 2, 3, 1, 4).reshape(-1, block)[self.gain_row[z_live]]
        first = (compact[self.z_row[z_live]] * n + self.unit[z_live]) * block
        out = np.bincount(
            (first[:, None] + np.arange(block)).ravel(),
            weights=(z_values[z_live, None] * gains).ravel(),
            minlength=kept * width,
        )
        out[compact[self.u_row[u_live]] * width + self.u_column[u_live]] += u_values[u_live]
        return residual[keep], out.reshape(kept, width), self.row_unit[keep]


@dataclass(frozen=True)
class _Model:
    """The prebuilt Functions of one problem structure. Layouts: inputs U (2, N n) and node
    states Z (4, N n) with column k n + i = interval/node k, unit i."""

    n: int
    m: int
    linearized: bool
    rate_rows: bool
    rollout: _Evaluator  # (z0 (4, n), U) -> the simulated node states (4, Nn)
    controller: _Evaluator  # (states (5, n), velocities (2, n)) -> the controller's inputs (2, N n)
    residual: _Evaluator  # (Z, U, p) -> r
    shoot_jacobian: _Evaluator  # (starts (4, Nn), U) -> ends, A (4, 4 Nn), B (4, 2 Nn)
    residual_jacobian: _Evaluator  # (Z, U, p) -> r, dr/dvec(Z), dr/dvec(U), sparse
    chain: _Chain  # the nonzeros of residual_jacobian -> dr/dU
    qp: _Evaluator | None
    nlp: ca.Function | None


# The prebuilt models of this process, by allocator options and problem structure: shared by
# every instance with the same options (a harness or soak makes one instance per run or chunk,
# and a model costs about 0.2 s to build). Instances hold only their warm start and fallback.
_MODELS: dict[tuple[Any, ...], _Model] = {}


INTERVALS = Option(
    "intervals",
    10,
    "shooting intervals N over the horizon (horizon = N resolve_every dt)",
    Integer(at_least=1),
)
RESOLVE_EVERY = Option(
    "resolve_every",
    5,
    "simulation steps per interval and per solve; between solves the plan is handed on",
    Integer(at_least=1),
)
TASK_WEIGHTS = Option(
    "task_weights", None, "multipliers of the scaled task rows (m,); None: all 1", Numbers(at_least=0)
)
SPEED_SMOOTHNESS = Option(
    "speed_smoothness",
    1e-2,
    "weight of squared speed changes between intervals ((m/s)^-2)",
    Number(at_least=0),
)
STEERING_SMOOTHNESS = Option(
    "steering_smoothness",
    1e-3,
    "weight of squared steering changes between intervals (rad^-2)",
    Number(at_least=0),
)
NOMINAL_WEIGHT = Option(
    "nominal_weight",
    1.0,
    "weight of the squared deviation from the nominal velocity ((m/s)^-2)",
    Number(at_least=0),
)
PRECEDENCE_WEIGHT = Option(
    "precedence_weight",
    1.0,
    "multiplier of nominal_weight for units under the precedence rule near an obstacle; 1 is off",
    Number(at_least=0),
)
OBSTACLE_MARGIN = Option(
    "obstacle_margin",
    0.15,
    "clearance from an obstacle's surface below which the penalty acts (m)",
    Number(at_least=0),
)
OBSTACLE_WEIGHT = Option(
    "obstacle_weight",
    100.0,
    "cost of a 1 cm obstacle intrusion relative to a 1 cm task error",
    Number(at_least=0),
)
SHADOW_WEIGHT = Option(
    "shadow_weight",
    0.1,
    "cost of a unit 1 cm inside an obstacle's shadow relative to a 1 cm task error; 0 is off",
    Number(at_least=0),
)
SHADOW_LENGTH = Option(
    "shadow_length", 1.5, "how far behind an obstacle's centre its shadow reaches (m)", Number(above=0)
)
UNIT_CLEARANCE = Option(
    "unit_clearance", 0.3, "distance between two units below which the penalty acts (m)", Number(at_least=0)
)
CLEARANCE_WEIGHT = Option(
    "clearance_weight",
    1.0,
    "cost of a 1 cm inter-unit intrusion relative to a 1 cm task error",
    Number(at_least=0),
)
GEARS = Option(
    "gears",
    "free",
    "free: the sign of each speed is free; rule: each unit keeps the gear rule's gear",
    Choice(("free", "rule")),
)
BACKEND = Option(
    "backend",
    "sqp",
    "sqp (Gauss-Newton SQP) or ipopt (the multiple-shooting NLP, the reference)",
    Choice(("sqp", "ipopt")),
)
MAX_ITERATIONS = Option(
    "max_iterations", None, "SQP iterations per solve (None: 4), or IPOPT's (None: 100)", Integer(at_least=1)
)
SECOND_START = Option(
    "second_start",
    True,
    "also solve from the base controller's rollout and keep the better (twice the work)",
    Flag(),
)
STEP_TOLERANCE = Option(
    "step_tolerance",
    1e-4,
    "the SQP stops when no input step exceeds this fraction of its range",
    Number(at_least=0),
)


@dataclass(frozen=True)
class RecedingHorizon:
    """The receding-horizon allocator; the formulation is in the module docstring.

    Attributes:
        intervals: shooting intervals N over the horizon (horizon = N resolve_every dt).
        resolve_every: simulation steps per interval and per solve (the controller runs at
            1 / (resolve_every dt) Hz); between solves the plan is handed on.
        task_weights: multipliers of the scaled task rows (m,), or None for all 1.
        speed_smoothness: weight of squared speed changes between intervals ((m/s)^-2).
        steering_smoothness: weight of squared steering changes between intervals (rad^-2).
        nominal_weight: weight of the squared deviation ((m/s)^-2) of each unit's velocity over
            each interval from its nominal velocity q'_d (Eq. 5, with the avoidance terms):
            it picks the motion within the task's null space, like the QP allocators.
        precedence_weight: multiplier of ``nominal_weight`` for the units under the paper's
            precedence rule within ``2 obstacle_margin`` of an obstacle; 1 (default) is off.
        obstacle_margin: clearance from an obstacle's surface (m) below which the penalty acts.
        obstacle_weight: cost of a 1 cm obstacle intrusion relative to a 1 cm task error
            (10 recovers the seeds that stall at 100 and stalls others: one_step.md, round 5).
        shadow_weight: cost of a unit 1 cm inside an obstacle's shadow (the strip behind it, seen
            along the platoon's direction of travel, that the unit must leave to pass) relative
            to a 1 cm task error; 0 is off. See ``_shadow``. At the default 0.1 the five seeds
            that stalled without shadows (of 20) recover, and one other stalls; 1 and 10 cost the
            variances or lose the platoon (one_step.md, round 6).
        shadow_length: how far behind an obstacle's centre its shadow reaches (m).
        unit_clearance: distance between two units (m) below which the penalty acts.
        clearance_weight: cost of a 1 cm inter-unit intrusion relative to a 1 cm task error.
        gears: "free": the sign of each speed is free (the solver may back a unit up or take
            it forward; the unit controller's gear rule follows the handed velocity); "rule":
            each unit keeps the gear the model's gear rule picks for the nominal velocity.
        backend: "sqp" (Gauss-Newton SQP on the active-set QP, DAQP) or "ipopt".
        max_iterations: SQP iterations per solve (default 4), or IPOPT iterations (default 100).
        second_start: also solve from the base controller's rollout (see ``_allocate``) and
            keep the better solution; doubles the work per solve. On by default: with the
            shifted plan alone the allocator lost to the paper's iteration on every error
            over 20 seeds (experiments/one_step.md).
        step_tolerance: the SQP stops when no input step exceeds this fraction of its range.
    """

    intervals: int = INTERVALS.field()
    resolve_every: int = RESOLVE_EVERY.field()
    task_weights: tuple[float, ...] | None = TASK_WEIGHTS.field()
    speed_smoothness: float = SPEED_SMOOTHNESS.field()
    steering_smoothness: float = STEERING_SMOOTHNESS.field()
    nominal_weight: float = NOMINAL_WEIGHT.field()
    precedence_weight: float = PRECEDENCE_WEIGHT.field()
    obstacle_margin: float = OBSTACLE_MARGIN.field()
    obstacle_weight: float = OBSTACLE_WEIGHT.field()
    shadow_weight: float = SHADOW_WEIGHT.field()
    shadow_length: float = SHADOW_LENGTH.field()
    unit_clearance: float = UNIT_CLEARANCE.field()
    clearance_weight: float = CLEARANCE_WEIGHT.field()
    gears: str = GEARS.field()
    backend: str = BACKEND.field()
    max_iterations: int | None = MAX_ITERATIONS.field()
    second_start: bool = SECOND_START.field()
    step_tolerance: float = STEP_TOLERANCE.field()
    _cache: dict[Any, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_options(self, "nmpc")
        if self.max_iterations is None:
            object.__setattr__(self, "max_iterations", 4 if self.backend == "sqp" else 100)

    @property
    def name(self) -> str:
        gears = ", rule gears" if self.gears == "rule" else ""
        return f"nmpc({self.backend}, N={self.intervals}, h={self.resolve_every}dt{gears})"

    @property
    def promise(self) -> str:
        gears = "the model's" if self.gears == "rule" else "either"
        return f"every unit in the sector of the gear it is handed ({gears}), not rate-aware"

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        if self.gears == "rule":
            return float(np.max(problem.achievable().distance(allocation.velocities)))
        sets = AchievableSets.for_gear(problem.state, np.ones(problem.n), problem.limits)
        return float(np.max(sets.distance_either_gear(allocation.velocities)))

    # --- building -----------------------------------------------------------------------------

    def _model(self, problem: AllocationProblem) -> _Model:
        expression = task_expression(problem.task)
        # A task with an expression is compiled into the model (a symbolic task's is its own);
        # any other is linearized at each solve, so one model serves every such task.
        if expression is None:
            compiled = None
        elif isinstance(problem.task, SymbolicTask):
            compiled = problem.task.expression
        else:
            compiled = type(problem.task)
        structure = (
            problem.n,
            problem.task_value.shape[0],
            len(problem.obstacles),
            problem.dt,
            problem.limits,
        )
        # The options, not the instance: the key must not keep an instance's plan alive.
        options = tuple(getattr(self, option.name) for option in fields(self) if option.compare)
        key = (options, *structure, compiled)
        if key not in _MODELS:
            _MODELS[key] = self._build(problem, expression)
        return _MODELS[key]

    def _build(self, problem: AllocationProblem, expression: Callable[..., Any] | None) -> _Model:
        n, m, limits, N = problem.n, problem.task_value.shape[0], problem.limits, self.intervals
        n_obstacles = len(problem.obstacles)
        h = self.resolve_every * problem.dt
        interval = unit_interval(self.resolve_every, problem.dt, limits.length)
        z, u = ca.SX.sym("z", 4), ca.SX.sym("u", 2)
        end = interval(z, u)
        with_jacobian = ca.Function(
            "unit_interval_jacobian",
            [z, u],
            [end, ca.densify(ca.jacobian(end, z)), ca.densify(ca.jacobian(end, u))],
        )

        # Residuals r(Z, U; p).
        Z, U = ca.SX.sym("z", 4, N * n), ca.SX.sym("u", 2, N * n)
        previous_speed, alpha0, theta0 = (
            ca.SX.sym("s_prev", n),
            ca.SX.sym("alpha0", n),
            ca.SX.sym("theta0", n),
        )
        nominal, nominal_scale = ca.SX.sym("nominal", n, 2), ca.SX.sym("nominal_scale", n)
        desired, desired_rate, weights = ca.SX.sym("fd", m), ca.SX.sym("fd_rate", m), ca.SX.sym("w", m)
        t0 = ca.SX.sym("t0")
        centers, radii = ca.SX.sym("centers", 2, n_obstacles), ca.SX.sym("radii", n_obstacles)
        travel = ca.SX.sym("travel", 2)
        parameters = [previous_speed, alpha0, theta0, ca.vec(nominal), nominal_scale]
        parameters += [desired, desired_rate, weights, t0]
        parameters += [ca.vec(centers), radii, travel]
        if expression is None:
            # A task without a symbolic form: its first-order model around the current state.
            value0, rows, q0 = ca.SX.sym("f0", m), ca.SX.sym("J", m, 2 * n), ca.SX.sym("q0", 2 * n)
            parameters += [value0, ca.vec(rows), q0]

            def task_at(x: ca.SX, y: ca.SX, t: ca.SX) -> ca.SX:
                return value0 + ca.mtimes(rows, ca.vertcat(x, y) - q0)

        else:

            def task_at(x: ca.SX, y: ca.SX, t: ca.SX) -> ca.SX:
                value = expression(x, y, t)
                return ca.vec(ca.vertcat(*value) if isinstance(value, (list, tuple)) else ca.SX(value))

        p = ca.vertcat(*parameters)
        task_rows, speed_rows, steering_rows, nominal_rows, obstacle_rows, pair_rows = [], [], [], [], [], []
        shadow_rows = []
        first = [i for i in range(n) for _ in range(i + 1, n)]
        second = [j for i in range(n) for j in range(i + 1, n)]
        speed_before, steering_before, heading_before = previous_speed, alpha0, theta0
        for k in range(N):
            columns = slice(k * n, (k + 1) * n)
            x, y = Z[0, columns].T, Z[1, columns].T
            speed, steering = U[0, columns].T, U[1, columns].T
            # The tip's velocity over interval k, at its start heading and end steering.
            direction = heading_before + steering
            velocity = ca.horzcat(speed * ca.cos(direction), speed * ca.sin(direction))
            deviation = ca.repmat(nominal_scale, 1, 2) * (velocity - nominal)
            nominal_rows.append(math.sqrt(self.nominal_weight / (N * n)) * ca.vec(deviation))
            heading_before = Z[2, columns].T
            tau = (k + 1) * h
            error = task_at(x, y, t0 + tau) - (desired + tau * desired_rate)
            task_rows.append(weights * error / (ERROR_SCALE * math.sqrt(N)))
            speed_rows.append(math.sqrt(self.speed_smoothness / (N * n)) * (speed - speed_before))
            steering_rows.append(math.sqrt(self.steering_smoothness / (N * n)) * (steering - steering_before))
            speed_before, steering_before = speed, steering
            for o in range(n_obstacles):
                distance = ca.sqrt((x - centers[0, o]) ** 2 + (y - centers[1, o]) ** 2 + 1e-12)
                intrusion = ca.fmax(0, radii[o] + self.obstacle_margin - distance)
                obstacle_rows.append(math.sqrt(self.obstacle_weight / N) * intrusion / ERROR_SCALE)
                if self.shadow_weight > 0:
                    shadow = self._shadow(x, y, centers[:, o], radii[o], travel)
                    shadow_rows.append(math.sqrt(self.shadow_weight / N) * shadow)
            if first and self.clearance_weight > 0:
                distance = ca.sqrt((x[first] - x[second]) ** 2 + (y[first] - y[second]) ** 2 + 1e-12)
                intrusion = ca.fmax(0, self.unit_clearance - distance)
                pair_rows.append(math.sqrt(self.clearance_weight / N) * intrusion / ERROR_SCALE)
        residual = ca.vertcat(
            *task_rows, *speed_rows, *steering_rows, *nominal_rows, *obstacle_rows, *pair_rows, *shadow_rows
        )
        residual_jacobian = ca.Function(
            "residual_jacobian",
            [Z, U, p],
            [residual, ca.jacobian(residual, ca.vec(Z)), ca.jacobian(residual, ca.vec(U))],
        )
        # The steering-rate rows |a_k - a_{k-1}| <= alpha_dot_max h (k >= 1) matter only when a
        # rate-limited interval cannot sweep the whole steering range.
        rate_rows = limits.max_steering_rate * h < 2 * limits.max_steering
        variables, constraints = 2 * n * N, (n * (N - 1) if rate_rows else 0)

        start, nodes, state = ca.SX.sym("start", 4, n), [], None
        for k in range(N):
            state = interval.map(n)(start if k == 0 else state, U[:, k * n : (k + 1) * n])
            nodes.append(state)

        qp = nlp = None
        if self.backend == "sqp":
            qp = _Evaluator(
                ca.conic(
                    "nmpc_qp",
                    "daqp",
                    {
                        "h": ca.Sparsity.dense(variables, variables),
                        "a": ca.Sparsity.dense(constraints, variables),
                    },
                    {"error_on_fail": False},
                )
            )
        else:
            z0 = ca.SX.sym("z0", 4, n)
            starts = ca.horzcat(z0, Z[:, : (N - 1) * n])
            gaps = ca.vec(interval.map(N * n)(starts, U) - Z)
            rates = ca.vec(U[1, n:] - U[1, :-n]) if rate_rows else ca.SX(0, 1)
            objective = 0.5 * ca.sumsqr(residual)
            nlp = ca.nlpsol(
                "nmpc_nlp",
                "ipopt",
                {
                    "x": ca.vertcat(ca.vec(U), ca.vec(Z)),
                    "p": ca.vertcat(ca.vec(z0), p),
                    "f": objective,
                    "g": ca.vertcat(gaps, rates),
                },
                {
                    "print_time": False,
                    "error_on_fail": False,
                    "ipopt": {
                        "print_level": 0,
                        "sb": "yes",
                        "max_iter": self.max_iterations,
                        "tol": 1e-8,
                    },
                },
            )
        return _Model(
            n=n,
            m=m,
            linearized=expression is None,
            rate_rows=rate_rows,
            rollout=_Evaluator(ca.Function("rollout", [start, U], [ca.horzcat(*nodes)])),
            controller=_Evaluator(controller_rollout(N, self.resolve_every, problem.dt, limits).map(n)),
            residual=_Evaluator(ca.Function("residual", [Z, U, p], [residual])),
            shoot_jacobian=_Evaluator(with_jacobian.map(N * n)),
            residual_jacobian=_Evaluator(residual_jacobian),
            chain=_Chain.of(residual_jacobian, N, n),
            qp=qp,
            nlp=nlp,
        )

    def _shadow(self, x: ca.SX, y: ca.SX, center: ca.SX, radius: ca.SX, travel: ca.SX) -> ca.SX:
        """Each unit's depth (in ``ERROR_SCALE``) inside the shadow of one obstacle: the strip of
        half-width ``radius + obstacle_margin`` behind its centre along ``travel`` (the unit
        direction of the platoon's nominal motion, or 0 for none), reaching ``shadow_length``
        back and weighted from 0 there to 1 at the centre (and back to 0 at the strip's
        half-width beyond it).

        A terminal cost in spirit: a unit in an obstacle's shadow will have to leave it
        sideways to pass, and the later it does, the more task error the detour costs. The
        obstacle penalty alone sees that only within the horizon, and a unit that meets the
        obstacle head on can stall against it (experiments/one_step.md).
        """
        dx, dy = x - center[0], y - center[1]
        along = dx * travel[0] + dy * travel[1]
        lateral = ca.sqrt((dx * travel[1] - dy * travel[0]) ** 2 + 1e-12)
        width = radius + self.obstacle_margin
        gate = ca.fmax(0, ca.fmin(1 + along / self.shadow_length, 1 - along / width))
        return ca.sumsqr(travel) * gate * ca.fmax(0, width - lateral) / ERROR_SCALE

    # --- one step -----------------------------------------------------------------------------

    def allocate(self, problem: AllocationProblem) -> Allocation:
        start = time.perf_counter()
        try:
            return self._allocate(problem, start)
        except Exception as error:  # never raise out of allocate: the fallback answers
            self._cache.pop("plan", None)
            return self._fallback(problem, type(error).__name__, start)

    def _allocate(self, problem: AllocationProblem, start: float) -> Allocation:
        plan = self._cache.get("plan")
        if plan is not None:
            steps = round((problem.t - plan["t"]) / problem.dt)
            same_run = plan["n"] == problem.n and plan["dt"] == problem.dt and problem.t > plan["t"] - 1e-12
            if same_run and 0 < steps < self.resolve_every:
                return Allocation.of(
                    problem,
                    self._hand(problem, plan, steps),
                    allocator=self.name,
                    status="plan",
                    iterations=0,
                    solve_time=time.perf_counter() - start,
                    substep=steps,
                )
            if not same_run or steps != self.resolve_every:
                # A new run (time went back, another platoon or step) or a gap: start cold.
                plan = None
                self._cache.pop("plan")
        model = self._model(problem)
        # Starts: the plan shifted by one interval and, cold or with second_start, what the unit
        # controllers would do holding the nominal velocity (its gears from the gear rule); the
        # better local solution wins.
        starts = []
        if plan is not None:
            starts.append(np.concatenate((plan["U"][1:], plan["U"][-1:])))
        if plan is None or self.second_start:
            starts.append(self._rollout_inputs(problem, model))
        previous_speed = plan["U"][0, :, 0] if plan is not None else starts[0][0, :, 0]
        p = self._parameters(problem, model, previous_speed)
        low, high = self._input_bounds(problem)
        solve = self._sqp if self.backend == "sqp" else self._ipopt
        best, iterations = None, 0
        for start_inputs in starts:
            result = solve(problem, model, np.clip(start_inputs, low, high), p, low, high)
            iterations += result[3]
            usable = not result[2].startswith("failed") and np.all(np.isfinite(result[0]))
            if best is None or (usable and (best[2].startswith("failed") or result[4] < best[4])):
                best = result
        U, Z, status, _, cost = best
        if status.startswith("failed") or not (np.all(np.isfinite(U)) and np.all(np.isfinite(Z))):
            self._cache.pop("plan", None)
            return self._fallback(problem, status.removeprefix("failed:"), start, iterations=iterations)
        plan = {
            "t": problem.t,
            "n": problem.n,
            "dt": problem.dt,
            "U": U,
            "Z": Z,
            "alpha0": problem.state.alpha,
        }
        self._cache["plan"] = plan
        return Allocation.of(
            problem,
            self._hand(problem, plan, 0),
            allocator=self.name,
            status=status,
            iterations=iterations,
            solve_time=time.perf_counter() - start,
            substep=0,
            cost=cost,
        )

    # --- solvers ------------------------------------------------------------------------------

    def _sqp(
        self,
        problem: AllocationProblem,
        model: _Model,
        U: np.ndarray,
        p: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, str, int, float]:
        """Gauss-Newton SQP in the inputs U (N, n, 2) within bounds (N, n, 2); returns U, the
        simulated node states Z (N, n, 4), the status, the iterations and the cost."""
        N, n, limits = self.intervals, problem.n, problem.limits
        z0 = _state_array(problem)
        scale = np.array([limits.max_speed, limits.max_steering])
        rate_bound = limits.max_steering_rate * self.resolve_every * problem.dt

        def simulate(inputs: np.ndarray) -> tuple[np.ndarray, float]:
            (states,) = model.rollout(z0.T, _to_columns(inputs))
            states = _from_columns(states.reshape(4, -1, order="F"), N, n)
            (residual,) = model.residual(_to_columns(states), _to_columns(inputs), p)
            return states, 0.5 * float(residual @ residual)

        Z, cost, guess = *simulate(U), None
        for iteration in range(1, self.max_iterations + 1):
            starts = np.concatenate((z0[None], Z[:-1]))
            _, A, B = model.shoot_jacobian(_to_columns(starts), _to_columns(U))
            # Column-major (4, 4 N n) and (4, 2 N n): block k n + i holds unit i's interval k.
            A = A.reshape(4, 4, n, N, order="F").transpose(3, 2, 0, 1)
            B = B.reshape(4, 2, n, N, order="F").transpose(3, 2, 0, 1)
            # Sensitivities of the simulated states, unit by unit: dZ_{k+1} = A_k dZ_k + B_k dU_k
            # with dZ_0 = 0, so dZ_{k+1} = sum_j G[k, j] dU_j.
            G = np.zeros((N, N, n, 4, 2))
            G[0, 0] = B[0]
            for k in range(1, N):
                G[k, :k] = A[k][None] @ G[k - 1, :k]
                G[k, k] = B[k]
            r, R, units = model.chain(*model.residual_jacobian(_to_columns(Z), _to_columns(U), p), G)
            # The step in the chain's unit-major order, (n, N, 2).
            step_low, step_high = (low - U).transpose(1, 0, 2).ravel(), (high - U).transpose(1, 0, 2).ravel()
            gradient = R.T @ r
            x, why, guess = self._step(model, R, units, gradient, step_low, step_high, U, rate_bound, guess)
            if x is None:
                return U, Z, f"failed:qp {why}".rstrip(), iteration, cost
            step = x.reshape(n, N, 2).transpose(1, 0, 2)
            # Backtrack on the cost of the simulated trajectory (Armijo, against the decrease the
            # Gauss-Newton model predicts): full steps oscillate between the bounds when many
            # inputs saturate, as in a cold start.
            predicted = float(gradient @ x + 0.5 * (np.sum((R @ x) ** 2) + _DAMPING * x @ x))
            fraction = 1.0
            for _ in range(8):
                trial = np.clip(U + fraction * step, low, high)
                trial_states, trial_cost = simulate(trial)
                if trial_cost <= cost + 1e-4 * fraction * predicted:
                    break
                fraction /= 2
            else:
                return U, Z, "stalled", iteration, cost
            U, Z, cost = trial, trial_states, trial_cost
            if fraction * np.max(np.abs(step) / scale) <= self.step_tolerance:
                return U, Z, "converged", iteration, cost
        return U, Z, "max_iterations", self.max_iterations, cost

    def _step(
        self,
        model: _Model,
        R: np.ndarray,
        units: np.ndarray,
        gradient: np.ndarray,
        step_low: np.ndarray,
        step_high: np.ndarray,
        U: np.ndarray,
        rate_bound: float,
        guess: BoxSolution | None,
    ) -> tuple[np.ndarray | None, str, BoxSolution | None]:
        """The Gauss-Newton step x ((2 N n,), the chain's unit-major order) within the bounds (and
        the rate rows), or None and why; and the active sets for the next iteration's guess.

        With box constraints alone: the active-set Newton method on the Hessian split into one
        block per unit and the coupling rows (from ``guess``, the previous iteration's sets),
        then DAQP and projected Newton on the dense Hessian if its sets cycle. With rate rows:
        DAQP.
        """
        N, n = U.shape[:2]
        if not model.rate_rows:
            blocks = np.empty((n, 2 * N, 2 * N))
            for i in range(n):
                own = R[units == i, 2 * N * i : 2 * N * (i + 1)]
                blocks[i] = own.T @ own
            blocks[:, np.arange(2 * N), np.arange(2 * N)] += _DAMPING
            guess = active_set_newton(
                BlockLowRank(blocks, R[units < 0]), gradient, step_low, step_high, guess
            )
            if guess.x is not None:
                return guess.x, "", guess
        hessian = R.T @ R
        hessian.flat[:: hessian.shape[0] + 1] += _DAMPING
        rows = self._rate_rows(U, rate_bound) if model.rate_rows else (np.zeros(0),) * 3
        x, *_ = model.qp(hessian, gradient, *rows, step_low, step_high)
        stats = model.qp.stats()
        if stats.get("success", False) and np.all(np.isfinite(x)):
            return x.copy(), "", guess
        if not model.rate_rows:
            x = projected_newton(hessian, gradient, step_low, step_high)
        return x, "" if x is not None else str(stats.get("return_status", "")), guess

    def _rate_rows(self, U: np.ndarray, rate_bound: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows D dU in [lower, upper] keeping |a_{k+1} - a_k| <= rate_bound (k = 0..N-2); the
        columns of dU unit-major, as the chain's."""
        N, n = U.shape[:2]
        difference = np.zeros((N - 1, n, n, N, 2))
        for i in range(n):
            difference[:, i, i, 1:, 1] += np.eye(N - 1)
            difference[:, i, i, :-1, 1] -= np.eye(N - 1)
        change = U[1:, :, 1] - U[:-1, :, 1]
        return (
            difference.reshape(-1, 2 * N * n),
            (-rate_bound - change).reshape(-1),
            (rate_bound - change).reshape(-1),
        )

    def _ipopt(
        self,
        problem: AllocationProblem,
        model: _Model,
        U: np.ndarray,
        p: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, str, int, float]:
        """IPOPT on the multiple-shooting NLP, from U and its simulated states; as ``_sqp``."""
        N, n, limits = self.intervals, problem.n, problem.limits
        (states,) = model.rollout(_state_array(problem).T, _to_columns(U))
        Z = _from_columns(states.reshape(4, -1, order="F"), N, n)
        z_low = np.broadcast_to([-np.inf, -np.inf, -np.inf, -limits.max_steering], (N, n, 4))
        z_high = np.broadcast_to([np.inf, np.inf, np.inf, limits.max_steering], (N, n, 4))
        rate_bound = limits.max_steering_rate * self.resolve_every * problem.dt
        n_rates = n * (N - 1) if model.rate_rows else 0
        result = model.nlp(
            x0=np.concatenate((_to_columns(U).reshape(-1, order="F"), _to_columns(Z).reshape(-1, order="F"))),
            p=np.concatenate((_state_array(problem).reshape(-1), p)),
            lbx=np.concatenate(
                (_to_columns(low).reshape(-1, order="F"), _to_columns(z_low).reshape(-1, order="F"))
            ),
            ubx=np.concatenate(
                (_to_columns(high).reshape(-1, order="F"), _to_columns(z_high).reshape(-1, order="F"))
            ),
            lbg=np.concatenate((np.zeros(4 * n * N), np.full(n_rates, -rate_bound))),
            ubg=np.concatenate((np.zeros(4 * n * N), np.full(n_rates, rate_bound))),
        )
        stats = model.nlp.stats()
        status, iterations = stats.get("return_status", "unknown"), int(stats.get("iter_count", 0))
        x = np.asarray(result["x"]).reshape(-1)
        split = 2 * n * N
        U = _from_columns(x[:split].reshape(2, -1, order="F"), N, n)
        Z = _from_columns(x[split:].reshape(4, -1, order="F"), N, n)
        cost = float(result["f"])
        if status not in _IPOPT_SUCCESS:
            return U, Z, f"failed:{status}", iterations, cost
        return U, Z, "optimal" if status == "Solve_Succeeded" else "acceptable", iterations, cost

    # --- helpers ------------------------------------------------------------------------------

    def _parameters(
        self, problem: AllocationProblem, model: _Model, previous_speed: np.ndarray
    ) -> np.ndarray:
        """The parameter vector p of the residuals."""
        n, m = problem.n, model.m
        rows = problem.jacobian.rows
        row_norm = np.sqrt(np.einsum("kij,kij->k", rows, rows))
        weights = 1.0 / (math.sqrt(n) * np.maximum(row_norm, _ROW_NORM_FLOOR))
        if self.task_weights is not None:
            if len(self.task_weights) != m:
                raise ValueError(f"nmpc: task_weights must have {m} entries, got {self.task_weights!r}")
            weights = weights * np.asarray(self.task_weights)
        parameters = [
            previous_speed,
            problem.state.alpha,
            problem.state.theta,
            problem.nominal.reshape(-1, order="F"),
            self._nominal_scale(problem),
            problem.desired,
            problem.desired_rate,
            weights,
            [problem.t],
            problem.obstacles.centers.reshape(-1),
            problem.obstacles.radii,
            self._travel(problem),
        ]
        if model.linearized:
            dense = np.concatenate((rows[:, :, 0], rows[:, :, 1]), axis=1)  # (m, 2n): O(m n)
            positions = problem.state.positions
            parameters += [problem.task_value, dense.reshape(-1, order="F"), positions.T.reshape(-1)]
        return np.concatenate([np.asarray(v, dtype=float).reshape(-1) for v in parameters])

    @staticmethod
    def _travel(problem: AllocationProblem) -> np.ndarray:
        """The unit direction (2,) of the platoon's nominal motion (the mean of the units' nominal
        velocities), or 0 when the platoon is to hold still."""
        motion = problem.nominal.mean(axis=0)
        speed = float(np.hypot(*motion))
        return motion / speed if speed > _DIRECTION_ONLY_SPEED else np.zeros(2)

    def _nominal_scale(self, problem: AllocationProblem) -> np.ndarray:
        """Factor (n,) of each unit's nominal-velocity rows: sqrt(precedence_weight) for the units
        under the precedence rule within 2 obstacle_margin of an obstacle, else 1."""
        if self.precedence_weight == 1:
            return np.ones(problem.n)  # the rule is off: no obstacle distances needed
        clearance, _ = problem.obstacles.nearest(problem.state.positions)
        near = problem.exempt & (clearance < 2 * self.obstacle_margin)
        return np.where(near, math.sqrt(self.precedence_weight), 1.0)

    def _input_bounds(self, problem: AllocationProblem) -> tuple[np.ndarray, np.ndarray]:
        """Bounds on U, each (N, n, 2): the speed (one-signed per the gear rule if gears="rule")
        and the steering angle (the first interval's also within the rate limit of alpha now)."""
        limits, n, N = problem.limits, problem.n, self.intervals
        speed_low, speed_high = np.full(n, -limits.max_speed), np.full(n, limits.max_speed)
        if self.gears == "rule":
            speed_low = np.where(problem.gear > 0, 0.0, speed_low)
            speed_high = np.where(problem.gear > 0, speed_high, 0.0)
        low, high = np.empty((N, n, 2)), np.empty((N, n, 2))
        low[:, :, 0], high[:, :, 0] = speed_low, speed_high
        low[:, :, 1], high[:, :, 1] = -limits.max_steering, limits.max_steering
        reach = limits.max_steering_rate * self.resolve_every * problem.dt
        low[0, :, 1] = np.maximum(low[0, :, 1], problem.state.alpha - reach)
        high[0, :, 1] = np.minimum(high[0, :, 1], problem.state.alpha + reach)
        return low, high

    def _rollout_inputs(self, problem: AllocationProblem, model: _Model) -> np.ndarray:
        """The inputs (N, n, 2) the unit controllers produce holding the nominal velocity."""
        state = problem.state
        states = np.vstack((state.x, state.y, state.theta, state.alpha, state.gear))
        (inputs,) = model.controller(states, problem.nominal.T)
        return inputs.reshape(problem.n, self.intervals, 2).transpose(1, 0, 2)

    def _hand(self, problem: AllocationProblem, plan: dict[str, Any], substep: int) -> np.ndarray:
        """Velocities (n, 2) that make the unit controller follow interval 0 of ``plan`` at
        ``substep`` (0 = the step of the solve): speed s_0 and the planned steering angle."""
        state, limits, dt = problem.state, problem.limits, problem.dt
        speed, steering = plan["U"][0, :, 0], plan["U"][0, :, 1]
        planned = plan["alpha0"] + (steering - plan["alpha0"]) * (substep + 1) / self.resolve_every
        # The unit controller turns the steering by K_alpha (target - alpha) dt: invert that.
        target = state.alpha + (planned - state.alpha) / (limits.steering_gain * dt)
        target = np.clip(target, -limits.max_steering, limits.max_steering)
        backing = np.where(speed != 0, speed < 0, state.gear < 0)
        direction = state.theta + target + np.where(backing, np.pi, 0.0)
        length = np.maximum(np.abs(speed), _DIRECTION_ONLY_SPEED)
        return length[:, None] * np.column_stack((np.cos(direction), np.sin(direction)))

    def _fallback(
        self, problem: AllocationProblem, why: str, start: float, iterations: int = 0
    ) -> Allocation:
        if "fallback" not in self._cache:
            self._cache["fallback"] = (
                get_allocator("qp")
                if "qp" in available_allocators()
                else get_allocator("iterative", max_iterations=4)
            )
        fallback: Allocator = self._cache["fallback"]
        result = fallback.allocate(problem)
        return Allocation.of(
            problem,
            result.velocities,
            allocator=self.name,
            status=f"fallback:{why}",
            iterations=iterations,
            solve_time=time.perf_counter() - start,
            fell_back=True,
            fallback=fallback.name,
        )


def _state_array(problem: AllocationProblem) -> np.ndarray:
    """The current unit states (n, 4): x, y, theta, alpha."""
    state = problem.state
    return np.column_stack((state.x, state.y, state.theta, state.alpha))


def _to_columns(array: np.ndarray) -> np.ndarray:
    """(N, n, c) -> (c, N n), column k n + i."""
    N, n, c = array.shape
    return array.reshape(N * n, c).T


def _from_columns(columns: np.ndarray, N: int, n: int) -> np.ndarray:
    """(c, N n) -> (N, n, c)."""
    return np.asarray(columns).T.reshape(N, n, -1)


register(
    "nmpc",
    RecedingHorizon,
    summary="receding-horizon control over the exact tricycle kinematics (CasADi, Gauss-Newton SQP)",
    use="plans ahead through turns and around obstacles; 20-60 ms per solve at n = 8: tens of units",
)
