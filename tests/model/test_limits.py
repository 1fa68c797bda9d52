import dataclasses

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from platoon_opt import AchievableSets, PlatoonState, VehicleLimits
from platoon_opt.limits import inner_projection, project_either_gear, unit_rows
from platoon_opt.vehicle import choose_gear, unit_controller
from tests.conftest import random_problem, random_state

LIMITS = VehicleLimits()


def sample_sector(sets: AchievableSets, i: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """Points of unit i's sector: a grid plus random samples, edges and apex included."""
    angles = np.concatenate(
        (np.linspace(sets.lower[i], sets.upper[i], 41), rng.uniform(sets.lower[i], sets.upper[i], count))
    )
    speeds = np.concatenate((np.linspace(0, sets.max_speed, 41), rng.uniform(0, sets.max_speed, count)))
    a, s = np.meshgrid(angles, speeds)
    a, s = a.ravel() + sets.axis[i], s.ravel()
    return np.column_stack((s * np.cos(a), s * np.sin(a)))


def unit_sets(sets: AchievableSets, i: int, count: int) -> AchievableSets:
    """Unit i's sector repeated ``count`` times, to test many points against it."""
    return AchievableSets(
        np.full(count, sets.axis[i]),
        np.full(count, sets.lower[i]),
        np.full(count, sets.upper[i]),
        sets.max_speed,
    )


@given(st.integers(0, 2**32 - 1), st.booleans())
def test_projection_is_achievable_and_no_sampled_point_is_closer(seed, rate_aware):
    rng = np.random.default_rng(seed)
    state = random_state(rng, 6)
    sets = AchievableSets.for_gear(state, state.gear, LIMITS, rate_aware=rate_aware, dt=0.01)
    velocity = rng.normal(0, 1.5, (6, 2))
    projected = sets.project(velocity)
    assert np.all(sets.contains(projected, tol=1e-12))
    for i in range(6):
        points = sample_sector(sets, i, 60, rng)
        best = np.min(np.linalg.norm(points - velocity[i], axis=1))
        assert np.linalg.norm(projected[i] - velocity[i]) <= best + 1e-12


@given(st.integers(0, 2**32 - 1))
def test_projection_of_an_achievable_velocity_is_itself(seed):
    rng = np.random.default_rng(seed)
    state = random_state(rng, 5)
    sets = AchievableSets.for_gear(state, state.gear, LIMITS)
    inside = np.array([sample_sector(sets, i, 1, rng)[rng.integers(0, 40)] for i in range(5)])
    np.testing.assert_allclose(sets.project(inside), inside, atol=1e-12)


@given(st.integers(0, 2**32 - 1))
def test_either_gear_picks_the_nearer_sector(seed):
    rng = np.random.default_rng(seed)
    state = random_state(rng, 5)
    velocity = rng.normal(0, 1.5, (5, 2))
    best = project_either_gear(velocity, state, LIMITS)
    for gear in (1.0, -1.0):
        one = AchievableSets.for_gear(state, np.full(5, gear), LIMITS).project(velocity)
        assert np.all(
            np.linalg.norm(best - velocity, axis=1) <= np.linalg.norm(one - velocity, axis=1) + 1e-12
        )


@given(st.integers(0, 2**32 - 1), st.sampled_from([0.01, 1.0, 100.0]))
def test_the_nearer_gear_is_the_sector_nearer_the_nominal_velocity(seed, scale):
    """``AllocationProblem.in_nearer_gears`` (the gear rule without hysteresis) against the
    distances to both gears' sectors: its sector is never farther from the nominal velocity than
    the other gear's, it is its own nearer gear, and nothing but the gears changes."""
    rng = np.random.default_rng(seed)
    problem = random_problem(rng, 12)
    problem = dataclasses.replace(problem, nominal=rng.normal(0, 1, (12, 2)) * scale)
    nearer = problem.in_nearer_gears()
    chosen = AchievableSets.for_gear(problem.state, nearer.gear, LIMITS).distance(problem.nominal)
    other = AchievableSets.for_gear(problem.state, -nearer.gear, LIMITS).distance(problem.nominal)
    assert np.all(chosen <= other + 1e-12 * scale)
    np.testing.assert_array_equal(nearer.nominal, problem.nominal)
    np.testing.assert_array_equal(nearer.in_nearer_gears().gear, nearer.gear)


@given(st.integers(0, 2**32 - 1), st.floats(0.0, 0.05))
def test_a_platoon_catches_up_when_its_mean_error_outruns_the_top_speed(seed, error):
    """``AllocationProblem.feedback_speed`` and ``catching_up`` against their closed form for the
    mean-variance task: the speed of the mean rows' feedback K_mu (f_d,mu - mu), here 50 ``error``
    in a random direction, and whether it exceeds the top speed (the variance rows' least-norm
    velocities sum to zero over the units, and the target's rate f_d' is left out);
    ``in_nearer_gears(where=...)`` changes only the gears it is asked to."""
    rng = np.random.default_rng(seed)
    problem = random_problem(rng, 7)
    angle = rng.uniform(-np.pi, np.pi)
    feedback = np.array([np.cos(angle), 0.0, np.sin(angle), 0.0]) * 50.0 * error
    feedback[[1, 3]] = rng.normal(0, 5, 2)
    rate = rng.normal(0, 2, 4)
    problem = dataclasses.replace(problem, desired_rate=rate, task_velocity=rate + feedback)
    speed = float(np.hypot(feedback[0], feedback[2]))
    np.testing.assert_allclose(float(problem.feedback_speed()), speed, rtol=1e-9, atol=1e-12)
    assume(abs(speed - LIMITS.max_speed) > 1e-9)
    assert bool(problem.catching_up()) == (speed > LIMITS.max_speed)
    mask = rng.random(7) < 0.5
    nearer = problem.in_nearer_gears().gear
    np.testing.assert_array_equal(
        problem.in_nearer_gears(where=mask).gear, np.where(mask, nearer, problem.gear)
    )
    np.testing.assert_array_equal(problem.in_nearer_gears(where=False).gear, problem.gear)


def test_a_nominal_between_the_right_angle_and_the_hysteresis_takes_the_other_gear():
    """Forward at heading 0 with the gear rule's 30 degrees of hysteresis: a nominal velocity at
    100 degrees keeps the gear rule's forward gear, and lies nearer the backing sector."""
    problem = random_problem(np.random.default_rng(0), 3)
    state = PlatoonState(problem.state.x, problem.state.y, np.zeros(3), np.zeros(3), np.ones(3))
    angle = np.radians([60.0, 100.0, 130.0])
    nominal = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    gear = choose_gear(nominal, state.theta, state.gear, LIMITS)
    problem = dataclasses.replace(problem, state=state, nominal=nominal, gear=gear)
    np.testing.assert_array_equal(problem.gear, [1.0, 1.0, -1.0])
    np.testing.assert_array_equal(problem.in_nearer_gears().gear, [1.0, -1.0, -1.0])


@settings(max_examples=25)
@given(st.integers(0, 2**32 - 1), st.integers(3, 40), st.booleans())
def test_polygon_is_inside_the_sector_and_close_to_it(seed, sides, rate_aware):
    rng = np.random.default_rng(seed)
    state = random_state(rng, 4)
    sets = AchievableSets.for_gear(state, state.gear, LIMITS, rate_aware=rate_aware, dt=0.01)
    normals, offsets = sets.polygon(sides)
    for i in range(4):
        points = sample_sector(sets, i, 200, rng)
        feasible = np.all(points @ normals[i].T <= offsets[i] + 1e-12, axis=1)
        # Every polygon point is in the sector; every sector point within the inscribed radius
        # (v_max cos(pi / sides)) is in the polygon.
        assert np.all(unit_sets(sets, i, int(feasible.sum())).contains(points[feasible], tol=1e-12))
        inner = np.linalg.norm(points, axis=1) <= sets.max_speed * np.cos(np.pi / sides) - 1e-12
        assert np.all(feasible[inner])


@given(st.integers(0, 2**32 - 1), st.floats(1e-4, 0.05))
def test_either_gear_with_asymmetric_rate_aware_sectors(seed, dt):
    rng = np.random.default_rng(seed)
    state = random_state(rng, 6)
    sets = AchievableSets.for_gear(state, np.ones(6), LIMITS, rate_aware=True, dt=dt)
    velocity = rng.normal(0, 1.5, (6, 2))
    nearest = np.minimum(
        np.linalg.norm(sets.project(velocity) - velocity, axis=1),
        np.linalg.norm(-sets.project(-velocity) - velocity, axis=1),
    )
    np.testing.assert_allclose(
        np.linalg.norm(sets.project_either_gear(velocity) - velocity, axis=1), nearest, atol=1e-12
    )


@settings(max_examples=50)
@given(st.integers(0, 2**32 - 1), st.integers(3, 40), st.booleans())
def test_inner_projection_is_the_longest_point_of_its_ray_within_the_rows(seed, sides, rate_aware):
    """Against the rows of ``unit_rows``: the result meets every row, lies on the ray of the exact
    projection no farther out, equals it where that meets the polygon's rows, and is the ray's
    last point within them (a hair farther breaks one)."""
    rng = np.random.default_rng(seed)
    state = random_state(rng, 8)
    sets = AchievableSets.for_gear(state, state.gear, LIMITS, rate_aware=rate_aware, dt=0.01)
    velocity = rng.normal(0, 1.5, (8, 2)) * rng.choice([0.1, 1.0, 10.0], (8, 1))
    projected = sets.project(velocity)
    inner = inner_projection(velocity, sets, "polygon", sides)
    normals, offsets = unit_rows(sets, "polygon", sides, LIMITS.max_speed)
    # The steering rows (offset 0) hold at the exact projection up to round-off; the polygon's
    # edges (offset > 0) are what shortens.
    edges = offsets > 0

    def excess(v: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return np.max(np.where(rows, np.einsum("ikj,ij->ik", normals, v) - offsets, -np.inf), axis=1)

    assert np.all(excess(inner, np.ones_like(edges)) <= 1e-12)
    scale = np.einsum("ij,ij->i", inner, projected) / np.maximum(
        np.einsum("ij,ij->i", projected, projected), 1e-300
    )
    np.testing.assert_allclose(inner, scale[:, None] * projected, rtol=0, atol=1e-12)
    assert np.all(scale <= 1 + 1e-12)
    within = excess(projected, edges) <= 0
    np.testing.assert_allclose(inner[within], projected[within], rtol=0, atol=1e-15)
    assert np.all(excess(inner * (1 + 1e-9), edges)[~within] > 0)
    np.testing.assert_array_equal(inner_projection(velocity, sets, "cone", sides), projected)


@given(st.integers(0, 2**32 - 1), st.floats(0.005, 0.05))
def test_steer_is_the_velocity_the_unit_drives_within_the_step(seed, dt):
    """Handed ``velocity``, a unit's controller (Eq. 2, deadbeat: K_alpha dt = 1) turns its steering
    as far toward the velocity's direction as its rate lets it and drives the velocity's speed: its
    tip then moves at ``steer(velocity)`` of its rate-aware sector. Inside the sector a velocity is
    its own image; steering is idempotent."""
    rng = np.random.default_rng(seed)
    limits = VehicleLimits(steering_gain=1 / dt)
    state = random_state(rng, 8)
    velocity = rng.normal(0, 1.0, (8, 2))
    gear = choose_gear(velocity, state.theta, state.gear, limits)
    sets = AchievableSets.for_gear(state, gear, limits, rate_aware=True, dt=dt)
    steered = sets.steer(velocity)
    command = unit_controller(state, velocity, limits, dt)
    np.testing.assert_array_equal(command.gear, gear)
    alpha = state.alpha + command.steering_rate * dt
    driven = command.speed[:, None] * np.column_stack(
        (np.cos(state.theta + alpha), np.sin(state.theta + alpha))
    )
    np.testing.assert_allclose(steered, driven, atol=1e-12)
    assert np.all(sets.contains(steered, tol=1e-12))
    np.testing.assert_allclose(sets.steer(steered), steered, atol=1e-12)
    inside = np.array([sample_sector(sets, i, 1, rng)[rng.integers(0, 40)] for i in range(8)])
    np.testing.assert_allclose(sets.steer(inside), inside, atol=1e-12)
