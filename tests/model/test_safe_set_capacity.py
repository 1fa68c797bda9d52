"""The safe sets' build of fixed shapes (``SafeSets.build(..., capacity=...)``), for compiled
code: traced by ``jax.jit`` it builds the host's rows (to rounding), relaxes an unsafe unit's
rows as the host does, marks exactly the units whose constraints or rows its capacity cannot
hold, and its sets keep every barrier through the vehicle model."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.barrier_constraints import Capacity, constraints_within
from platoon_opt.limits import AchievableSets
from platoon_opt.safe_sets import SafeSets
from platoon_opt.safety import search
from platoon_opt.vehicle import PlatoonState, choose_gear
from tests.conftest import barrier_margin, padded_safe_state, safe_problem

# Enough for every state of ``safe_problem``: at most 3 obstacles and 8 units.
ROOMY = Capacity(obstacles=3, neighbours=7, rows=40)


def _compiled(state, obstacles, gear, limits, dt, params, capacity, rate_aware):
    sets = AchievableSets.for_gear(state, gear, limits, rate_aware=rate_aware, dt=dt)
    return SafeSets.build(state, obstacles, limits, dt, sets, params, capacity=capacity)


COMPILED = jax.jit(_compiled, static_argnames=("params", "capacity", "rate_aware"))
PROJECT = jax.jit(SafeSets.project)


def _both(seed, crowded, shrink, rate_aware, capacity=ROOMY):
    """The host's and the compiled build of a ``safe_problem`` with its positions scaled by
    ``shrink`` (below 1: often unsafe), in random gears."""
    problem = safe_problem(seed, crowded=crowded)
    state = dataclasses.replace(problem.state, x=problem.state.x * shrink, y=problem.state.y * shrink)
    gear = np.where(np.random.default_rng(seed).random(problem.n) < 0.3, -1.0, 1.0)
    sets = AchievableSets.for_gear(state, gear, problem.limits, rate_aware=rate_aware, dt=problem.dt)
    host = SafeSets.build(state, problem.obstacles, problem.limits, problem.dt, sets, problem.safety)
    compiled = COMPILED(
        *padded_safe_state(state, problem, gear),
        problem.limits,
        problem.dt,
        problem.safety,
        capacity,
        rate_aware,
    )
    return problem, state, host, jax.tree_util.tree_map(lambda leaf: _units(leaf, problem.n), compiled)


def _units(leaf, n):
    """The first n units of a per-unit leaf as numpy; a number as it is."""
    leaf = np.asarray(leaf)
    return leaf[:n] if leaf.ndim else leaf


@settings(max_examples=200, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    crowded=st.booleans(),
    shrink=st.sampled_from([1.0, 0.7, 0.4]),
    rate_aware=st.booleans(),
)
def test_a_compiled_build_is_the_host_build(seed, crowded, shrink, rate_aware):
    """Rows, relaxations and barrier values agree to rounding (XLA's and numpy's arithmetic
    differ in the last bits); the capacity's spare rows are padding."""
    _, _, host, compiled = _both(seed, crowded, shrink, rate_aware)
    k = host.normals.shape[1]
    assert not np.any(compiled.overflow)
    np.testing.assert_allclose(compiled.normals[:, :k], host.normals, rtol=0, atol=1e-12)
    scale = np.maximum(1.0, np.abs(host.offsets))
    assert np.all(np.abs(compiled.offsets[:, :k] - host.offsets) <= 1e-12 * scale)
    # Spare rows, as the host's padding rows: zero normals, relaxed like the unit's other rows.
    assert np.all(compiled.normals[:, k:] == 0)
    assert np.all(compiled.offsets[:, k:] == compiled.slack[:, None])
    np.testing.assert_allclose(compiled.slack, host.slack, rtol=1e-12, atol=1e-12)
    assert np.array_equal(np.isinf(compiled.worst), np.isinf(host.worst))
    finite = np.isfinite(host.worst)
    np.testing.assert_allclose(compiled.worst[finite], host.worst[finite], rtol=1e-12, atol=1e-12)


def test_unsafe_states_are_among_the_compared():
    """The comparison above meets relaxed units (the compiled bisection loop runs)."""
    relaxed = sum(np.count_nonzero(_both(seed, True, 0.4, True)[2].slack) for seed in range(10))
    assert relaxed > 0


@pytest.mark.parametrize("seed", range(40))
def test_a_small_capacity_marks_exactly_the_units_it_cannot_hold(seed):
    """One obstacle slot, two neighbour slots and six rows: a unit overflows when the host gives
    it more obstacles, more neighbours or more rows; every other unit has the host's rows."""
    capacity = Capacity(obstacles=1, neighbours=2, rows=6)
    problem, state, host, compiled = _both(seed, True, 1.0, True, capacity)
    params = problem.safety
    table = constraints_within(
        state.positions,
        problem.obstacles,
        params.obstacle_margin,
        params.safety_distance,
        search(params, problem.limits, problem.dt),
    )
    obstacles = np.count_nonzero(table.present & (table.share == 1), axis=1)
    neighbours = np.count_nonzero(table.present & (table.share == 2), axis=1)
    rows = np.count_nonzero(np.any(host.barrier_normals != 0, axis=2), axis=1)
    expected = (obstacles > 1) | (neighbours > 2) | (rows > 6)
    assert np.array_equal(compiled.overflow, expected)
    k = min(host.normals.shape[1], compiled.normals.shape[1])
    held = ~expected
    np.testing.assert_allclose(compiled.normals[held, :k], host.normals[held, :k], rtol=0, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), crowded=st.booleans(), rate_aware=st.booleans())
def test_the_compiled_sets_keep_every_barrier_through_the_vehicle_model(seed, crowded, rate_aware):
    """The guarantee of tests/model/test_safety.py, with the sets built by compiled code."""
    problem = safe_problem(seed, crowded=crowded)
    velocity = np.random.default_rng(seed).normal(0, 1.0, (problem.n, 2))
    state = problem.state
    gear = choose_gear(velocity, state.theta, state.gear, problem.limits)
    safe = COMPILED(
        *padded_safe_state(state, problem, gear),
        problem.limits,
        problem.dt,
        problem.safety,
        ROOMY,
        rate_aware,
    )
    assert not np.any(safe.overflow) and np.all(safe.slack == 0)
    padded = np.concatenate((velocity, np.zeros((8 - problem.n, 2))))
    allocated = np.asarray(PROJECT(safe, jnp.asarray(padded)))[: problem.n]
    assert barrier_margin(problem, allocated, problem.safety) >= -1e-12


def test_the_numpy_build_of_fixed_shapes_is_the_host_build_to_the_bit():
    """The same build on numpy arrays: the host's rows, bit for bit, in the capacity's shape."""
    for seed in range(30):
        problem = safe_problem(seed, crowded=True)
        state, params = problem.state, problem.safety
        sets = AchievableSets.for_gear(state, state.gear, problem.limits, rate_aware=True, dt=problem.dt)
        host = SafeSets.build(state, problem.obstacles, problem.limits, problem.dt, sets, params)
        fixed = SafeSets.build(
            state, problem.obstacles, problem.limits, problem.dt, sets, params, capacity=ROOMY
        )
        k = host.normals.shape[1]
        assert np.array_equal(fixed.normals[:, :k], host.normals)
        assert np.array_equal(fixed.offsets[:, :k], host.offsets)
        assert np.array_equal(fixed.slack, host.slack) and np.array_equal(fixed.worst, host.worst)


def test_beyond_all_pairs_the_numpy_build_of_fixed_shapes_is_the_host_build_to_the_bit():
    """60 units on a jittered grid 0.5 m apart among obstacles: the cell list's constraints give
    the host's rows (its k-d tree's), bit for bit, where the capacity holds them."""
    problem = safe_problem(0)
    capacity = Capacity(obstacles=3, neighbours=12, rows=40, cell_units=8)
    for seed in range(5):
        rng = np.random.default_rng(seed)
        grid = 0.5 * np.stack(np.meshgrid(np.arange(10), np.arange(6)), axis=-1).reshape(-1, 2)
        positions = grid + rng.uniform(-0.05, 0.05, grid.shape)
        n = positions.shape[0]
        state = PlatoonState(
            positions[:, 0], positions[:, 1], rng.uniform(-np.pi, np.pi, n), np.zeros(n), np.ones(n)
        )
        obstacles = CircularObstacles([[1.2, 1.3], [3.1, 0.2]], [0.1, 0.1])
        sets = AchievableSets.for_gear(state, state.gear, problem.limits, rate_aware=True, dt=problem.dt)
        host, fixed = (
            SafeSets.build(state, obstacles, problem.limits, problem.dt, sets, problem.safety, capacity=c)
            for c in (None, capacity)
        )
        assert not np.any(fixed.overflow)
        k = host.normals.shape[1]
        assert np.array_equal(fixed.normals[:, :k], host.normals)
        assert np.array_equal(fixed.offsets[:, :k], host.offsets)
        assert np.array_equal(fixed.slack, host.slack) and np.array_equal(fixed.worst, host.worst)
