"""The compiled CasADi Functions of one problem structure of the receding horizon (docs/nmpc.md).

``horizon_for(problem, formulation, backend, max_iterations)`` returns the prebuilt Functions
(``Horizon``) of the problem's structure (units, task rows, obstacles, dt, limits, task
expression), built once per process: the exact kinematics of one interval (docs/nmpc.md,
Eq. 1.6), the unit controllers' rollout (section 4.6), the residuals and their sparse
Jacobians (section 2, chained by ``Chain``: Eq. 4.2), and DAQP's QP (section 4.3) or IPOPT's
NLP (section 5).
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.nmpc import box_qp
from platoon_opt.solvers.nmpc.clearance import Clearance
from platoon_opt.solvers.nmpc.kinematics import interval_states
from platoon_opt.solvers.nmpc.linearization import Linearization
from platoon_opt.solvers.nmpc.residuals import Formulation, residuals
from platoon_opt.solvers.symbolic import SymbolicTask, mean_variance_expression
from platoon_opt.tasks import MeanVarianceTask
from platoon_opt.vehicle import VehicleLimits


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


def unit_interval(substeps: int, dt: float, length: float, reach: float | None = None) -> ca.Function:
    """One interval of one unit (docs/nmpc.md, Eq. 1.6): (z = (x, y, theta, alpha), u = (s, a))
    -> z after ``substeps`` steps of ``dt`` s at speed s, the steering moving from alpha to a
    linearly (``reach`` None) or by at most ``reach`` rad a step (the rate limit), then held;
    ``length`` is the unit's (m). The steps are ``kinematics.interval_states``."""
    z, u = ca.SX.sym("z", 4), ca.SX.sym("u", 2)
    states = interval_states((z[0], z[1], z[2], z[3]), u[0], u[1], substeps, dt, length, reach)
    return ca.Function("unit_interval", [z, u], [ca.vertcat(*states[-1])])


def controller_rollout(intervals: int, substeps: int, dt: float, limits: VehicleLimits) -> ca.Function:
    """One unit under its controller (the paper's Eq. 2, ``unit_controller``) holding a desired
    velocity (m/s): (state (x, y, theta, alpha, gear), velocity (2,)) -> inputs (2, intervals),
    column k the signed speed of the last substep of interval k and the steering angle at its end.

    It mirrors ``unit_controller`` and ``step_vehicles`` operation by operation (the gear rule
    with hysteresis, the clipped steering rate, ``np.mod``'s wrap and ``np.sinc``'s chord), so
    the Python loop it replaces agrees with it to rounding (tests/solvers/test_nmpc.py).
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


class Evaluator:
    """Calls a ``casadi.Function`` on preallocated NumPy buffers (no DM conversions).

    Arguments are written into ``inputs`` (each the column-major nonzeros of that input);
    ``__call__`` returns copies of the output buffers, which the next call overwrites. Copies,
    because a horizon, and so its buffers, is shared by every allocator of its formulation in the
    process (``horizon_for``): a view kept past the next call of any of them (a solution's states,
    a stored plan) would silently change. The copies cost 1-5 us a call at n = 8, N = 10, the
    calls 0.1-0.6 ms (measured on a shared 2-core machine).
    """

    def __init__(self, function: ca.Function) -> None:
        self.function = function
        self._buffer, self._evaluate = function.buffer()
        self.inputs = [np.zeros(function.nnz_in(i)) for i in range(function.n_in())]
        self.outputs = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
        # ``array.data`` is ``memoryview(array)`` (same buffer, format and shape), typed as one:
        # NumPy's stubs declare ``ndarray.__buffer__`` only for Python >= 3.12.
        for i, array in enumerate(self.inputs):
            self._buffer.set_arg(i, array.data)
        for i, array in enumerate(self.outputs):
            self._buffer.set_res(i, array.data)

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        for target, value in zip(self.inputs, args):
            target[:] = np.asarray(value, dtype=float).reshape(-1, order="F")
        self._evaluate()
        return [output.copy() for output in self.outputs]

    def stats(self) -> dict[str, Any]:
        return self._buffer.stats()


@dataclass(frozen=True)
class Chain:
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
        by_unit: the rows that involve one unit, ordered by unit, (rows of one unit,).
        u_row, u_column: of dr/dU|_Z's nonzeros (their column-major order; unit-major
            columns), each (nnz_u,).
        z_row, unit, gain_row: of dr/dZ's nonzeros (column-major order), each (nnz_z,):
            row, unit, and the row (k n + i) 4 + c of G laid out as (N n 4, N 2).
    """

    n: int
    N: int
    row_unit: np.ndarray
    by_unit: np.ndarray
    u_row: np.ndarray
    u_column: np.ndarray
    z_row: np.ndarray
    unit: np.ndarray
    gain_row: np.ndarray

    @classmethod
    def of(cls, jacobian: ca.Function, N: int, n: int) -> Chain:
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
        own = np.flatnonzero(row_unit >= 0)
        by_unit = own[np.argsort(row_unit[own], kind="stable")]
        return cls(n, N, row_unit, by_unit, u_row, u_column, z_row, unit, (node * n + unit) * 4 + coordinate)

    def __call__(
        self, residual: np.ndarray, z_values: np.ndarray, u_values: np.ndarray, G: np.ndarray
    ) -> Linearization:
        """dr/dU at the residual rows that are nonzero or have a nonzero derivative, split into
        the rows of one unit (``row_unit``) and the coupling rows, from the nonzeros of dr/dZ and
        dr/dU|_Z and G (N, N, n, 4, 2)."""
        n, block = self.n, 2 * self.N
        width = n * block
        z_live, u_live = np.flatnonzero(z_values), np.flatnonzero(u_values)
        keep = residual != 0
        keep[self.z_row[z_live]] = True
        keep[self.u_row[u_live]] = True
        own_rows = self.by_unit[keep[self.by_unit]]
        coupled_rows = np.flatnonzero(keep & (self.row_unit < 0))
        # A kept row's place among the rows of its kind.
        place = np.zeros(residual.size, dtype=np.intp)
        place[own_rows] = np.arange(own_rows.size)
        place[coupled_rows] = np.arange(coupled_rows.size)
        spread = np.arange(block)

        z_rows = self.z_row[z_live]
        terms = G.transpose(0, 2, 3, 1, 4).reshape(-1, block)[self.gain_row[z_live]] * z_values[z_live, None]
        z_own = self.row_unit[z_rows] >= 0
        own = _sums(
            (place[z_rows[z_own], None] * block + spread).ravel(), terms[z_own].ravel(), own_rows.size * block
        )
        coupled = ~z_own
        coupling = _sums(
            ((place[z_rows[coupled]] * n + self.unit[z_live[coupled]])[:, None] * block + spread).ravel(),
            terms[coupled].ravel(),
            coupled_rows.size * width,
        )
        # dr/dU|_Z: one nonzero per (row, column), so no sums.
        u_rows, u_columns, values = self.u_row[u_live], self.u_column[u_live], u_values[u_live]
        u_own = self.row_unit[u_rows] >= 0
        own[place[u_rows[u_own]] * block + u_columns[u_own] % block] += values[u_own]
        coupling[place[u_rows[~u_own]] * width + u_columns[~u_own]] += values[~u_own]
        return Linearization(
            residual[own_rows],
            own.reshape(-1, block),
            self.row_unit[own_rows],
            residual[coupled_rows],
            coupling.reshape(-1, width),
        )


def _sums(index: np.ndarray, weights: np.ndarray, size: int) -> np.ndarray:
    """The sums of ``weights`` at each ``index`` (size,), as floats: ``np.bincount`` answers
    integers when there is no index at all (no state derivative on a unit's rows, as with
    ``nominal_weight = 0``), and the derivatives dr/dU|_Z added to them would not fit."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64, copy=False)


@dataclass(frozen=True)
class Horizon:
    """The prebuilt Functions of one problem structure. Layouts: inputs U (2, N n) and node
    states Z (4, N n) with column k n + i = interval/node k, unit i."""

    n: int
    N: int
    m: int
    linearized: bool
    rate_rows: bool
    rate_bound: float  # alpha_dot_max h (rad): the steering change one interval allows
    reach: float | None  # alpha_dot_max dt (rad) with steering="rate", else None (Eq. 1.6')
    rollout: Evaluator  # (z0 (4, n), U) -> the simulated node states (4, Nn)
    controller: Evaluator  # (states (5, n), velocities (2, n)) -> the controller's inputs (2, N n)
    residual: Evaluator  # (Z, U, p) -> r
    shoot_jacobian: Evaluator  # (starts (4, Nn), U) -> ends, A (4, 4 Nn), B (4, 2 Nn)
    residual_jacobian: Evaluator  # (Z, U, p) -> r, dr/dvec(Z), dr/dvec(U), sparse
    chain: Chain  # the nonzeros of residual_jacobian -> dr/dU, split as the Hessian
    # The SQP's clearance rows, left out of residual and residual_jacobian; None without them
    # (clearance_weight = 0, or in IPOPT's NLP).
    clearance: Clearance | None
    qp: Evaluator | None  # DAQP (backend "sqp": up to box_qp.DENSE_UP_TO inputs, or with rate rows)
    nlp: ca.Function | None


# The prebuilt horizons of this process, by formulation, backend and problem structure: shared by
# every allocator with the same options (a harness or soak makes one instance per run or chunk,
# and a horizon costs about 0.2 s to build). Allocators hold only their warm start and fallback.
_HORIZONS: dict[tuple[Any, ...], Horizon] = {}


def horizon_for(
    problem: AllocationProblem, formulation: Formulation, backend: str, max_iterations: int
) -> Horizon:
    """The horizon of ``problem``'s structure, built on first use: ``backend`` "sqp" builds DAQP's
    QP, "ipopt" the NLP with ``max_iterations`` as IPOPT's cap."""
    expression = task_expression(problem.task)
    # A task with an expression is compiled into the horizon (a symbolic task's is its own);
    # any other is linearized at each solve, so one horizon serves every such task.
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
    # The options, not the allocator: the key must not keep an allocator's plan alive.
    key = (formulation, backend, max_iterations, *structure, compiled)
    if key not in _HORIZONS:
        _HORIZONS[key] = _build(problem, formulation, backend, max_iterations, expression)
    return _HORIZONS[key]


def _build(
    problem: AllocationProblem,
    formulation: Formulation,
    backend: str,
    max_iterations: int,
    expression: Callable[..., Any] | None,
) -> Horizon:
    n, m, limits, N = problem.n, problem.task_value.shape[0], problem.limits, formulation.intervals
    substeps = formulation.resolve_every
    h = substeps * problem.dt
    reach = limits.max_steering_rate * problem.dt if formulation.steering == "rate" else None
    interval = unit_interval(substeps, problem.dt, limits.length, reach)
    z, u = ca.SX.sym("z", 4), ca.SX.sym("u", 2)
    end = interval(z, u)
    with_jacobian = ca.Function(
        "unit_interval_jacobian",
        [z, u],
        [end, ca.densify(ca.jacobian(end, z)), ca.densify(ca.jacobian(end, u))],
    )
    steps = functools.partial(
        interval_states, substeps=substeps, dt=problem.dt, length=limits.length, reach=reach
    )
    # The SQP evaluates only the clearance rows of the pairs that can meet (clearance.py): all
    # n (n - 1) N / 2 of them in the model made it O(n^2) to build and to evaluate.
    clearance = None
    if backend == "sqp" and formulation.clearance_weight > 0 and n > 1:
        clearance = Clearance.of(formulation.unit_clearance, formulation.clearance_weight, N, h)
    residual, Z, U, p = residuals(
        formulation,
        n,
        m,
        len(problem.obstacles),
        problem.dt,
        steps,
        expression,
        clearance_rows=clearance is None,
    )
    residual_jacobian = ca.Function(
        "residual_jacobian",
        [Z, U, p],
        [residual, ca.jacobian(residual, ca.vec(Z)), ca.jacobian(residual, ca.vec(U))],
    )
    # The steering-rate rows |a_k - a_{k-1}| <= alpha_dot_max h (k >= 1) matter only when a
    # rate-limited interval cannot sweep the whole steering range (docs/nmpc.md, Eq. 1.5).
    rate_rows = limits.max_steering_rate * h < 2 * limits.max_steering
    variables, constraints = 2 * n * N, (n * (N - 1) if rate_rows else 0)

    start, nodes, state = ca.SX.sym("start", 4, n), [], None
    for k in range(N):
        state = interval.map(n)(start if k == 0 else state, U[:, k * n : (k + 1) * n])
        nodes.append(state)

    qp = nlp = None
    # DAQP answers the dense QPs (up to box_qp.DENSE_UP_TO inputs) and those with rate rows; above,
    # the box QPs are solved on the split, and a dense QP's buffers alone would be O((n N)^2)
    # (128 MB at n = 200).
    if backend == "sqp":
        if rate_rows or variables <= box_qp.DENSE_UP_TO:
            qp = Evaluator(
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
                    "max_iter": max_iterations,
                    "tol": 1e-8,
                },
            },
        )
    return Horizon(
        n=n,
        N=N,
        m=m,
        linearized=expression is None,
        rate_rows=rate_rows,
        # As the allocator's bounds compute it (the same rounding).
        rate_bound=limits.max_steering_rate * substeps * problem.dt,
        reach=reach,
        rollout=Evaluator(ca.Function("rollout", [start, U], [ca.horzcat(*nodes)])),
        controller=Evaluator(controller_rollout(N, substeps, problem.dt, limits).map(n)),
        residual=Evaluator(ca.Function("residual", [Z, U, p], [residual])),
        shoot_jacobian=Evaluator(with_jacobian.map(N * n)),
        residual_jacobian=Evaluator(residual_jacobian),
        chain=Chain.of(residual_jacobian, N, n),
        clearance=clearance,
        qp=qp,
        nlp=nlp,
    )
