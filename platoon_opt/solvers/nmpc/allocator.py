"""Receding-horizon allocator ("nmpc"): optimal control over the exact tricycle kinematics.

Every ``resolve_every`` simulation steps ``RecedingHorizon`` solves an optimal control problem
over ``intervals`` shooting intervals (Gauss-Newton SQP, or IPOPT as the reference) and hands
each unit the velocity that makes its controller drive the plan's first interval; between
solves it hands the stored plan. A failed solve falls back to ``qp`` (else the paper's
iteration, m = 4) with the status ``"fallback:<why>"`` (an exception's type and message);
``allocate`` raises only a ``ConfigurationError`` (``task_weights`` that do not fit the task:
``check_task`` says so before a run). The formulation is docs/nmpc.md; why the defaults are
what they are, experiments/one_step.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields

import numpy as np

from platoon_opt.allocation import Allocation, Allocator
from platoon_opt.arrays import one_blas_thread
from platoon_opt.errors import ConfigurationError, error_text
from platoon_opt.limits import AchievableSets
from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.nmpc.compiled import Horizon, horizon_for
from platoon_opt.solvers.nmpc.plan import Plan
from platoon_opt.solvers.nmpc.residuals import Formulation, check_task_weights, parameters
from platoon_opt.solvers.nmpc.solve import HorizonSolution, ipopt, sqp
from platoon_opt.solvers.options import Choice, Flag, Integer, Number, Numbers, Option, check_options
from platoon_opt.solvers.registry import available_allocators, get_allocator, register
from platoon_opt.solvers.safety import SafetyOptions, safety_filter


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
PREVIEW = Option(
    "preview",
    True,
    "track the reference over the horizon when the closed loop hands it; off: extrapolate f_d",
    Flag(),
)
STEERING = Option(
    "steering",
    "rate",
    "within an interval the steering moves to its end angle at the rate limit (rate) or linearly (linear)",
    Choice(("rate", "linear")),
)
TASK_SAMPLES = Option(
    "task_samples",
    "steps",
    "where the task rows compare f with f_d: every simulation step of the horizon (steps) or its nodes",
    Choice(("steps", "nodes")),
)
GAIN_WEIGHTS = Option(
    "gain_weights",
    True,
    "weigh each scaled task row by its tracking gain over the smallest (K_r / min K); off: alike",
    Flag(),
)
FADE_GAINS = Option(
    "fade_gains",
    False,
    "fade the gain weights toward 1 while the law asks the platoon's mean for more than the top speed",
    Flag(),
)
TASK_WEIGHTS = Option(
    "task_weights",
    None,
    "multipliers of the scaled task rows (m,), on top of the gain weights; None: all 1",
    Numbers(at_least=0),
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
PENALTY_MARGIN = Option(
    "penalty_margin",
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
class RecedingHorizon(SafetyOptions):
    """The receding-horizon allocator. Sections and equations below are docs/nmpc.md's; why
    the main defaults are what they are is experiments/one_step.md (its last section).

    Attributes:
        intervals: shooting intervals N over the horizon (horizon = N resolve_every dt).
        resolve_every: simulation steps per interval and per solve (the controller runs at
            1 / (resolve_every dt) Hz); between solves the plan is handed on (section 6).
        preview: the task rows track f_d at the horizon's nodes as the closed loop hands it
            (``problem.desired_ahead``, the reference over the next N resolve_every dt seconds);
            off, or when the problem carries none, f_d extrapolated at its rate (Eq. 1.7).
        steering: how the steering moves within an interval toward the interval's end angle:
            "rate", at the steering-rate limit, then held (Eq. 1.6'); "linear", by equal steps
            over the interval's steps (Eq. 1.6).
        task_samples: where the task rows compare the task with its target (Eq. 2.1): at every
            simulation step of the horizon ("steps"), as the errors are measured, or at its
            nodes only ("nodes").
        gain_weights: weigh each scaled task row by its tracking gain K_r over the smallest
            positive gain (Eq. 2.9: the weights under which the tracking law's response is the
            optimal one); off, every scaled row alike.
        fade_gains: with ``gain_weights``, let each gain weight w_r fade to 1 + (w_r - 1) / s,
            s the speed the law's feedback asks of the units' centroid over the top speed, at
            least 1 (Eq. 2.9'): the gains' balance where the mean's error is within what the
            units can close, the rows alike while the platoon catches up.
        task_weights: multipliers of the scaled task rows (m,), on top of ``gain_weights``, or
            None for all 1 (Eq. 2.8).
        speed_smoothness: weight of squared speed changes between intervals ((m/s)^-2, Eq. 2.2).
        steering_smoothness: weight of squared steering changes between intervals (rad^-2,
            Eq. 2.3).
        nominal_weight: weight of the squared deviation ((m/s)^-2) of each unit's velocity over
            each interval from its nominal velocity q'_d (the paper's Eq. 5, with the avoidance
            terms): it picks the motion within the task's null space, like the QP allocators
            (Eq. 2.4).
        precedence_weight: multiplier of ``nominal_weight`` for the units under the paper's
            precedence rule within ``2 penalty_margin`` of an obstacle; 1 (default) is off.
        penalty_margin: clearance from an obstacle's surface (m) below which the penalty acts.
        obstacle_weight: cost of a 1 cm obstacle intrusion relative to a 1 cm task error
            (Eq. 2.5).
        shadow_weight: cost of a unit 1 cm inside an obstacle's shadow (the strip behind it, seen
            along the platoon's direction of travel, that the unit must leave to pass) relative
            to a 1 cm task error; 0 is off (section 3).
        shadow_length: how far behind an obstacle's centre its shadow reaches (m).
        unit_clearance: distance between two units (m) below which the penalty acts (Eq. 2.7).
        clearance_weight: cost of a 1 cm inter-unit intrusion relative to a 1 cm task error.
        gears: "free": the sign of each speed is free (the solver may back a unit up or take
            it forward; the unit controller's gear rule follows the handed velocity); "rule":
            each unit keeps the gear the model's gear rule picks for the nominal velocity.
        backend: "sqp" (Gauss-Newton SQP on the active-set QP, DAQP; section 4) or "ipopt"
            (section 5).
        max_iterations: SQP iterations per solve (default 4), or IPOPT iterations (default 100).
        second_start: also solve from the unit controllers' rollout of the nominal velocity and
            keep the better solution (section 4.6); doubles the work per solve. On by default.
        step_tolerance: the SQP stops when no input step exceeds this fraction of its range.
    """

    intervals: int = INTERVALS.field()
    resolve_every: int = RESOLVE_EVERY.field()
    preview: bool = PREVIEW.field()
    steering: str = STEERING.field()
    task_samples: str = TASK_SAMPLES.field()
    gain_weights: bool = GAIN_WEIGHTS.field()
    fade_gains: bool = FADE_GAINS.field()
    task_weights: tuple[float, ...] | None = TASK_WEIGHTS.field()
    speed_smoothness: float = SPEED_SMOOTHNESS.field()
    steering_smoothness: float = STEERING_SMOOTHNESS.field()
    nominal_weight: float = NOMINAL_WEIGHT.field()
    precedence_weight: float = PRECEDENCE_WEIGHT.field()
    penalty_margin: float = PENALTY_MARGIN.field()
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
    # ``max_iterations`` resolved (None: the backend's default), as the int the solves take.
    _max_iterations: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_options(self, "nmpc")
        max_iterations = self.max_iterations
        if max_iterations is None:
            max_iterations = 4 if self.backend == "sqp" else 100
        object.__setattr__(self, "max_iterations", max_iterations)
        object.__setattr__(self, "_max_iterations", max_iterations)
        # The options that define the least squares, by name (a renamed field fails here).
        values = {option.name: getattr(self, option.name) for option in fields(Formulation)}
        object.__setattr__(self, "_formulation", Formulation(**values))

    @property
    def name(self) -> str:
        gears = ", rule gears" if self.gears == "rule" else ""
        target = "" if self.preview else ", extrapolated target"
        steering = ", linear steering" if self.steering == "linear" else ""
        samples = ", task at the nodes" if self.task_samples == "nodes" else ""
        alike = "" if self.gain_weights else ", task rows alike"
        faded = ", gains faded" if self.gain_weights and self.fade_gains else ""
        barrier = "".join(f", {part}" for part in self.safety_name())
        return (
            f"nmpc({self.backend}, N={self.intervals}, h={self.resolve_every}dt"
            f"{gears}{target}{steering}{samples}{alike}{faded}{barrier})"
        )

    @property
    def promise(self) -> str:
        gears = "the model's" if self.gears == "rule" else "either"
        return f"every unit in the sector of the gear it is handed ({gears}), not rate-aware"

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        if self.gears == "rule":
            return float(np.max(problem.achievable().distance(allocation.velocities)))
        sets = AchievableSets.for_gear(problem.state, np.ones(problem.n), problem.limits)
        return float(np.max(sets.distance_either_gear(allocation.velocities)))

    def _horizon(self, problem: AllocationProblem) -> Horizon:
        """The prebuilt horizon of ``problem``'s structure under these options."""
        return horizon_for(problem, self._formulation, self.backend, self._max_iterations)

    # --- one step -----------------------------------------------------------------------------

    def preview_times(self, problem: AllocationProblem) -> np.ndarray:
        """The times after ``problem.t`` (s) at which the task rows want f_d
        (``allocation.Previewing``): every step of the horizon, or its nodes k resolve_every dt,
        k = 1..N, with ``task_samples="nodes"``; none without ``preview`` or when this step
        hands the stored plan."""
        plan = self._state.plan
        handing = plan is not None and _handed_substep(plan, problem, self.resolve_every) is not None
        if not self.preview or handing:
            return np.empty(0)
        return self._formulation.task_times(problem.dt)

    def check_task(self, names: tuple[str, ...]) -> None:
        """``OptionError`` unless ``task_weights`` has one weight per task component (``names``)."""
        check_task_weights(self.task_weights, names)

    def allocate(self, problem: AllocationProblem) -> Allocation:
        """The plan's velocities (through ``safety_filter`` when barriers are on)."""
        start = time.perf_counter()
        try:
            safety = self.safety_for(problem)
            with one_blas_thread():  # its factors are tiny: see platoon_opt.arrays.one_blas_thread
                allocation = self._allocate(problem, start)
        except ConfigurationError:  # a bad option is the caller's to fix: no step answers it
            self._state.plan = None
            raise
        except Exception as error:  # else never raise out of allocate: the fallback answers
            self._state.plan = None
            allocation = self._fallback(problem, error_text(error), start)
        return safety_filter(problem, allocation, safety)

    def _allocate(self, problem: AllocationProblem, start: float) -> Allocation:
        """Hand the stored plan between solves, else solve from the starts (docs/nmpc.md,
        sections 4.6 and 6); a failed solve falls back."""
        plan = self._state.plan
        if plan is not None:
            steps = _handed_substep(plan, problem, self.resolve_every)
            if steps is not None:
                return Allocation.of(
                    problem,
                    plan.hand(problem, steps),
                    allocator=self.name,
                    status="plan",
                    iterations=0,
                    solve_time=time.perf_counter() - start,
                    solved=False,
                    substep=steps,
                )
            if plan.steps_since(problem) != self.resolve_every:
                # A new run (time went back, another platoon or step) or a gap: start cold.
                plan = self._state.plan = None
        horizon = self._horizon(problem)
        # Starts: the plan shifted by one interval and, cold or with second_start, what the unit
        # controllers would do holding the nominal velocity (its gears from the gear rule); the
        # better local solution wins.
        starts = []
        if plan is not None:
            starts.append(plan.shifted())
        if plan is None or self.second_start:
            starts.append(self._rollout_inputs(problem, horizon))
        previous_speed = plan.inputs[0, :, 0] if plan is not None else starts[0][0, :, 0]
        p = self._parameters(problem, horizon, previous_speed)
        low, high = self._input_bounds(problem)
        clipped = [np.clip(inputs, low, high) for inputs in starts]
        solutions = [self._solve(problem, horizon, inputs, p, low, high) for inputs in clipped]
        iterations = sum(solution.iterations for solution in solutions)
        usable = [solution for solution in solutions if _usable(solution)]
        if not usable:
            self._state.plan = None
            return self._fallback(problem, _failure(solutions), start, iterations=iterations)
        # The lowest cost; on a tie the first start (the shifted plan, if there is one).
        U, Z, status, _, cost = min(usable, key=lambda solution: solution.cost)
        plan = Plan(
            t=problem.t,
            n=problem.n,
            dt=problem.dt,
            substeps=self.resolve_every,
            reach=horizon.reach,
            inputs=U,
            states=Z,
            alpha0=problem.state.alpha,
            standstill=self.step_tolerance * problem.limits.max_speed,
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
        horizon: Horizon,
        U: np.ndarray,
        p: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
    ) -> HorizonSolution:
        """The backend's solve from the inputs U (N, n, 2) within the bounds (N, n, 2)."""
        if self.backend == "sqp":
            return sqp(problem, horizon, U, p, low, high, self._max_iterations, self.step_tolerance)
        return ipopt(problem, horizon, U, p, low, high)

    # --- helpers ------------------------------------------------------------------------------

    def _parameters(
        self, problem: AllocationProblem, horizon: Horizon, previous_speed: np.ndarray
    ) -> np.ndarray:
        """The parameter vector p of the residuals; ``previous_speed`` (n,) is the speed handed
        before this solve (m/s)."""
        return parameters(problem, self._formulation, horizon.linearized, previous_speed)

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

    def _rollout_inputs(self, problem: AllocationProblem, horizon: Horizon) -> np.ndarray:
        """The inputs (N, n, 2) the unit controllers produce holding the nominal velocity."""
        state = problem.state
        states = np.vstack((state.x, state.y, state.theta, state.alpha, state.gear))
        (inputs,) = horizon.controller(states, problem.nominal.T)
        return inputs.reshape(problem.n, self.intervals, 2).transpose(1, 0, 2)

    def _fallback(
        self, problem: AllocationProblem, why: str, start: float, iterations: int = 0
    ) -> Allocation:
        """The fallback allocator's answer, with the status ``"fallback:<why>"`` (section 7): a
        one-step program in place of the horizon's, so ``program_changed``."""
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
            program_changed=True,
            fallback=fallback.name,
            program=fallback.name,
        )


def _usable(solution: HorizonSolution) -> bool:
    """Whether a solve's answer can be handed: not failed, inputs, states and cost finite."""
    return (
        not solution.status.startswith("failed")
        and bool(np.all(np.isfinite(solution.inputs)))
        and bool(np.all(np.isfinite(solution.states)))
        and math.isfinite(solution.cost)
    )


def _failure(solutions: list[HorizonSolution]) -> str:
    """Why no solve is usable: the first failed one's reason, else non-finite values."""
    for solution in solutions:
        if solution.status.startswith("failed"):
            return solution.status.removeprefix("failed:")
    return "non-finite solution"


register(
    "nmpc",
    RecedingHorizon,
    summary="receding-horizon control over the exact tricycle kinematics (CasADi, Gauss-Newton SQP)",
    use="plans ahead through turns and around obstacles; 10-30 ms per solve at n = 8: tens of units",
)


def _handed_substep(plan: Plan, problem: AllocationProblem, resolve_every: int) -> int | None:
    """The simulation steps since ``plan``'s solve when ``problem`` comes between two solves of
    its run (the plan is handed on), else None (the step solves)."""
    steps = plan.steps_since(problem)
    return steps if steps is not None and 0 < steps < resolve_every else None
