"""Tricycle-drive vehicles (paper Eq. 1), the unit controller (Eq. 2) and the gear rule.

Backing: the position is the tip, at the steered wheel, so a backing unit is unstable in
heading (like a cart pushed by its castor): away from zero steering the body swings until
the steering saturates, the direction of travel drifts, and the gear rule eventually
takes the unit forward again. Straight backing holds.

The functions are vectorized over the ``n`` units of a platoon and written once for numpy and
``jax.numpy`` (``platoon_opt.arrays.namespace``): numpy in, numpy out; inside the compiled engine
they are traced. Positions are the vehicle tip in metres, angles in radians wrapped to
(-pi, pi], speeds in m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from platoon_opt.arrays import namespace, pytree, unchecked
from platoon_opt.validation import finite_array, positive

# ``VehicleLimits.integration``: the exact arc over a step, or an Euler step of Eq. 1.
INTEGRATIONS = ("arc", "euler")
# The desired speed (m/s) at or below which a unit told where to wait stands. A solver hands a
# blocked unit its zero velocity up to rounding (1e-17 m/s); read as a direction, that velocity
# would hold the unit's steering against an obstacle for good, or steer it by noise.
STANDING_SPEED = 1e-9


def wrap_angle(angle: Any) -> Any:
    """Wrap angles (rad) to (-pi, pi]."""
    xp = namespace(angle)
    # mod lies in [0, 2 pi), so this lies in (-pi, pi] except where the remainder rounds up to
    # 2 pi (an input a hair above pi).
    wrapped = math.pi - xp.mod(math.pi - xp.asarray(angle, dtype=float), 2 * math.pi)
    return xp.where(wrapped == -math.pi, math.pi, wrapped)


@pytree(
    data=(
        "wheel_radius",
        "length",
        "max_speed",
        "max_steering",
        "max_steering_rate",
        "steering_gain",
        "gear_hysteresis",
    ),
    static=("integration",),
)
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
        integration: how ``step_vehicles`` moves the tip over a step: "arc" follows the exact
            arc of constant speed and steering, "euler" the straight step of Eq. 1 at the
            step's start (x += r w cos(theta + alpha) dt); an ablation choice (the paper does
            not say), not a key of the scenario file. The barrier rows and ``nmpc``'s
            prediction keep the arcs.
    """

    wheel_radius: float = 0.025
    length: float = 0.25
    max_speed: float = 1.0
    max_steering: float = math.pi / 4
    max_steering_rate: float = 40.0
    steering_gain: float = 100.0
    gear_hysteresis: float = math.radians(30.0)
    integration: str = "arc"

    def __post_init__(self) -> None:
        for name in ("wheel_radius", "length", "max_speed", "max_steering_rate", "steering_gain"):
            positive(f"VehicleLimits.{name}", getattr(self, name))
        steering = positive("VehicleLimits.max_steering", self.max_steering)
        if steering >= math.pi / 2:
            raise ValueError(f"VehicleLimits.max_steering must be < pi/2, got {steering!r}")
        hysteresis = positive("VehicleLimits.gear_hysteresis", self.gear_hysteresis, allow_zero=True)
        if hysteresis >= math.pi / 2:
            raise ValueError(f"VehicleLimits.gear_hysteresis must be < pi/2, got {hysteresis!r}")
        if self.integration not in INTEGRATIONS:
            raise ValueError(f"VehicleLimits.integration must be 'arc' or 'euler', got {self.integration!r}")


@pytree(data=("x", "y", "theta", "alpha", "gear"))
@dataclass(frozen=True)
class PlatoonState:
    """State of n >= 2 units; every array has shape (n,) (numpy, or JAX inside the engine).

    Attributes:
        x, y: tip position (m).
        theta: body heading (rad).
        alpha: steering angle (rad).
        gear: +1 forward, -1 backing; the gear rule's memory (hysteresis).
    """

    x: Any
    y: Any
    theta: Any
    alpha: Any
    gear: Any = field(default=None)  # None: every unit forward

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
    def trusted(cls, x: Any, y: Any, theta: Any, alpha: Any, gear: Any) -> PlatoonState:
        """A state from arrays already checked (the simulation's own steps): no validation."""
        return unchecked(cls, x=x, y=y, theta=theta, alpha=alpha, gear=gear)

    @property
    def n(self) -> int:
        """Number of units."""
        return self.x.shape[0]

    @property
    def positions(self) -> Any:
        """Tip positions, shape (n, 2), m."""
        return namespace(self.x, self.y).stack((self.x, self.y), axis=1)

    def check_limits(self, limits: VehicleLimits) -> None:
        """Raise ``ValueError`` if a steering angle exceeds ``limits.max_steering``."""
        worst = float(np.max(np.abs(self.alpha)))
        if worst > limits.max_steering + 1e-12:
            raise ValueError(
                f"PlatoonState.alpha must lie within +-{limits.max_steering:.6g} rad, got {worst:.6g}"
            )


def gear_axis(theta: Any, gear: Any) -> Any:
    """Direction (rad) a unit's tip moves in with zero steering: theta forward, theta + pi backing."""
    return wrap_angle(theta + namespace(theta, gear).where(gear < 0, math.pi, 0.0))


def gear_rule(velocity: Any, speed: Any, theta: Any, gear: Any, hysteresis: Any) -> tuple[Any, Any]:
    """The gear rule with hysteresis: switch when the desired velocity leaves pi/2 + ``hysteresis``
    of the current gear's axis.

    Args:
        velocity: desired tip velocities (n, 2), m/s, of speeds ``speed`` (n,).
        theta: headings (n,), rad; gear: current gears (n,), +1 or -1; hysteresis: rad.

    Returns:
        New gears (n,), and the direction of each velocity relative to the new gear's axis (n,),
        rad in (-pi, pi]. A zero desired velocity keeps the gear; an exact tie (velocity at
        pi/2 + hysteresis) keeps it too.
    """
    xp = namespace(velocity, theta, gear)
    heading_error = wrap_angle(xp.arctan2(velocity[:, 1], velocity[:, 0]) - gear_axis(theta, gear))
    switch = (speed > 1e-12) & (xp.abs(heading_error) > math.pi / 2 + hysteresis)
    # Reversing the axis turns the relative direction by pi.
    relative = xp.where(switch, heading_error - xp.copysign(math.pi, heading_error), heading_error)
    return xp.where(switch, -gear, gear), relative


def choose_gear(velocity: Any, theta: Any, gear: Any, limits: VehicleLimits) -> Any:
    """The gears (n,) the gear rule picks for desired tip velocities (n, 2), m/s, from headings
    ``theta`` (n,) and gears ``gear`` (n,): ``gear_rule``."""
    speed = namespace(velocity).hypot(velocity[:, 0], velocity[:, 1])
    return gear_rule(velocity, speed, theta, gear, limits.gear_hysteresis)[0]


@pytree(data=("speed", "steering_rate", "gear"))
@dataclass(frozen=True)
class UnitCommand:
    """Inputs of the units for one step, each shape (n,): signed speed r w (m/s),
    steering rate alpha' (rad/s), and the gear used."""

    speed: Any
    steering_rate: Any
    gear: Any


def unit_controller(
    state: PlatoonState,
    velocity: Any,
    limits: VehicleLimits,
    dt: Any,
    *,
    waiting: Any = None,
) -> UnitCommand:
    """Eq. 2 with backing: steer toward the desired velocity, drive at its (capped) speed.

    The gear comes from ``gear_rule``; the steering target is the desired direction
    relative to the gear's axis, clipped to the steering limit; the steering rate is
    ``K_alpha (alpha_d - alpha)`` clipped to the rate limit and to what keeps
    ``|alpha| <= max_steering`` after ``dt``. A zero desired velocity holds the steering, or,
    given ``waiting``, a unit whose desired speed is at most ``STANDING_SPEED`` stands and steers
    (and picks its gear) toward ``waiting``.

    Args:
        velocity: desired tip velocities (n, 2), m/s.
        dt: step length (s) over which the steering rate will be held.
        waiting: (n, 2) m/s, where a unit told to stand would go (barriers stop a unit whose
            steering points the wrong way: standing, it can still turn its wheel); None: hold.
    """
    xp = namespace(velocity, state.theta, waiting)
    speed = xp.hypot(velocity[:, 0], velocity[:, 1])
    toward, toward_speed = velocity, speed
    if waiting is not None:
        stands = speed <= STANDING_SPEED
        toward = xp.where(stands[:, None], waiting, velocity)
        toward_speed = xp.hypot(toward[:, 0], toward[:, 1])
        speed = xp.where(stands, 0.0, speed)
    gear, relative = gear_rule(toward, toward_speed, state.theta, state.gear, limits.gear_hysteresis)
    speed = xp.minimum(speed, limits.max_speed)
    steering_target = xp.clip(relative, -limits.max_steering, limits.max_steering)
    steering_target = xp.where(toward_speed > 0, steering_target, state.alpha)
    # The rate limit, and never letting the steering leave its range within the step.
    rate = xp.clip(
        limits.steering_gain * (steering_target - state.alpha),
        xp.maximum(-limits.max_steering_rate, (-limits.max_steering - state.alpha) / dt),
        xp.minimum(limits.max_steering_rate, (limits.max_steering - state.alpha) / dt),
    )
    return UnitCommand(speed=gear * speed, steering_rate=rate, gear=gear)


def step_vehicles(state: PlatoonState, command: UnitCommand, limits: VehicleLimits, dt: Any) -> PlatoonState:
    """Advance every unit by ``dt`` seconds under Eq. 1.

    The steering moves first at the commanded rate (held over the step); the tip then
    follows the exact arc of constant speed and steering over the step: the direction
    of travel theta + alpha turns at theta' = (r w / d) sin(alpha). With
    ``limits.integration`` "euler" it moves instead the full step along the direction of travel
    at the step's start, theta + alpha, and the heading turns by the same amount.
    """
    xp = namespace(state.x, command.speed)
    alpha = xp.clip(state.alpha + command.steering_rate * dt, -limits.max_steering, limits.max_steering)
    turn = command.speed / limits.length * xp.sin(alpha) * dt
    if limits.integration == "euler":
        direction, chord = state.theta + alpha, command.speed * dt
    else:
        direction = state.theta + alpha + turn / 2
        chord = command.speed * dt * xp.sinc(turn / (2 * math.pi))  # sinc(x) = sin(pi x) / (pi x)
    x, y = state.x + chord * xp.cos(direction), state.y + chord * xp.sin(direction)
    return PlatoonState.trusted(x, y, wrap_angle(state.theta + turn), alpha, command.gear)
