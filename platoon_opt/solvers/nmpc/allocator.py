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

import time
from dataclasses import dataclass, field, fields

import numpy as np

from platoon_opt.limits import AchievableSets
from platoon_opt.problem import Allocation, AllocationProblem, Allocator
from platoon_opt.solvers.nmpc.model import Model, model_for
from platoon_opt.solvers.nmpc.plan import Plan
from platoon_opt.solvers.nmpc.residuals import Formulation, parameters
from platoon_opt.solvers.nmpc.solve import HorizonSolution, ipopt, sqp
from platoon_opt.solvers.options import Choice, Flag, Integer, Number, Numbers, Option, check_options
from platoon_opt.solvers.registry import available_allocators, get_allocator, register


@dataclass
class _State:
    """What an allocator keeps between calls: the plan of its last solve (None: the next call
    starts cold) and the fallback allocator, made on first use."""

    plan: Plan | None = None
    fallback: Allocator | None = None


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
    _state: _State = field(default_factory=_State, init=False, repr=False, compare=False)
    _formulation: Formulation = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_options(self, "nmpc")
        if self.max_iterations is None:
            object.__setattr__(self, "max_iterations", 4 if self.backend == "sqp" else 100)
        # The options that define the least squares, by name (a renamed field fails here).
        values = {option.name: getattr(self, option.name) for option in fields(Formulation)}
        object.__setattr__(self, "_formulation", Formulation(**values))

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

    def _model(self, problem: AllocationProblem) -> Model:
        """The prebuilt model of ``problem``'s structure under these options."""
        return model_for(problem, self._formulation, self.backend, self.max_iterations)

    # --- one step -----------------------------------------------------------------------------

    def allocate(self, problem: AllocationProblem) -> Allocation:
        start = time.perf_counter()
        try:
            return self._allocate(problem, start)
        except Exception as error:  # never raise out of allocate: the fallback answers
            self._state.plan = None
            return self._fallback(problem, type(error).__name__, start)

    def _allocate(self, problem: AllocationProblem, start: float) -> Allocation:
        plan = self._state.plan
        if plan is not None:
            steps = plan.steps_since(problem)
            if steps is not None and 0 < steps < self.resolve_every:
                return Allocation.of(
                    problem,
                    plan.hand(problem, steps),
                    allocator=self.name,
                    status="plan",
                    iterations=0,
                    solve_time=time.perf_counter() - start,
                    substep=steps,
                )
            if steps != self.resolve_every:
                # A new run (time went back, another platoon or step) or a gap: start cold.
                plan = self._state.plan = None
        model = self._model(problem)
        # Starts: the plan shifted by one interval and, cold or with second_start, what the unit
        # controllers would do holding the nominal velocity (its gears from the gear rule); the
        # better local solution wins.
        starts = []
        if plan is not None:
            starts.append(plan.shifted())
        if plan is None or self.second_start:
            starts.append(self._rollout_inputs(problem, model))
        previous_speed = plan.inputs[0, :, 0] if plan is not None else starts[0][0, :, 0]
        p = self._parameters(problem, model, previous_speed)
        low, high = self._input_bounds(problem)
        clipped = [np.clip(inputs, low, high) for inputs in starts]
        solutions = [self._solve(problem, model, inputs, p, low, high) for inputs in clipped]
        best = solutions[0]
        for other in solutions[1:]:
            usable = not other.status.startswith("failed") and np.all(np.isfinite(other.inputs))
            if usable and (best.status.startswith("failed") or other.cost < best.cost):
                best = other
        iterations = sum(solution.iterations for solution in solutions)
        U, Z, status, _, cost = best
        if status.startswith("failed") or not (np.all(np.isfinite(U)) and np.all(np.isfinite(Z))):
            self._state.plan = None
            return self._fallback(problem, status.removeprefix("failed:"), start, iterations=iterations)
        plan = Plan(
            t=problem.t,
            n=problem.n,
            dt=problem.dt,
            substeps=self.resolve_every,
            inputs=U,
            states=Z,
            alpha0=problem.state.alpha,
        )
        self._state.plan = plan
        return Allocation.of(
            problem,
            plan.hand(problem, 0),
            allocator=self.name,
            status=status,
            iterations=iterations,
            solve_time=time.perf_counter() - start,
            substep=0,
            cost=cost,
        )

    def _solve(
        self,
        problem: AllocationProblem,
        model: Model,
        U: np.ndarray,
        p: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
    ) -> HorizonSolution:
        """The backend's solve from the inputs U (N, n, 2) within the bounds (N, n, 2)."""
        if self.backend == "sqp":
            return sqp(problem, model, U, p, low, high, self.max_iterations, self.step_tolerance)
        return ipopt(problem, model, U, p, low, high)

    # --- helpers ------------------------------------------------------------------------------

    def _parameters(self, problem: AllocationProblem, model: Model, previous_speed: np.ndarray) -> np.ndarray:
        """The parameter vector p of the residuals."""
        return parameters(problem, self._formulation, model.linearized, previous_speed)

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

    def _rollout_inputs(self, problem: AllocationProblem, model: Model) -> np.ndarray:
        """The inputs (N, n, 2) the unit controllers produce holding the nominal velocity."""
        state = problem.state
        states = np.vstack((state.x, state.y, state.theta, state.alpha, state.gear))
        (inputs,) = model.controller(states, problem.nominal.T)
        return inputs.reshape(problem.n, self.intervals, 2).transpose(1, 0, 2)

    def _fallback(
        self, problem: AllocationProblem, why: str, start: float, iterations: int = 0
    ) -> Allocation:
        if self._state.fallback is None:
            self._state.fallback = (
                get_allocator("qp")
                if "qp" in available_allocators()
                else get_allocator("iterative", max_iterations=4)
            )
        fallback = self._state.fallback
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


register(
    "nmpc",
    RecedingHorizon,
    summary="receding-horizon control over the exact tricycle kinematics (CasADi, Gauss-Newton SQP)",
    use="plans ahead through turns and around obstacles; 20-60 ms per solve at n = 8: tens of units",
)
