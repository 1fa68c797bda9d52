"""The SQP's clearance rows (platoon_opt/solvers/nmpc/clearance.py): the rows of the pairs that
can meet within the horizon, evaluated outside the CasADi model (docs/nmpc.md, Eq. 2.7 and
section 9)."""

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.solvers import get_allocator
from platoon_opt.vehicle import VehicleLimits
from tests.conftest import random_problem

SMALL = {"intervals": 4, "resolve_every": 2}


def test_the_pair_rows_and_their_derivatives_are_the_models():
    """With every pair in reach, the task rows of the SQP's model and its pair rows equal the
    coupling rows of the model that holds all pairs (IPOPT's), whose derivatives CasADi takes:
    residuals, derivatives chained through G, and the cost. Units crowd within 0.5 m, so that
    pair rows are live."""
    rng = np.random.default_rng(3)
    n, N = 6, SMALL["intervals"]
    problem = random_problem(rng, n)
    sqp = get_allocator("nmpc", **SMALL)
    full = get_allocator("nmpc", backend="ipopt", **SMALL)
    in_sqp, in_full = sqp._horizon(problem), full._horizon(problem)
    assert in_sqp.clearance is not None and in_full.clearance is None
    Z, U = rng.uniform(-0.25, 0.25, (4, N * n)), rng.uniform(-0.5, 0.5, (2, N * n))
    p = sqp._parameters(problem, in_sqp, np.zeros(n))
    G = np.tril(np.ones((N, N)))[:, :, None, None, None] * rng.normal(size=(N, N, n, 4, 2))
    pairs = in_sqp.clearance.near(np.zeros((n, 2)), 1.0)
    np.testing.assert_array_equal(pairs.pairs, list(itertools.combinations(range(n), 2)))
    states = Z.T.reshape(N, n, 4)

    expected = in_full.chain(*in_full.residual_jacobian(Z, U, p), G)
    got = in_sqp.chain(*in_sqp.residual_jacobian(Z, U, p), G).with_coupling(*pairs.linearization(states, G))
    task_rows = in_sqp.chain(*in_sqp.residual_jacobian(Z, U, p), G).coupled_residual.size
    assert expected.coupled_residual.size > task_rows
    # Two CasADi models: the same rows, rounded alike or within a few ulps.
    np.testing.assert_array_equal(got.own_unit, expected.own_unit)
    np.testing.assert_allclose(got.own_residual, expected.own_residual, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(got.own, expected.own, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(got.coupled_residual, expected.coupled_residual, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(got.coupling, expected.coupling, rtol=1e-12, atol=1e-10)
    (everything,) = in_full.residual(Z, U, p)
    (without,) = in_sqp.residual(Z, U, p)
    rows = pairs.residual(states)
    np.testing.assert_allclose(without @ without + rows @ rows, everything @ everything, rtol=1e-13)


_N_UNITS = 12


def _node_states(horizon, start, U):
    """The node states (N, n, 4) of the horizon's kinematics from ``start`` (n, 4) under U (N, n, 2)."""
    N, n = U.shape[:2]
    (states,) = horizon.rollout(start.T, U.reshape(N * n, 2).T)
    return states.reshape(4, -1, order="F").T.reshape(N, n, 4)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.floats(0.2, 6.0), speed_fraction=st.floats(0.0, 1.0))
def test_the_pairs_near_are_the_pairs_within_the_reach(seed, spread, speed_fraction):
    """``near`` holds exactly the pairs closer now than unit_clearance + 2 v N h, in order."""
    rng = np.random.default_rng(seed)
    clearance = get_allocator("nmpc")._horizon(random_problem(rng, _N_UNITS)).clearance
    positions = rng.uniform(-spread, spread, (_N_UNITS, 2))
    speed = speed_fraction * VehicleLimits().max_speed
    reach = clearance.distance + 2 * speed * clearance.duration
    within = [
        (i, j)
        for i, j in itertools.combinations(range(_N_UNITS), 2)
        if np.hypot(*(positions[i] - positions[j])) <= reach
    ]
    got = clearance.near(positions, speed).pairs
    np.testing.assert_array_equal(got.reshape(-1, 2), np.array(within, dtype=int).reshape(-1, 2))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    gaps=st.lists(st.floats(0.5, 1.5), min_size=_N_UNITS // 2, max_size=_N_UNITS // 2),
    aim=st.booleans(),
)
def test_no_pair_left_out_comes_within_the_clearance(seed, gaps, aim):
    """Six pairs of units 10 m apart from the others, each pair ``gaps`` times the reach apart,
    driven at the speed bound through the horizon's exact kinematics (the units' own,
    docs/nmpc.md Eq. 1.6), straight at each other (closing at twice the bound) or at random: no
    pair outside ``Clearance.near`` comes closer than ``unit_clearance`` at a node."""
    rng = np.random.default_rng(seed)
    n, limits = _N_UNITS, VehicleLimits()
    horizon = get_allocator("nmpc")._horizon(random_problem(rng, n))
    clearance, N, speed = horizon.clearance, horizon.N, limits.max_speed
    reach = clearance.distance + 2 * speed * clearance.duration
    direction = rng.uniform(-np.pi, np.pi, n // 2)
    half = 0.5 * reach * np.array(gaps)[:, None] * np.column_stack((np.cos(direction), np.sin(direction)))
    centres = np.column_stack((10.0 * np.arange(n // 2), np.zeros(n // 2)))
    positions = np.stack((centres - half, centres + half), axis=1).reshape(n, 2)
    facing = np.stack((direction, direction + np.pi), axis=1).reshape(n)
    start = np.column_stack((positions, facing, np.zeros(n)))
    U = np.zeros((N, n, 2))
    U[:, :, 0] = speed
    if not aim:
        start[:, 2:] = np.column_stack(
            (rng.uniform(-np.pi, np.pi, n), rng.uniform(-limits.max_steering, limits.max_steering, n))
        )
        U[:, :, 0] *= rng.choice([-1.0, 1.0], (N, n))
        U[:, :, 1] = rng.uniform(-limits.max_steering, limits.max_steering, (N, n))
    pairs = clearance.near(positions, speed)
    states = _node_states(horizon, start, U)
    every = type(pairs)(
        clearance.distance, clearance.scale, np.array(list(itertools.combinations(range(n), 2)))
    )
    live = every.pairs[np.any(every.residual(states).reshape(N, -1) > 0, axis=0)]
    assert {tuple(pair) for pair in live} <= {tuple(pair) for pair in pairs.pairs}


def test_the_reach_is_tight_for_two_units_driving_at_each_other():
    """Two units facing each other, driving straight at each other at the speed bound, end the
    horizon exactly ``reach - 2 v_max N h`` apart: at just beyond the reach they stay out of the
    clearance, just within it they come inside."""
    problem = random_problem(np.random.default_rng(1), 2)
    horizon = get_allocator("nmpc")._horizon(problem)
    clearance, N, speed = horizon.clearance, horizon.N, VehicleLimits().max_speed
    reach = clearance.distance + 2 * speed * clearance.duration
    U = np.zeros((N, 2, 2))
    U[:, :, 0] = speed
    for factor, meets in ((1 + 1e-9, False), (1 - 1e-3, True)):
        start = np.array([[0.0, 0.0, 0.0, 0.0], [factor * reach, 0.0, np.pi, 0.0]])
        pairs = clearance.near(start[:, :2], speed)
        assert len(pairs.pairs) == meets
        closest = np.hypot(
            *(_node_states(horizon, start, U)[-1, 0, :2] - _node_states(horizon, start, U)[-1, 1, :2])
        )
        assert (closest < clearance.distance) == meets
        np.testing.assert_allclose(closest, factor * reach - 2 * speed * clearance.duration, rtol=1e-12)
