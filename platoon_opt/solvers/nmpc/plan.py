"""The receding horizon's plan: the last solve, handed to the unit controllers until the next.

``Plan.hand`` turns the plan's first interval into the velocities that make each unit's
controller (the paper's Eq. 2) drive it (docs/nmpc.md, section 6); ``Plan.steps_since`` tells
whether a problem continues the plan's run, and how many simulation steps after the solve it
comes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from platoon_opt.problem import AllocationProblem

# A handed velocity this short still carries its direction to the unit controller (which
# holds the steering for a zero velocity) and moves the unit by 1e-11 m per step.
_DIRECTION_ONLY_SPEED = 1e-9


@dataclass(frozen=True)
class Plan:
    """One solve of the horizon, as stored between solves.

    Attributes:
        t: time of the solve (s).
        n: units.
        dt: simulation step (s).
        substeps: simulation steps per interval (the allocator's ``resolve_every``).
        reach: the steering change per step at the rate limit (rad) with ``steering="rate"``,
            None for the linear steering (docs/nmpc.md, Eq. 1.6').
        inputs: U (N, n, 2): each unit's speed (m/s, signed) over interval k and steering
            angle (rad) at its end.
        states: Z (N, n, 4): the planned node states x, y (m), theta, alpha (rad).
        alpha0: the steering angles at the solve (n,), rad.
        standstill: planned speeds of at most this magnitude (m/s) are handed as zero: the
            solver resolves a speed only to this (its step tolerance of the speed's range), so
            their sign is noise, and following it flipped a standing unit's gear at every solve.
    """

    t: float
    n: int
    dt: float
    substeps: int
    reach: float | None
    inputs: np.ndarray
    states: np.ndarray
    alpha0: np.ndarray
    standstill: float

    def steps_since(self, problem: AllocationProblem) -> int | None:
        """Simulation steps from the solve to ``problem``, or None when ``problem`` is not of
        the plan's run (another platoon or step, or time went back)."""
        steps = round((problem.t - self.t) / problem.dt)
        same_run = self.n == problem.n and self.dt == problem.dt and problem.t > self.t - 1e-12
        return steps if same_run else None

    def shifted(self) -> np.ndarray:
        """The inputs (N, n, 2) shifted by one interval, the last one held: the warm start of
        the next solve."""
        return np.concatenate((self.inputs[1:], self.inputs[-1:]))

    def hand(self, problem: AllocationProblem, substep: int) -> np.ndarray:
        """Velocities (n, 2) that make the unit controller follow interval 0 of the plan at
        ``substep`` (0 = the step of the solve): speed s_0 and the planned steering angle
        (docs/nmpc.md, Eq. 6.1)."""
        state, limits, dt = problem.state, problem.limits, problem.dt
        speed, steering = self.inputs[0, :, 0], self.inputs[0, :, 1]
        speed = np.where(np.abs(speed) <= self.standstill, 0.0, speed)
        if self.reach is None:
            planned = self.alpha0 + (steering - self.alpha0) * (substep + 1) / self.substeps
        else:
            bound = (substep + 1) * self.reach
            planned = self.alpha0 + np.clip(steering - self.alpha0, -bound, bound)
        # The unit controller turns the steering by K_alpha (target - alpha) dt: invert that.
        target = state.alpha + (planned - state.alpha) / (limits.steering_gain * dt)
        target = np.clip(target, -limits.max_steering, limits.max_steering)
        backing = np.where(speed != 0, speed < 0, state.gear < 0)
        direction = state.theta + target + np.where(backing, np.pi, 0.0)
        length = np.maximum(np.abs(speed), _DIRECTION_ONLY_SPEED)
        return length[:, None] * np.column_stack((np.cos(direction), np.sin(direction)))
