"""Degenerate platoons and inputs: every registered allocator returns finite velocities and a
closed-loop step stays finite and within the limits."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from platoon_opt import (
    AllocationProblem,
    CircularObstacles,
    MeanVarianceTask,
    PlatoonController,
    PlatoonState,
    VehicleLimits,
)
from platoon_opt.solvers import available_allocators, get_allocator
from platoon_opt.vehicle import choose_gear

LIMITS = VehicleLimits()
GAINS = np.array([50.0, 10.0, 50.0, 10.0])
# Allocators too slow to run on every degenerate case in the suite (tested on their own).
SLOW = {"nmpc"}


def ring(n: int = 8) -> PlatoonState:
    angle = 2 * np.pi * np.arange(n) / n
    return PlatoonState(np.cos(angle), np.sin(angle), np.full(n, np.pi / 2), np.zeros(n))


def case(name: str) -> dict:
    """Inputs of one degenerate case: state, desired f_d and f_d', gains, dt, obstacles."""
    state, obstacles, dt, gains = ring(), CircularObstacles.none(), 0.01, GAINS
    task = MeanVarianceTask()
    desired = task.value(state.positions) + np.array([1.0, 0.0, 0.5, 0.0])
    rate = np.array([0.8, 0.0, 0.0, 0.0])
    if name == "coincident_units":
        state = PlatoonState(np.zeros(8), np.zeros(8), np.linspace(-3, 3, 8), np.zeros(8))
    elif name == "vertical_line":
        state = PlatoonState(np.zeros(8), np.linspace(0, 7, 8), np.zeros(8), np.zeros(8))
    elif name == "horizontal_line":
        state = PlatoonState(np.linspace(0, 7, 8), np.zeros(8), np.zeros(8), np.zeros(8))
    elif name == "two_units":
        state = PlatoonState([0.0, 2.0], [0.0, 1.0], [0.0, 1.0], [0.0, 0.0])
        desired = task.value(state.positions) + np.array([1.0, 0.0, 0.5, 0.0])
    elif name == "desired_variance_zero":
        desired = np.array([1.0, 0.0, 0.5, 0.0])
    elif name == "target_at_mean":
        desired, rate = task.value(state.positions), np.zeros(4)
    elif name == "zero_nominal":
        state = PlatoonState(4.0 * np.arange(8), np.zeros(8), np.zeros(8), np.zeros(8))
        desired, rate = task.value(state.positions), np.zeros(4)
    elif name == "unit_inside_obstacle":
        obstacles = CircularObstacles([[1.0, 0.0]], [0.3])
    elif name == "obstacle_covering_platoon":
        obstacles = CircularObstacles([[0.0, 0.0]], [5.0])
    elif name == "huge_gains":
        gains = np.full(4, 1e6)
    elif name == "tiny_dt":
        dt = 1e-6
    elif name == "huge_dt":
        dt = 1.0
    elif name == "steering_at_limit":
        state = replace(state, alpha=np.where(np.arange(8) % 2 == 0, 1, -1) * LIMITS.max_steering)
    elif name == "perpendicular_velocity":
        state = PlatoonState(4.0 * np.arange(8), np.zeros(8), np.zeros(8), np.zeros(8))
        desired, rate = task.value(state.positions), np.array([0.0, 0.0, 0.7, 0.0])
    else:
        raise KeyError(name)
    return dict(state=state, desired=desired, rate=rate, gains=gains, dt=dt, obstacles=obstacles)


CASES = (
    "coincident_units",
    "vertical_line",
    "horizontal_line",
    "two_units",
    "desired_variance_zero",
    "target_at_mean",
    "zero_nominal",
    "unit_inside_obstacle",
    "obstacle_covering_platoon",
    "huge_gains",
    "tiny_dt",
    "huge_dt",
    "steering_at_limit",
    "perpendicular_velocity",
)


@pytest.mark.parametrize("allocator_name", [a for a in available_allocators() if a not in SLOW])
@pytest.mark.parametrize("name", CASES)
def test_degenerate_case_is_finite_and_within_limits(name, allocator_name):
    inputs = case(name)
    controller = PlatoonController(
        task=MeanVarianceTask(),
        gains=inputs["gains"],
        limits=LIMITS,
        allocator=get_allocator(allocator_name),
        obstacles=inputs["obstacles"],
    )
    state = inputs["state"]
    for k in range(3):
        result = controller.step(state, inputs["desired"], inputs["rate"], inputs["dt"], k * inputs["dt"])
        assert np.all(np.isfinite(result.allocation.velocities)), result.allocation.status
        assert isinstance(result.allocation.status, str)
        state = result.state
        for key in ("x", "y", "theta", "alpha"):
            assert np.all(np.isfinite(getattr(state, key)))
        assert np.all(np.abs(state.alpha) <= LIMITS.max_steering + 1e-12)


@pytest.mark.parametrize(
    "name, degenerate", [("coincident_units", 2), ("vertical_line", 1), ("horizontal_line", 1)]
)
def test_zero_variance_is_reported(name, degenerate):
    inputs = case(name)
    problem = AllocationProblem.build(
        inputs["state"], MeanVarianceTask(), inputs["desired"], inputs["rate"], GAINS, LIMITS, 0.01
    )
    allocation = get_allocator("iterative").allocate(problem)
    assert allocation.degenerate_task == degenerate


def test_coincident_units_repel_deterministically():
    inputs = case("coincident_units")
    build = lambda: AllocationProblem.build(  # noqa: E731
        inputs["state"], MeanVarianceTask(), inputs["desired"], inputs["rate"], GAINS, LIMITS, 0.01
    )
    first, second = build(), build()
    np.testing.assert_array_equal(first.secondary, second.secondary)
    assert np.all(np.linalg.norm(first.secondary, axis=1) > 0)


def test_zero_nominal_velocity_is_exactly_zero():
    inputs = case("zero_nominal")
    problem = AllocationProblem.build(
        inputs["state"], MeanVarianceTask(), inputs["desired"], inputs["rate"], GAINS, LIMITS, 0.01
    )
    np.testing.assert_allclose(problem.nominal, 0.0, atol=1e-12)


def test_gear_tie_keeps_the_gear():
    """A desired velocity exactly at the switching angle keeps the current gear."""
    for hysteresis in (0.0, math.radians(30)):
        limits = replace(LIMITS, gear_hysteresis=hysteresis)
        angle = math.pi / 2 + hysteresis
        velocity = np.array([[math.cos(angle), math.sin(angle)], [math.cos(-angle), math.sin(-angle)]])
        np.testing.assert_array_equal(choose_gear(velocity, np.zeros(2), np.ones(2), limits), [1, 1])


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(dt=0.0), "dt"),
        (dict(gains=np.array([1.0, -1.0, 1.0, 1.0])), "gains"),
        (dict(gains=np.ones(3)), "gains"),
        (dict(desired=np.array([0.0, math.nan, 0.0, 0.0])), "desired"),
        (dict(desired_rate=np.ones(5)), "desired_rate"),
    ],
)
def test_bad_problem_input_names_the_field(change, field):
    state = ring()
    arguments = dict(
        state=state,
        task=MeanVarianceTask(),
        desired=np.zeros(4),
        desired_rate=np.zeros(4),
        gains=GAINS,
        limits=LIMITS,
        dt=0.01,
    )
    arguments.update(change)
    with pytest.raises(ValueError, match=field):
        AllocationProblem.build(**arguments)


def test_steering_beyond_the_limit_is_rejected():
    state = replace(ring(), alpha=np.full(8, 1.0))
    with pytest.raises(ValueError, match="alpha"):
        AllocationProblem.build(state, MeanVarianceTask(), np.zeros(4), np.zeros(4), GAINS, LIMITS, 0.01)
