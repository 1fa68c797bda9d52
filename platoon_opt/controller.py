"""One control step: build the allocation problem, allocate, run the unit controllers, move."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np

from platoon_opt.allocation import Allocation, Allocator, Previewing, safe_fallback, safety_of
from platoon_opt.arrays import host, namespace
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.barrier_constraints import Capacity
from platoon_opt.errors import AllocationError, ConfigurationError, error_text
from platoon_opt.problem import AllocationProblem
from platoon_opt.safety import SafetyParams
from platoon_opt.tasks import Task
from platoon_opt.vehicle import (
    STANDING_SPEED,
    PlatoonState,
    UnitCommand,
    VehicleLimits,
    step_vehicles,
    unit_controller,
)


def drive(
    state: PlatoonState, velocity: Any, limits: VehicleLimits, dt: Any, waiting: Any = None
) -> tuple[UnitCommand, PlatoonState]:
    """The unit controllers (Eq. 2) toward ``velocity`` (n, 2), m/s, and the step of the vehicles
    (Eq. 1) over ``dt`` s: the commands and the new state. ``waiting``: see ``unit_controller``."""
    command = unit_controller(state, velocity, limits, dt, waiting=waiting)
    return command, step_vehicles(state, command, limits, dt)


# ``drive`` compiled, numpy in and out: the host loop's step of the vehicles (its limits and step,
# which a run keeps, static: see ``problem._pose_compiled``).
drive_compiled = host(drive, static=("limits", "dt"))


def fallback_status(error: BaseException) -> str:
    """The status of a step the controller answered because the allocator raised ``error``."""
    return f"fallback:{error_text(error)}"


@dataclass(frozen=True)
class StepResult:
    """What one control step did: the new state, the problem posed, the allocation and the
    unit commands applied."""

    state: PlatoonState
    problem: AllocationProblem
    allocation: Allocation
    command: UnitCommand


def standing_targets(
    problem: AllocationProblem, params: SafetyParams, velocities: Any, *, capacity: Capacity | None = None
) -> tuple[Any, Any]:
    """Velocities (n, 2) m/s toward which units steer while they stand, and in which gear, and
    whether a safe-set build for a standing unit overflowed ``capacity`` (compiled code:
    ``SafeSets.build``; never on the host, ``capacity`` None).

    Barriers stop a unit whose steering cannot reach a safe direction within the step (the
    rate-aware sector), or whose every safe direction points away from its nominal velocity.
    Standing, it can still turn its wheel and change gear. It aims at its nominal velocity slid
    along its barrier rows (``SafeSets.sliding``, with the rows of the step's own set: over the
    whole steering range the rows allow for so much steering lag that a nominal velocity into an
    obstacle has no part left along it), and steers toward the velocity of either gear's safe
    set, over the whole steering range, that goes furthest along that aim (``SafeSets.support``:
    a direction the rows let it drive only a few mm along counts for little): backing out of a
    corner, or turning its wheel away from an obstacle or a neighbour. A unit whose aim has no
    such velocity (wedged between rows) steers toward its nominal velocity. A unit stands when
    its speed is at most ``STANDING_SPEED`` (a solver's zero up to rounding); units that move
    keep their ``velocities``. On numpy only the standing units' sets are searched; traced, every
    unit's (the same numbers per unit).
    """
    xp = namespace(velocities, problem.nominal)
    standing = xp.hypot(velocities[:, 0], velocities[:, 1]) <= STANDING_SPEED
    if xp is np and not np.any(standing):
        return velocities, False
    units = np.flatnonzero(standing) if xp is np else slice(None)
    nominal = problem.nominal[units]
    own = problem.safe_sets(params, capacity=capacity)
    aim = own.take(units).sliding(nominal)
    best, score, overflow = nominal, xp.zeros(nominal.shape[0]), own.overflow
    for gear in (problem.gear, -problem.gear):
        sets = problem.safe_sets(params, rate_aware=False, gear=gear, capacity=capacity)
        candidate = sets.take(units).support(aim)
        along = xp.einsum("ij,ij->i", candidate, aim)
        better = (xp.hypot(candidate[:, 0], candidate[:, 1]) > STANDING_SPEED) & (along > score)
        best, score = xp.where(better[:, None], candidate, best), xp.where(better, along, score)
        overflow = overflow | sets.overflow
    if xp is np:
        targets = velocities.copy()
        targets[units] = best
        return targets, False
    return xp.where(standing[:, None], best, velocities), xp.any(standing & overflow)


@dataclass(frozen=True)
class PlatoonController:
    """The platoon controller: task, gains K, limits, avoidance, the scenario's safety parameters
    (``problem.safety``) and an allocator.

    With ``strict=False`` an allocator that raises does not end a run: the nominal velocity projected
    onto each unit's achievable (or safe: ``allocation.safe_fallback``) set is used, with status
    ``"fallback:<Type>: <message>"`` (one line). A ``ConfigurationError`` (a bad option, file or
    flag) is no failure of a step and always ends the run, strict or not: a fallback on every step
    would hide it. With
    ``strict=True`` a step raises ``AllocationError`` instead, and also when the allocator answered
    with a fallback of its own (``Allocation.fell_back``, e.g. a backend that failed): a strict run
    never degrades silently; a strict run that completes is identical to the same run without strict.

    ``reference``, f_d(t) (m,) as a function of time (s), lets an allocator that plans ahead
    (``allocation.Previewing``) see the target over its horizon; without it that allocator
    extrapolates f_d at its rate.
    """

    task: Task
    gains: np.ndarray
    limits: VehicleLimits
    allocator: Allocator
    avoidance: AvoidanceParams = AvoidanceParams()
    obstacles: CircularObstacles = CircularObstacles.none()
    strict: bool = False
    safety: SafetyParams = SafetyParams()
    reference: Callable[[float], np.ndarray] | None = None
    _previews: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Whether f_d ahead goes to the allocator, decided once: checking a runtime protocol costs
        # tens of microseconds, a few percent of a host-loop step at n = 8.
        object.__setattr__(
            self, "_previews", self.reference is not None and isinstance(self.allocator, Previewing)
        )

    def problem(
        self, state: PlatoonState, desired: np.ndarray, desired_rate: np.ndarray, dt: float, t: float
    ) -> AllocationProblem:
        """The allocation problem of ``state`` at time ``t``, with f_d over the horizon of an
        allocator that plans ahead at this step."""
        problem = AllocationProblem.build(
            state,
            self.task,
            desired,
            desired_rate,
            self.gains,
            self.limits,
            dt,
            avoidance=self.avoidance,
            obstacles=self.obstacles,
            t=t,
            safety=self.safety,
            compiled=True,
        )
        return self.previewed(problem)

    def previewed(self, problem: AllocationProblem) -> AllocationProblem:
        """``problem`` with f_d over the horizon of an allocator that plans ahead (``Previewing``)
        at this step, from ``reference``; else ``problem`` as it is."""
        if not self._previews:
            return problem
        reference = cast(Callable[[float], np.ndarray], self.reference)
        times = cast(Previewing, self.allocator).preview_times(problem)
        if not len(times):
            return problem
        return replace(problem, desired_ahead=np.stack([reference(problem.t + tau) for tau in times]))

    def allocate(self, problem: AllocationProblem) -> Allocation:
        """Run the allocator; on an exception fall back (or raise ``AllocationError`` if strict, as
        also for an allocation that fell back). A ``ConfigurationError`` propagates as it is."""
        start = time.perf_counter()
        try:
            allocation = self.allocator.allocate(problem)
        except ConfigurationError:
            raise
        except Exception as error:
            if self.strict:
                raise AllocationError(
                    allocator=self.allocator.name, reason=f"raised {error!r}", t=problem.t
                ) from error
            return Allocation.of(
                problem,
                safe_fallback(problem, self.allocator),
                allocator=self.allocator.name,
                status=fallback_status(error),
                iterations=0,
                solve_time=time.perf_counter() - start,
                fell_back=True,
                program_changed=True,
                program="projection",
            )
        if self.strict and allocation.fell_back:
            raise AllocationError(
                allocator=self.allocator.name, reason=f"fell back: {allocation.status}", t=problem.t
            )
        return allocation

    def waiting(self, problem: AllocationProblem, velocities: np.ndarray) -> np.ndarray | None:
        """Where the units allocated a zero velocity steer while they stand (``standing_targets``)
        with barriers on for this allocator; None (barriers off) holds their steering."""
        params = safety_of(problem, self.allocator)
        return standing_targets(problem, params, velocities)[0] if params.enabled else None

    def step(
        self, state: PlatoonState, desired: np.ndarray, desired_rate: np.ndarray, dt: float, t: float
    ) -> StepResult:
        """Advance the platoon by ``dt`` seconds toward f_d = ``desired`` (m,), f_d' = ``desired_rate``."""
        problem = self.problem(state, desired, desired_rate, dt, t)
        allocation = self.allocate(problem)
        waiting = self.waiting(problem, allocation.velocities)
        command, after = drive_compiled(state, allocation.velocities, self.limits, dt, waiting)
        check_moved(command, after, dt)
        return StepResult(after, problem, allocation, command)


def check_moved(command: UnitCommand, after: PlatoonState, dt: float) -> None:
    """Raise ``ValueError`` if the vehicles' step under ``command`` left a position not finite."""
    if not (np.isfinite(after.x).all() and np.isfinite(after.y).all()):
        # Every input reaches the position through the chord and the direction.
        raise ValueError(
            "step: the commanded speeds and steering rates and dt must be finite, got "
            f"{command.speed!r}, {command.steering_rate!r}, {dt!r}"
        )
