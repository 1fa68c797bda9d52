"""Liveness with barriers (docs/safety.md, "Turning room"): the turning rows are the exact rate of
their heading-aware barrier under the vehicle model, leave a unit at their boundary a way to
move, and units stopped by barriers steer while they stand; in closed loop a unit driven head-on
at an obstacle goes round it instead of waiting at its margin."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import tomllib
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.barrier_constraints import Constraints
from platoon_opt.controller import standing_targets
from platoon_opt.limits import AchievableSets
from platoon_opt.safety import SafetyParams, turning_radius, turning_rows
from platoon_opt.scenarios import parse_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers.registry import get_allocator
from platoon_opt.vehicle import PlatoonState, unit_controller, wrap_angle
from tests.conftest import LIMITS, build_problem

DT = 0.01
RADIUS = 0.3


def _barrier(position, theta, gear, centre):
    """H of the turning rows: |g|^2 - (R + rho_t (1 - sin|psi|))^2 ahead of the unit, else None."""
    g = position - centre
    toward = math.atan2(-g[1], -g[0])
    psi = wrap_angle(theta + (math.pi if gear < 0 else 0.0) - toward)
    if abs(psi) >= math.pi / 2:
        return None
    return g @ g - (RADIUS + turning_radius(LIMITS) * (1 - math.sin(abs(psi)))) ** 2


def _rows(theta, gear, centre, position=(0.0, 0.0)):
    state = PlatoonState(
        np.array([position[0], 9.0]),
        np.array([position[1], 9.0]),
        np.array([theta, 0.0]),
        np.zeros(2),
        np.array([gear, 1.0]),
    )
    sets = AchievableSets.for_gear(state, state.gear, LIMITS)
    offset = state.positions[:1] - centre
    table = Constraints(centre[None], np.array([RADIUS]), np.ones(1), np.ones(1, dtype=bool))
    return turning_rows(state.theta[:1], sets.axis[:1], offset, table, LIMITS, DT, 0.5)


@settings(max_examples=300)
@given(
    theta=st.floats(-math.pi, math.pi),
    gear=st.sampled_from([-1.0, 1.0]),
    cx=st.floats(-1.0, 1.0),
    cy=st.floats(-1.0, 1.0),
)
def test_a_turning_row_is_the_rate_of_its_barrier_under_the_vehicle_model(theta, gear, cx, cy):
    """The row's normal is -grad_v dH/dt, with the heading turning at theta' = e_perp . v / d."""
    centre = np.array([cx, cy])
    value = _barrier(np.zeros(2), theta, gear, centre)
    ahead, normal, _ = _rows(theta, gear, centre)
    assert ahead[0] == (value is not None and np.hypot(cx, cy) > RADIUS)
    psi = abs(wrap_angle(theta + (math.pi if gear < 0 else 0.0) - math.atan2(cy, cx)))
    if not ahead[0] or psi < 1e-3 or psi > math.pi / 2 - 1e-3:
        return  # |psi| has a kink at 0, and the rows end at pi/2
    step = 1e-7

    def rate(v):
        turn = (-math.sin(theta) * v[0] + math.cos(theta) * v[1]) / LIMITS.length
        after = _barrier(step * v, theta + step * turn, gear, centre)
        before = _barrier(-step * v, theta - step * turn, gear, centre)
        return (after - before) / (2 * step)

    gradient = np.array([rate(np.array([1.0, 0.0])), rate(np.array([0.0, 1.0]))])
    np.testing.assert_allclose(-normal[0], gradient / np.linalg.norm(gradient), atol=1e-5)


def test_at_the_boundary_head_on_the_unit_may_still_drive_forward_turning_away():
    """Head-on at H = 0: driving straight in is cut off, turning at the steering limit is not."""
    centre = np.array([RADIUS + turning_radius(LIMITS), 0.0])
    ahead, normal, offset = _rows(0.0, 1.0, centre)
    assert ahead[0] and offset[0] == pytest.approx(0.0, abs=1e-12)
    steer = LIMITS.max_steering
    assert normal[0] @ [1.0, 0.0] > 0
    assert normal[0] @ [math.cos(steer), math.sin(steer)] < 0


@pytest.mark.parametrize("rounding", [0.0, 1e-17])
def test_a_standing_unit_steers_toward_where_it_waits_to_go(rounding):
    """Also when the solver's zero is rounding (1e-17 m/s, in a direction of its own): the unit
    stands, it does not read that direction."""
    state = PlatoonState(np.zeros(2), np.array([0.0, 5.0]), np.zeros(2), np.array([0.7, 0.0]))
    held = unit_controller(state, np.zeros((2, 2)), LIMITS, DT)  # told nothing: holds its wheel
    assert np.all(held.steering_rate == 0)
    velocity = np.full((2, 2), rounding)
    waiting = np.array([[-1.0, -0.2], [0.0, 0.0]])  # behind unit 0: it changes gear
    command = unit_controller(state, velocity, LIMITS, DT, waiting=waiting)
    assert np.all(command.speed == 0)
    assert command.gear[0] == -1 and command.steering_rate[0] < 0
    assert command.gear[1] == 1 and command.steering_rate[1] == 0


def test_a_unit_pinned_at_the_margin_in_its_gear_backs_out():
    """At the guaranteed boundary, heading straight in, no forward velocity is safe; the nominal
    velocity points up and a little back, within the gear rule's hysteresis of forward: the
    standing target is the nearest safe velocity of the other gear, backing."""
    obstacles = CircularObstacles(np.array([[0.55, 0.0]]), np.array([0.5]))
    problem = build_problem([0.0, 0.0], [0.0, 3.0], [0.0, 0.0])
    nominal = np.array([[-0.2, 1.0], [0.0, 1.0]])
    problem = dataclasses.replace(problem, obstacles=obstacles, nominal=nominal, gear=np.ones(2))
    params = SafetyParams(mode="barrier", turning_room=False)
    velocities = np.array([[0.0, 0.0], [0.0, 1.0]])
    targets = standing_targets(problem, params, velocities)[0]
    assert targets[0] @ [1.0, 0.0] < 0 and targets[0] @ nominal[0] > 0  # backing, toward the nominal
    np.testing.assert_array_equal(targets[1], velocities[1])


HEAD_ON = """
name = "head_on"
[simulation]
dt = 0.01
duration = 14.0
[platoon]
n = 3
center = [0.0, 0.0]
variance = [0.1, 0.1]
heading = 0.0
[target]
speed = 0.5
waypoints = [[0.0, 0.0], [6.0, 0.0]]
[task]
kind = "mean_variance"
gains = [50.0, 10.0, 50.0, 10.0]
[task.desired]
var_x = 0.1
var_y = 0.1
[safety]
mode = "barrier"
[[obstacles]]
center = [3.0, 0.0]
radius = 0.5
"""


@pytest.mark.parametrize("turning", [True, False])
@pytest.mark.parametrize(
    "allocator, options",
    [("iterative", {"max_iterations": 0}), ("dual", {"reading": "task-exact", "rate_aware": True})],
)
def test_a_unit_driven_head_on_at_an_obstacle_goes_round_it(turning, allocator, options):
    """Three units drive along x through an obstacle on the axis; the unit on the axis meets it
    head-on. With turning rows it turns away early; without them it reaches the margin heading
    in, is blocked (its nominal velocity has no part in its safe set), and its escape
    (``solvers.safety.escape``) backs it out: either way it passes, never inside the margin."""
    data = tomllib.loads(HEAD_ON)
    data["safety"]["turning_room"] = turning
    # The iteration runs in the engine, the dual in the host loop: both loops' handouts meet the
    # head-on unit, and compiling four programs would take a minute.
    trajectory = simulate(
        parse_scenario(data, "head_on"),
        get_allocator(allocator, **options),
        compiled=allocator == "iterative",
    )
    assert trajectory.compiled == (allocator == "iterative")
    assert (trajectory.x[-1] > 3.6).all()  # beyond the obstacle's far side
    clearance = np.hypot(trajectory.x - 3.0, trajectory.y) - 0.5
    assert clearance.min() >= 0.05 - 1e-9
