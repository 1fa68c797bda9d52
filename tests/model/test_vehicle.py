import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from platoon_opt import PlatoonState, VehicleLimits
from platoon_opt.vehicle import UnitCommand, choose_gear, step_vehicles, unit_controller, wrap_angle
from tests.conftest import random_state

LIMITS = VehicleLimits()


@given(st.integers(0, 2**32 - 1), st.integers(2, 30), st.floats(1e-4, 0.2), st.floats(0.0, 50.0))
def test_no_limit_is_ever_exceeded(seed, n, dt, scale):
    rng = np.random.default_rng(seed)
    state = random_state(rng, n)
    velocity = rng.normal(0, scale, (n, 2))
    command = unit_controller(state, velocity, LIMITS, dt)
    assert np.all(np.abs(command.speed) <= LIMITS.max_speed + 1e-12)
    assert np.all(np.abs(command.steering_rate) <= LIMITS.max_steering_rate + 1e-9)
    after = step_vehicles(state, command, LIMITS, dt)
    assert np.all(np.abs(after.alpha) <= LIMITS.max_steering + 1e-12)
    # The tip moves at most max_speed * dt.
    moved = np.hypot(after.x - state.x, after.y - state.y)
    assert np.all(moved <= LIMITS.max_speed * dt + 1e-12)


def test_step_is_the_exact_arc():
    state = PlatoonState(x=[0.0, 1.0], y=[0.0, 2.0], theta=[0.3, -2.0], alpha=[0.5, -0.7], gear=[1, -1])
    command = UnitCommand(speed=np.array([0.9, -0.6]), steering_rate=np.zeros(2), gear=state.gear)
    coarse = step_vehicles(state, command, LIMITS, 0.4)
    fine = state
    for _ in range(20000):
        fine = step_vehicles(fine, command, LIMITS, 0.4 / 20000)
    for key in ("x", "y", "theta"):
        np.testing.assert_allclose(getattr(coarse, key), getattr(fine, key), atol=1e-10)


def test_kinematics_match_eq1():
    state = PlatoonState(x=[0.0, 0.0], y=[0.0, 0.0], theta=[0.2, 1.0], alpha=[0.4, -0.3])
    dt = 1e-7
    command = UnitCommand(speed=np.array([0.8, -0.5]), steering_rate=np.zeros(2), gear=np.array([1.0, -1.0]))
    after = step_vehicles(state, command, LIMITS, dt)
    direction = state.theta + state.alpha
    np.testing.assert_allclose((after.x - state.x) / dt, command.speed * np.cos(direction), rtol=1e-6)
    np.testing.assert_allclose((after.y - state.y) / dt, command.speed * np.sin(direction), rtol=1e-6)
    np.testing.assert_allclose(
        (after.theta - state.theta) / dt, command.speed / LIMITS.length * np.sin(state.alpha), rtol=1e-6
    )


def drive(state: PlatoonState, velocity: np.ndarray, seconds: float, dt: float = 0.01) -> PlatoonState:
    for _ in range(int(round(seconds / dt))):
        state = step_vehicles(state, unit_controller(state, velocity, LIMITS, dt), LIMITS, dt)
    return state


def test_straight_line_tracking_converges():
    state = PlatoonState(x=[0.0, 0.0], y=[0.0, 3.0], theta=[math.pi / 2, 2.0], alpha=[0.0, 0.0])
    velocity = np.array([[0.8, 0.0], [0.8, 0.0]])
    after = drive(state, velocity, 4.0)
    np.testing.assert_allclose(wrap_angle(after.theta + after.alpha), 0.0, atol=1e-3)
    assert np.all(after.gear == 1)
    moved = drive(after, velocity, 1.0)
    np.testing.assert_allclose(moved.x - after.x, 0.8, atol=1e-3)
    np.testing.assert_allclose(moved.y - after.y, 0.0, atol=1e-3)


def test_backing_drives_the_tip_backward():
    state = PlatoonState(x=[0.0, 0.0], y=[0.0, 3.0], theta=[0.0, 0.0], alpha=[0.0, 0.0])
    velocity = np.array([[-0.5, 0.0], [-0.5, 0.1]])
    after = drive(state, velocity, 0.4)
    assert np.all(after.gear == -1)
    np.testing.assert_allclose(after.x - state.x, -0.2, atol=0.01)
    np.testing.assert_allclose(after.y[1] - state.y[1], 0.04, atol=0.01)
    # Straight back holds; at an angle the body swings (the steered wheel is the tip, so
    # backing is unstable in heading) until the gear rule takes the unit forward again.
    later = drive(after, velocity, 3.0)
    assert later.gear[0] == -1 and abs(later.theta[0]) < 1e-9
    assert later.gear[1] == 1


@pytest.mark.parametrize("hysteresis, expected_flips", [(math.radians(30), 0), (0.0, 10)])
def test_gear_rule_hysteresis_stops_chattering(hysteresis, expected_flips):
    limits = replace(LIMITS, gear_hysteresis=hysteresis)
    theta, gear = np.zeros(2), np.ones(2)
    flips = 0
    for k in range(10):
        angle = math.radians(95 if k % 2 == 0 else 85)  # the desired velocity wobbles about abeam
        velocity = np.tile([math.cos(angle), math.sin(angle)], (2, 1))
        new = choose_gear(velocity, theta, gear, limits)
        flips += int(new[0] != gear[0])
        gear = new
    assert flips == expected_flips


def test_gear_switches_past_the_hysteresis_band_and_zero_velocity_keeps_it():
    theta, gear = np.zeros(3), np.ones(3)
    angles = np.radians([119.0, 121.0, 180.0])
    velocity = np.column_stack((np.cos(angles), np.sin(angles)))
    np.testing.assert_array_equal(choose_gear(velocity, theta, gear, LIMITS), [1, -1, -1])
    np.testing.assert_array_equal(choose_gear(np.zeros((3, 2)), theta, -gear, LIMITS), [-1, -1, -1])


@pytest.mark.parametrize(
    "field, value",
    [
        ("max_speed", 0.0),
        ("max_steering", 2.0),
        ("length", -1.0),
        ("steering_gain", math.nan),
        ("integration", "rk4"),
    ],
)
def test_bad_limits_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        VehicleLimits(**{field: value})


def test_bad_state_names_the_field():
    with pytest.raises(ValueError, match="n >= 2"):
        PlatoonState(x=[0.0], y=[0.0], theta=[0.0], alpha=[0.0])
    with pytest.raises(ValueError, match=r"PlatoonState\.y"):
        PlatoonState(x=[0.0, 1.0], y=[0.0, math.inf], theta=[0.0, 0.0], alpha=[0.0, 0.0])
    with pytest.raises(ValueError, match=r"PlatoonState\.theta must have shape"):
        PlatoonState(x=[0.0, 1.0], y=[0.0, 1.0], theta=[0.0], alpha=[0.0, 0.0])


def test_wrap_angle_stays_in_half_open_range_at_the_edges():
    edges = np.array([np.pi, -np.pi, np.nextafter(np.pi, 4), np.nextafter(-np.pi, -4), 3 * np.pi, -3 * np.pi])
    wrapped = wrap_angle(edges)
    assert np.all((wrapped > -np.pi) & (wrapped <= np.pi))
    np.testing.assert_allclose(np.cos(wrapped), np.cos(edges), atol=1e-12)


def test_euler_steps_straight_along_the_travel_direction_at_the_steps_start():
    state = PlatoonState(x=[0.0, 1.0], y=[0.0, 2.0], theta=[0.3, -1.0], alpha=[0.5, 0.0])
    command = UnitCommand(speed=np.array([0.8, -0.5]), steering_rate=np.zeros(2), gear=np.array([1.0, -1.0]))
    euler = step_vehicles(state, command, replace(LIMITS, integration="euler"), 0.01)
    arc = step_vehicles(state, command, LIMITS, 0.01)
    direction = state.theta + state.alpha
    np.testing.assert_allclose(
        euler.x, state.x + command.speed * 0.01 * np.cos(direction), rtol=0, atol=1e-15
    )
    np.testing.assert_allclose(
        euler.y, state.y + command.speed * 0.01 * np.sin(direction), rtol=0, atol=1e-15
    )
    np.testing.assert_array_equal(euler.theta, arc.theta)
    # Straight (zero steering) the two agree; turning, the Euler step cuts the arc's half turn.
    assert euler.x[1] == pytest.approx(arc.x[1], abs=1e-15)
    assert abs(euler.y[0] - arc.y[0]) > 1e-6
