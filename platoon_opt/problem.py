"""The seam between the model and the allocators.

``AllocationProblem`` holds every input of one control step; an allocator turns it into
an ``Allocation`` (``platoon_opt.allocation``). Shapes: n units, m task components; velocities (n, 2) in m/s.

``pose`` assembles a problem (Eq. 5) in numpy or, traced, inside the compiled engine;
``AllocationProblem.build`` checks its inputs and poses it compiled, handing numpy arrays to the
allocators.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from platoon_opt.arrays import host, namespace, pytree
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles, repulsion
from platoon_opt.barrier_constraints import Capacity
from platoon_opt.limits import AchievableSets
from platoon_opt.safe_sets import SafeSets
from platoon_opt.safety import SafetyParams
from platoon_opt.tasks import Task, TaskJacobian
from platoon_opt.validation import finite_array, positive
from platoon_opt.vehicle import PlatoonState, VehicleLimits, choose_gear, gear_axis, gear_rule

# The fields ``pose`` computes; the others are its inputs.
POSED = (
    "jacobian",
    "task_value",
    "task_velocity",
    "secondary",
    "nominal",
    "exempt",
    "gear",
    "obstacle_distance",
    "unit_distance",
)


@pytree(
    data=(
        "state",
        "limits",
        "jacobian",
        "task_value",
        "desired",
        "desired_rate",
        "gains",
        "task_velocity",
        "secondary",
        "nominal",
        "exempt",
        "gear",
        "obstacle_distance",
        "unit_distance",
        "dt",
        "t",
        "avoidance",
        "obstacles",
        "desired_ahead",
    ),
    static=("task", "safety"),
)
@dataclass(frozen=True)
class AllocationProblem:
    """Inputs of one allocation step (numpy arrays; JAX ones inside the compiled engine).

    Attributes:
        state: the platoon (n units).
        limits: vehicle limits.
        jacobian: J(q), m x 2n, stored as rows (m, n, 2).
        task_value: f(q) (m,).
        desired: f_d(t) (m,).
        desired_rate: f_d'(t) (m,).
        gains: the tracking gains K, its diagonal (m,) or the whole (m, m), 1/s.
        task_velocity: u = K (f_d - f) + f_d' - df/dt (m,).
        secondary: v = v_repo + v_repr (n, 2), m/s.
        nominal: q'_d = J^+ u + N v, Eq. 5 (n, 2), m/s.
        exempt: units under the paper's precedence rule (n,) bool.
        gear: the gear rule applied to the nominal velocity (n,), +1 / -1.
        obstacle_distance: each unit's signed distance to the nearest obstacle surface (n,), m
            (negative inside, inf without obstacles), as Eq. 6 measured it.
        unit_distance: each unit's distance to its nearest other unit within d_minr (n,), m (inf
            beyond), as Eq. 7 measured it.
        dt: control step (s).
        t: time (s).
        task: the task f (for allocators that predict, e.g. receding horizon).
        avoidance, obstacles: the avoidance parameters and obstacles of this step.
        safety: the barrier constraints the scenario asks for (``safety.SafetyParams``; an
            allocator's options may override them).
        desired_ahead: f_d at the times ``t + preview_times`` that an allocator planning ahead
            asked for (``Previewing``), (K, m); None when the caller gave no preview (such an
            allocator then extrapolates f_d at its rate).
    """

    state: PlatoonState
    limits: VehicleLimits
    jacobian: TaskJacobian
    task_value: Any
    desired: Any
    desired_rate: Any
    gains: Any
    task_velocity: Any
    secondary: Any
    nominal: Any
    exempt: Any
    gear: Any
    obstacle_distance: Any
    unit_distance: Any
    dt: Any
    t: Any
    task: Task
    avoidance: AvoidanceParams
    obstacles: CircularObstacles
    safety: SafetyParams = SafetyParams()
    desired_ahead: Any = None

    @classmethod
    def build(
        cls,
        state: PlatoonState,
        task: Task,
        desired: np.ndarray,
        desired_rate: np.ndarray,
        gains: np.ndarray,
        limits: VehicleLimits,
        dt: float,
        *,
        avoidance: AvoidanceParams | None = None,
        obstacles: CircularObstacles | None = None,
        t: float = 0.0,
        safety: SafetyParams | None = None,
        desired_ahead: np.ndarray | None = None,
        compiled: bool = False,
    ) -> AllocationProblem:
        """Check the inputs and pose one step's problem (``pose``): task velocity, repulsion, the
        nominal velocity (Eq. 5), the precedence flags and the gears, as numpy arrays.

        ``compiled``: pose it with ``pose`` compiled (once per shape; a closed loop's many steps),
        if the task can be traced (``traceable``); else in numpy (a single problem: no compile).

        Args:
            desired: f_d(t), shape (m,).
            desired_rate: f_d'(t), shape (m,).
            gains: K as its diagonal (m,) or a full (m, m) matrix; a diagonal must be >= 0.
            dt: control step (s), > 0.
            desired_ahead: f_d at later times (K, m), for an allocator that plans ahead
                (``Previewing``), or None.

        Raises:
            ValueError / TypeError naming the field and the value: wrong shapes, non-finite
            values, dt <= 0, a negative gain, a steering angle beyond the limit.
        """
        dt = positive("dt", dt)
        state.check_limits(limits)
        m = len(task.names)
        desired = finite_array("desired", desired, (m,))
        desired_rate = finite_array("desired_rate", desired_rate, (m,))
        gains = np.asarray(gains, dtype=float)
        gains = finite_array("gains", gains, (m,) if gains.ndim == 1 else (m, m))
        if gains.ndim == 1 and (gains < 0).any():
            raise ValueError(f"gains must be >= 0, got {gains!r}")
        inputs: dict[str, Any] = {
            "state": state,
            "task": task,
            "desired": desired,
            "desired_rate": desired_rate,
            "gains": gains,
            "limits": limits,
            "dt": dt,
            "avoidance": avoidance or AvoidanceParams(),
            "obstacles": obstacles if obstacles is not None else CircularObstacles.none(),
            "t": float(t),
            "safety": safety or SafetyParams(),
        }
        computed = (_pose_compiled if compiled and traceable(task) else posed_fields)(**inputs)
        if desired_ahead is not None:
            desired_ahead = finite_array("desired_ahead", desired_ahead, (None, m))
        return cls(**inputs, **computed, desired_ahead=desired_ahead)

    @property
    def n(self) -> int:
        """Number of units."""
        return self.state.n

    def achievable(self, *, rate_aware: bool = False) -> AchievableSets:
        """Each unit's achievable set C_i in its chosen gear (optionally rate-aware)."""
        if rate_aware:
            return AchievableSets.for_gear(self.state, self.gear, self.limits, rate_aware=True, dt=self.dt)
        return self._achievable

    def safe_sets(
        self,
        params: SafetyParams,
        *,
        rate_aware: bool = True,
        gear: np.ndarray | None = None,
        speed: str = "cone",
        sides: int = 16,
        capacity: Capacity | None = None,
    ) -> SafeSets:
        """Each unit's safe achievable set (``SafeSets``) under ``params``: its set in ``gear``
        (default: the chosen gear, ``self.gear``) in the speed model ``speed`` ("cone" or
        "polygon" with ``sides``), cut by its barrier rows (``capacity``: a build of fixed
        shapes for compiled code, ``SafeSets.build``). The set is rate-aware (what the
        steering reaches within the step) unless ``rate_aware=False``: over the whole steering
        range the barrier rows must allow for a steering lag of up to 67 degrees and leave a unit
        at an obstacle no way along it (docs/safety.md, section 6)."""
        if gear is None:
            sets = self.achievable(rate_aware=rate_aware)
        else:
            sets = AchievableSets.for_gear(self.state, gear, self.limits, rate_aware=rate_aware, dt=self.dt)
        return SafeSets.build(
            self.state,
            self.obstacles,
            self.limits,
            self.dt,
            sets,
            params,
            speed=speed,
            sides=sides,
            capacity=capacity,
        )

    def steered(self) -> AllocationProblem:
        """This problem with each unit's nominal velocity as the unit drives it within the step
        (``AchievableSets.steer`` over the rate-aware sector): what a program that knows the
        steering's reach measures deviation from (docs/programs.md, section 3, "Rate-aware")."""
        return dataclasses.replace(self, nominal=self.achievable(rate_aware=True).steer(self.nominal))

    def in_nearer_gears(self, where: Any = True) -> AllocationProblem:
        """This problem with each unit's gear the one whose sector lies nearer its nominal
        velocity: the gear rule without hysteresis (the sectors are symmetric about their gear's
        axis, so the nearer is the one whose axis lies within pi/2 of the velocity; a tie or a
        standing nominal keeps the gear). The paper's iteration projects onto that sector
        (docs/programs.md, section 3, "Gears"). ``where`` (a bool, or one per unit) False keeps
        the gear rule's gear."""
        xp = namespace(self.nominal)
        speed = xp.hypot(self.nominal[:, 0], self.nominal[:, 1])
        gear, _ = gear_rule(self.nominal, speed, self.state.theta, self.gear, 0.0)
        return dataclasses.replace(self, gear=xp.where(where, gear, self.gear))

    def feedback_speed(self) -> Any:
        """The speed (m/s) at which the task velocity's feedback part u - f_d', spread over the
        units at least norm (J^+), moves their centroid; for the mean-variance task
        ||K_mu (f_d,mu - mu)||. The target's own rate f_d' is left out: the units follow it in
        the gear they are in. A scalar (traced in the engine)."""
        xp = namespace(self.nominal)
        centroid = self.jacobian.pinv_apply(self.task_velocity - self.desired_rate).sum(axis=0) / self.n
        return xp.hypot(centroid[0], centroid[1])

    def catching_up(self) -> Any:
        """Whether the platoon is catching up: ``feedback_speed`` exceeds the top speed, so that
        the tracking law asks for more than every unit at full speed could give
        (docs/programs.md, section 3, "Gears"). A bool (traced in the engine)."""
        return self.feedback_speed() > self.limits.max_speed

    @cached_property
    def _achievable(self) -> AchievableSets:
        # Built once per step: allocators ask for it several times.
        return AchievableSets.for_gear(self.state, self.gear, self.limits)

    def task_residual(self, velocity: np.ndarray) -> float:
        """||J v - u||."""
        residual = self.jacobian.apply(velocity) - self.task_velocity
        # What np.linalg.norm computes for a vector, without its overhead (a few us at small n).
        return math.sqrt(float(residual @ residual))


def traceable(task: Task) -> bool:
    """Whether ``task``'s methods can run on traced JAX arrays (written with numpy or jax.numpy
    operations, ``platoon_opt.arrays.namespace``), so that the compiled engine can pose its
    problems; a task that calls a host library (CasADi, on the allocators' floor) says False."""
    return bool(getattr(task, "traceable", False))


def pose(
    state: PlatoonState,
    task: Task,
    desired: Any,
    desired_rate: Any,
    gains: Any,
    limits: VehicleLimits,
    dt: Any,
    *,
    avoidance: AvoidanceParams,
    obstacles: CircularObstacles,
    t: Any,
    safety: SafetyParams,
) -> AllocationProblem:
    """One step's problem, unchecked, in numpy or traced: u = K (f_d - f) + f_d' - df/dt, the
    repulsion v (Eqs. 6 and 7), the nominal velocity q'_d = J^+ u + N v (Eq. 5), the precedence
    flags and the gear rule applied to q'_d. ``gains`` is K's diagonal (m,) or K (m, m)."""
    positions = state.positions
    value = task.value(positions, t)
    feedback = gains * (desired - value) if gains.ndim == 1 else gains @ (desired - value)
    jacobian = task.jacobian(positions, t)
    task_velocity = feedback + desired_rate - task.time_derivative(positions, t)
    if avoidance.ahead_reference == "heading":
        reference = state.theta
    else:
        reference = gear_axis(state.theta + state.alpha, state.gear)
    push = repulsion(positions, reference, obstacles, avoidance)
    nominal = jacobian.pinv_apply(task_velocity) + jacobian.null_project(push.velocity)
    return AllocationProblem(
        state=state,
        limits=limits,
        jacobian=jacobian,
        task_value=value,
        desired=desired,
        desired_rate=desired_rate,
        gains=gains,
        task_velocity=task_velocity,
        secondary=push.velocity,
        nominal=nominal,
        exempt=push.exempt,
        gear=choose_gear(nominal, state.theta, state.gear, limits),
        obstacle_distance=push.obstacle_distance,
        unit_distance=push.unit_distance,
        dt=dt,
        t=t,
        task=task,
        avoidance=avoidance,
        obstacles=obstacles,
        safety=safety,
    )


def posed_fields(
    state: PlatoonState,
    task: Task,
    desired: Any,
    desired_rate: Any,
    gains: Any,
    limits: VehicleLimits,
    dt: Any,
    *,
    avoidance: AvoidanceParams,
    obstacles: CircularObstacles,
    t: Any,
    safety: SafetyParams,
) -> dict[str, Any]:
    """What ``pose`` computes (the fields ``POSED``)."""
    posed = pose(
        state,
        task,
        desired,
        desired_rate,
        gains,
        limits,
        dt,
        avoidance=avoidance,
        obstacles=obstacles,
        t=t,
        safety=safety,
    )
    return {name: getattr(posed, name) for name in POSED}


# ``posed_fields`` compiled, answering numpy: what ``AllocationProblem.build`` hands the allocators. The
# numbers a closed loop keeps (limits, avoidance, dt) are static: passing each as an argument costs
# more than the pose itself at small n.
_pose_compiled = host(posed_fields, static=("task", "safety", "limits", "avoidance", "dt"))
