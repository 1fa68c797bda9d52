"""Tricycle-drive vehicles (paper Eq. 1), the unit controller (Eq. 2) and the gear rule.

Backing: the position is the tip, at the steered wheel, so a backing unit is unstable in
heading (like a cart pushed by its castor): away from zero steering the body swings until
the steering saturates, the direction of travel drifts, and the gear rule eventually
takes the unit forward again. Straight backing holds.

All functions are vectorized over the ``n`` units of a platoon. Positions are the
vehicle tip in metres, angles in radians wrapped to (-pi, pi], speeds in m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from platoon_opt.validation import finite_array, positive


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles (rad) to (-pi, pi]."""
    # np.mod lies in [0, 2 pi), so this lies in (-pi, pi] except where the remainder rounds
    # up to 2 pi (an input a hair above pi).
    wrapped = np.pi - np.mod(np.pi - np.asarray(angle, dtype=float), 2 * np.pi)
    return np.where(wrapped == -np.pi, np.pi, wrapped)


@dataclass(frozen=True)
class VehicleLimits:
    """Geometry and limits of one tricycle unit (paper Sec. 2 defaults).

    Attributes:
        wheel_radius: front wheel radius r (m).
        length: body length d (m).
        max_speed: bound on |r w| (m/s).
        max_steering: bound on |alpha| (rad), below pi/2.
        max_steering_rate: bound on |alpha'| (rad/s).
        steering_gain: K_alpha of Eq. 2 (1/s).
        gear_hysteresis: the gear rule keeps the current gear while the desired
            velocity is within pi/2 + gear_hysteresis of that gear's axis (rad);
            0 switches as soon as the velocity points behind (chatters at sharp turns).
    """

    wheel_radius: float = 0.025
    length: float = 0.25
    max_speed: float = 1.0
    max_steering: float = math.pi / 4
    max_steering_rate: float = 40.0
    steering_gain: float = 100.0
    gear_hysteresis: float = math.radians(30.0)

    def __post_init__(self) -> None:
        for name in ("wheel_radius", "length", "max_speed", "max_steering_rate", "steering_gain"):
            positive(f"VehicleLimits.{name}", getattr(self, name))
        steering = positive("VehicleLimits.max_steering", self.max_steering)
        if steering >= math.pi / 2:
            raise ValueError(f"VehicleLimits.max_steering must be < pi/2, got {steering!r}")
        hysteresis = positive("VehicleLimits.gear_hysteresis", self.gear_hysteresis, allow_zero=True)
        if hysteresis >= math.pi / 2:
            raise ValueError(f"VehicleLimits.gear_hysteresis must be < pi/2, got {hysteresis!r}")


@dataclass(frozen=True)
class PlatoonState:
    """State of n >= 2 units; every array has shape (n,).

    Attributes:
        x, y: tip position (m).
        theta: body heading (rad).
        alpha: steering angle (rad).
        gear: +1 forward, -1 backing; the gear rule's memory (hysteresis).
    """

    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    gear: np.ndarray = field(default=None)  # type: ignore[arg-type]  # None: every unit forward

    def __post_init__(self) -> None:
        x = finite_array("PlatoonState.x", self.x, (None,))
        n = x.shape[0]
        if n < 2:
            raise ValueError(f"PlatoonState.x must hold n >= 2 units, got n = {n}")
        object.__setattr__(self, "x", x)
        for name in ("y", "theta", "alpha"):
            object.__setattr__(self, name, finite_array(f"PlatoonState.{name}", getattr(self, name), (n,)))
        gear = np.ones(n) if self.gear is None else finite_array("PlatoonState.gear", self.gear, (n,))
        if not np.all(np.abs(gear) == 1):
            raise ValueError(f"PlatoonState.gear must be +1 or -1, got {gear!r}")
        object.__setattr__(self, "gear", gear)

    @classmethod
    def _trusted(
        cls, x: np.ndarray, y: np.ndarray, theta: np.ndarray, alpha: np.ndarray, gear: np.ndarray
    ) -> PlatoonState:
        """A state from arrays already checked (the simulation's own steps): no validation."""
        state = object.__new__(cls)
        for name, value in (("x", x), ("y", y), ("theta", theta), ("alpha", alpha), ("gear", gear)):
            object.__setattr__(state, name, value)
        return state

    @property
    def n(self) -> int:
        """Number of units."""
        return self.x.shape[0]

    @property
    def positions(self) -> np.ndarray:
        """Tip positions, shape (n, 2), m."""
        return np.column_stack((self.x, self.y))

    def check_limits(self, limits: VehicleLimits) -> None:
        """Raise ``ValueError`` if a steering angle exceeds ``limits.max_steering``."""
        worst = float(np.max(np.abs(self.alpha)))
        if worst > limits.max_steering + 1e-12:
            raise ValueError(
                f"PlatoonState.alpha must lie within +-{limits.max_steering:.6g} rad, got {worst:.6g}"
            )


def gear_axis(theta: np.ndarray, gear: np.ndarray) -> np.ndarray:
    """Direction (rad) a unit's tip moves in with zero steering: theta forward, theta + pi backing."""
    return wrap_angle(theta + np.where(gear < 0, np.pi, 0.0))


def choose_gear(
    velocity: np.ndarray, theta: np.ndarray, gear: np.ndarray, limits: VehicleLimits
) -> np.ndarray:
    """The gear rule with hysteresis: switch when the desired velocity leaves pi/2 + h of the axis.

    Args:
        velocity: desired tip velocities, shape (n, 2), m/s.
        theta: headings (n,), rad.
        gear: current gears (n,), +1 or -1.

    Returns:
        New gears (n,). A zero desired velocity keeps the gear; an exact tie (velocity
        at pi/2 + h) keeps it too.
    """
    return _gear_rule(velocity, np.hypot(velocity[:, 0], velocity[:, 1]), theta, gear, limits)[0]


def _gear_rule(
    velocity: np.ndarray, speed: np.ndarray, theta: np.ndarray, gear: np.ndarray, limits: VehicleLimits
) -> tuple[np.ndarray, np.ndarray]:
    """``choose_gear`` given the speeds |velocity| (n,), and the direction of each velocity
    relative to the new gear's axis (n,), rad in (-pi, pi]."""
    heading_error = wrap_angle(np.arctan2(velocity[:, 1], velocity[:, 0]) - gear_axis(theta, gear))
    switch = (speed > 1e-12) & (np.abs(heading_error) > np.pi / 2 + limits.gear_hysteresis)
    # Reversing the axis turns the relative direction by pi.
    relative = np.where(switch, heading_error - np.copysign(np.pi, heading_error), heading_error)
    return np.where(switch, -gear, gear), relative


@dataclass(frozen=True)
class UnitCommand:
    """Inputs of the units for one step, each shape (n,): signed speed r w (m/s),
    steering rate alpha' (rad/s), and the gear used."""

    speed: np.ndarray
    steering_rate: np.ndarray
    gear: np.ndarray


def unit_controller(
    state: PlatoonState,
    velocity: np.ndarray,
    limits: VehicleLimits,
    dt: float,
    *,
    waiting: np.ndarray | None = None,
) -> UnitCommand:
    """Eq. 2 with backing: steer toward the desired velocity, drive at its (capped) speed.

    The gear comes from ``choose_gear``; the steering target is the desired direction
    relative to the gear's axis, clipped to the steering limit; the steering rate is
    ``K_alpha (alpha_d - alpha)`` clipped to the rate limit and to what keeps
    ``|alpha| <= max_steering`` after ``dt``. A zero desired velocity holds the steering, or,
    given ``waiting``, the unit stands and steers (and picks its gear) toward ``waiting``.

    Args:
        velocity: desired tip velocities (n, 2), m/s.
        dt: step length (s) over which the steering rate will be held.
        waiting: (n, 2) m/s, where a unit told to stand would go (barriers stop a unit whose
            steering points the wrong way: standing, it can still turn its wheel); None: hold.
    """
    speed = np.hypot(velocity[:, 0], velocity[:, 1])
    toward, toward_speed = velocity, speed
    if waiting is not None:
        toward = np.where((speed == 0)[:, None], waiting, velocity)
        toward_speed = np.hypot(toward[:, 0], toward[:, 1])
    gear, relative = _gear_rule(toward, toward_speed, state.theta, state.gear, limits)
    speed = np.minimum(speed, limits.max_speed)
    steering_target = np.clip(relative, -limits.max_steering, limits.max_steering)
    steering_target = np.where(toward_speed > 0, steering_target, state.alpha)
    # The rate limit, and never letting the steering leave its range within the step.
    rate = np.clip(
        limits.steering_gain * (steering_target - state.alpha),
        np.maximum(-limits.max_steering_rate, (-limits.max_steering - state.alpha) / dt),
        np.minimum(limits.max_steering_rate, (limits.max_steering - state.alpha) / dt),
    )
    return UnitCommand(speed=gear * speed, steering_rate=rate, gear=gear)


def step_vehicles(
    state: PlatoonState, command: UnitCommand, limits: VehicleLimits, dt: float
) -> PlatoonState:
    """Advance every unit by ``dt`` seconds under Eq. 1.

    The steering moves first at the commanded rate (held over the step); the tip then
    follows the exact arc of constant speed and steering over the step: the direction
    of travel theta + alpha turns at theta' = (r w / d) sin(alpha).
    """
    alpha = np.clip(state.alpha + command.steering_rate * dt, -limits.max_steering, limits.max_steering)
    turn = command.speed / limits.length * np.sin(alpha) * dt
    direction = state.theta + alpha + turn / 2
    chord = command.speed * dt * np.sinc(turn / (2 * np.pi))  # np.sinc(x) = sin(pi x) / (pi x)
    x, y = state.x + chord * np.cos(direction), state.y + chord * np.sin(direction)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        # Every input reaches x through the chord and the direction.
        raise ValueError(
            "step_vehicles: command.speed, command.steering_rate and dt must be finite, got "
            f"{command.speed!r}, {command.steering_rate!r}, {dt!r}"
        )
    return PlatoonState._trusted(x, y, wrap_angle(state.theta + turn), alpha, command.gear)
