"""Barrier constraints and safe sets (docs/safety.md): the guarantee through the real vehicle
model, the exact projection, the direction bound, feasibility, the slack, O(n) memory."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.errors import ConfigurationError
from platoon_opt.limits import AchievableSets
from platoon_opt.safe_sets import SafeSets
from platoon_opt.safety import SafetyParams, direction_error, robust_rows
from platoon_opt.vehicle import PlatoonState, VehicleLimits, choose_gear, step_vehicles, unit_controller
from tests.conftest import LIMITS, barrier_margin, safe_problem

BARRIER = SafetyParams(mode="barrier")


def _sets_for(problem, velocity, rate_aware):
    """The safe sets of the gear the unit controller will choose for ``velocity``."""
    state = problem.state
    gear = choose_gear(velocity, state.theta, state.gear, problem.limits)
    return problem.safe_sets(problem.safety, rate_aware=rate_aware, gear=gear)


@settings(max_examples=1500)
@given(seed=st.integers(0, 2**32 - 1), rate_aware=st.booleans(), crowded=st.booleans())
def test_a_safe_velocity_keeps_every_barrier_through_the_vehicle_model(seed, rate_aware, crowded):
    problem = safe_problem(seed, crowded=crowded)
    velocity = np.random.default_rng(seed).normal(0, 1.0, (problem.n, 2))
    safe = _sets_for(problem, velocity, rate_aware)
    assert np.all(safe.slack == 0)  # feasible from every safe state
    allocated = safe.project(velocity)
    assert np.max(safe.violation(allocated)) <= 1e-12
    assert barrier_margin(problem, allocated, problem.safety) >= -1e-12


def test_without_the_robust_rows_the_vehicle_model_breaks_barriers(monkeypatch):
    """The steering lag and the arc matter: with a zero direction bound some steps leave the set."""
    import platoon_opt.safety as safety

    monkeypatch.setattr(safety, "direction_error", lambda state, sets, limits, dt: np.zeros(state.n))
    worst = np.inf
    for seed in range(400):
        problem = safe_problem(seed, crowded=True)
        velocity = np.random.default_rng(seed).normal(0, 1.0, (problem.n, 2))
        allocated = _sets_for(problem, velocity, False).project(velocity)
        worst = min(worst, barrier_margin(problem, allocated, problem.safety))
    assert worst < -1e-6


@settings(max_examples=300)
@given(seed=st.integers(0, 2**32 - 1), rate_aware=st.booleans())
def test_the_executed_direction_is_within_the_bound(seed, rate_aware):
    problem = safe_problem(seed)
    state, limits, dt = problem.state, problem.limits, problem.dt
    rng = np.random.default_rng(seed)
    sets = problem.achievable(rate_aware=rate_aware)
    phi = rng.uniform(sets.lower, sets.upper)
    velocity = rng.uniform(0.01, 1.0, problem.n)[:, None] * sets.unit_vectors(phi)
    bound = direction_error(state, sets, limits, dt)
    after = step_vehicles(state, unit_controller(state, velocity, limits, dt), limits, dt)
    moved = after.positions - state.positions
    angle = np.angle((moved[:, 0] + 1j * moved[:, 1]) * np.exp(-1j * (sets.axis + phi)))
    assert np.all(np.abs(angle) <= bound)


@settings(max_examples=300)
@given(seed=st.integers(0, 2**32 - 1), scale=st.sampled_from([1.5, 1e3, 1e5]))
def test_the_projection_is_the_nearest_point(seed, scale):
    """Against every feasible point y of a dense random sample: (w - P w) . (y - P w) <= 0, also
    for velocities far outside (the dual's iterates reach 1e5 m/s)."""
    problem = safe_problem(seed, crowded=True)
    rng = np.random.default_rng(seed)
    safe = problem.safe_sets(BARRIER, rate_aware=bool(seed % 2), speed=("cone", "polygon")[seed % 3 == 0])
    w = rng.normal(0, scale, (problem.n, 2))
    p = safe.project(w)
    assert np.max(safe.violation(p)) <= 1e-12
    samples = rng.uniform(-1, 1, (400, problem.n, 2))
    for y in samples:
        inside = safe.violation(y) <= 0
        assert np.all(np.einsum("ij,ij->i", w - p, y - p)[inside] <= 1e-12 * scale)
        closer = np.einsum("ij,ij->i", y - p, y + p - 2 * w)  # |w - y|^2 - |w - p|^2
        assert np.all(closer[inside] >= -1e-12 * scale)


@settings(max_examples=200)
@given(seed=st.integers(0, 2**32 - 1))
def test_sliding_is_the_nearest_point_of_the_barrier_rows_and_the_disk(seed):
    """``SafeSets.sliding``: the projection onto the barrier rows and the speed disk alone (the
    sector's rows dropped): it meets them, it is nearer to w than every sampled point that does,
    and a velocity that meets them slides nowhere."""
    problem = safe_problem(seed, crowded=True)
    rng = np.random.default_rng(seed)
    safe = problem.safe_sets(BARRIER, rate_aware=bool(seed % 2))
    w = rng.normal(0, 2.0, (problem.n, 2))
    p = safe.sliding(w)

    def violation(v):
        rows = np.einsum("ikj,ij->ik", safe.barrier_normals, v) - safe.barrier_offsets
        return np.maximum(np.max(rows, axis=1, initial=-np.inf), np.hypot(*v.T) - safe.radius)

    assert np.max(violation(p)) <= 1e-12
    for k, y in enumerate(rng.uniform(-1, 1, (400, problem.n, 2))):
        inside = violation(y) <= 0
        assert np.all(np.einsum("ij,ij->i", w - p, y - p)[inside] <= 1e-12)
        if k < 50:  # a projection per sample: 10,000 over the examples, most of this test's time
            np.testing.assert_allclose(safe.sliding(y)[inside], y[inside], atol=1e-12)


def test_a_far_velocity_nearly_normal_to_an_edge_projects_onto_the_edge():
    """A dual iterate of a closed-loop run (paper_obstacles, seed 1): a velocity 2e5 m/s out, almost
    normal to a polygon edge. Its projection lies inside the edge; the distance test once lost it
    to rounding at |w|^2 and picked a corner 0.39 m/s away, so the dual's gradient jumped and
    Newton stalled."""
    normals = np.array(
        [
            [0.9852730884767575, -0.17098813152810177],
            [-0.8091057489041731, -0.5876630727638221],
            [0.35309872049672253, 0.9355860695754172],
            [-0.031812607555238834, 0.9994938509068159],
            [-0.4118807544889207, 0.9112377538719725],
            [-0.7292437902600012, 0.6842539692009301],
        ]
    )
    offsets = np.array([0.0, 0.0] + [math.cos(math.pi / 16)] * 4)
    sets = AchievableSets(np.array([1.5441665556068198]), np.array([-0.1452]), np.array([0.6548]), 1.0)
    tangent = np.array([-normals[3, 1], normals[3, 0]])
    # Along the edge's tangent, 1 mm/s apart: each projection is the edge's point below it.
    w = np.array([-6602.410870989956, 207435.65432154105]) + np.linspace(-0.15, 0.15, 301)[:, None] * tangent
    p = SafeSets(
        sets.take(np.zeros(301, int)),
        np.repeat(normals[None], 301, 0),
        np.repeat(offsets[None], 301, 0),
        6,
        1.0,
        np.zeros(301),
        np.full(301, np.inf),
        np.zeros(301, dtype=bool),
    ).project(w)
    expected = offsets[3] * normals[3] + (w @ tangent)[:, None] * tangent
    assert np.max(np.abs(p - expected)) <= 1e-9


def test_robust_rows_hold_for_every_rotation():
    rng = np.random.default_rng(0)
    direction = np.array([0.6, 0.8])
    for error, budget in ((0.3, 0.5), (0.01, 0.0), (1.2, 2.0)):
        normals, offsets = robust_rows(direction, np.float64(budget), np.float64(error))
        v = rng.uniform(-4, 4, (20000, 2))
        inside = np.all(v @ normals.T <= offsets, axis=1)
        for e in np.linspace(-error, error, 41):
            rotated = v @ np.array([[math.cos(e), math.sin(e)], [-math.sin(e), math.cos(e)]])
            assert np.all(rotated[inside] @ direction >= -budget - 1e-12)


def test_an_unsafe_state_gets_a_slack_and_a_non_empty_set():
    # A unit inside an inflated obstacle, heading into it: it cannot leave within the step.
    state = PlatoonState(np.array([0.3, 3.0]), np.array([0.0, 0.0]), np.array([math.pi, 0.0]), np.zeros(2))
    obstacles = CircularObstacles(np.array([[0.0, 0.0]]), np.array([0.28]))
    sets = AchievableSets.for_gear(state, state.gear, LIMITS, rate_aware=True, dt=0.01)
    safe = SafeSets.build(state, obstacles, LIMITS, 0.01, sets, BARRIER)
    assert safe.slack[0] > 0 and safe.slack[1] == 0 and safe.worst[0] < 0
    point = safe.project(np.zeros((2, 2)))
    assert np.max(safe.violation(point)) <= 1e-12


def test_a_cutoff_too_short_for_one_step_is_a_configuration_error():
    params = SafetyParams(mode="barrier", safety_distance=0.3, neighbour_cutoff=0.31)
    with pytest.raises(
        ConfigurationError, match=r"neighbour_cutoff must be >= safety_distance \+ 2 max_speed dt"
    ):
        params.check(LIMITS, 0.01)
    with pytest.raises(ConfigurationError, match="max_steering \\+ gear_hysteresis < 90"):
        BARRIER.check(VehicleLimits(max_steering=math.radians(70)), 0.01)


@pytest.mark.parametrize(
    "field, value", [("mode", "on"), ("barrier_rate", 0.0), ("barrier_rate", 1.5), ("safety_distance", -1.0)]
)
def test_bad_safety_params_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"SafetyParams.{field}"):
        SafetyParams(**{field: value})


def test_memory_is_linear_in_the_units():
    """n = 100,000 units on a grid with obstacles among them: the rows are O(n k), the peak of
    building and projecting a few hundred bytes per unit, nothing n x n."""
    n = 100_000
    side = int(math.ceil(math.sqrt(n)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), axis=-1).reshape(-1, 2)[:n] * 0.4
    state = PlatoonState(grid[:, 0], grid[:, 1], np.zeros(n), np.zeros(n))
    obstacles = CircularObstacles(np.array([[20.2, 20.2], [60.2, 30.2]]), np.array([0.1, 0.1]))
    sets = AchievableSets.for_gear(state, state.gear, LIMITS, rate_aware=True, dt=0.01)
    params = SafetyParams(mode="barrier", neighbour_cutoff=0.45)
    tracemalloc.start()
    safe = SafeSets.build(state, obstacles, LIMITS, 0.01, sets, params)
    safe.project(np.ones((n, 2)))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    # 4 grid neighbours and one obstacle within 0.45 m (3 rows each); a turning row for each of the
    # 6 neighbours ahead within 0.45 + turning_radius m, and for the obstacle
    assert safe.normals.shape[1] <= 2 + 3 * 5 + 7
    assert peak < 4_000 * n


def test_a_state_on_the_boundary_to_rounding_needs_no_slack():
    """Two units 4e-14 m inside the safety distance (what a step that keeps h >= 0 leaves after
    rounding) are on the boundary, not unsafe."""
    state = PlatoonState(np.array([0.0, 0.3 - 4e-14]), np.zeros(2), np.array([0.0, math.pi]), np.zeros(2))
    sets = AchievableSets.for_gear(state, state.gear, LIMITS, rate_aware=True, dt=0.01)
    safe = SafeSets.build(state, CircularObstacles.none(), LIMITS, 0.01, sets, BARRIER)
    assert np.all(safe.slack == 0)
