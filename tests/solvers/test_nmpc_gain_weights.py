"""``nmpc``'s task rows weighed by the tracking gains (``gain_weights``, docs/nmpc.md, Eq. 2.9)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import solve_continuous_are

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc.residuals import gain_weights
from platoon_opt.solvers.nmpc.solve import _to_columns
from tests.conftest import random_problem

SHORT = {"intervals": 3, "resolve_every": 3}


def test_the_weights_are_the_gains_over_the_smallest_positive_gain():
    np.testing.assert_array_equal(gain_weights(np.array([50.0, 10, 50, 10])), [5, 1, 5, 1])
    np.testing.assert_array_equal(gain_weights(np.diag([50.0, 10, 20, 10, 10])), [5, 1, 2, 1, 1])
    # A gain of 0 (an error the law leaves alone) weighs 0; no positive gain leaves every row at 1.
    np.testing.assert_array_equal(gain_weights(np.array([0.0, 4, 8, 4])), [0, 1, 2, 1])
    np.testing.assert_array_equal(gain_weights(np.zeros(4)), [1, 1, 1, 1])


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(0.1, 100), min_size=1, max_size=5))
def test_the_tracking_law_is_the_optimal_response_to_the_weighted_errors(gains):
    """For e' = w (a task error moved at the rate w chosen), the cost integral of
    sum_r (K_r e_r)^2 + |w|^2 has the optimal feedback w = -K e: the tracking law's own response.
    The Riccati solution P of A = 0, B = I, Q = diag(K)^2, R = I gives the gain R^-1 B^T P."""
    K = np.diag(gains)
    identity = np.identity(len(gains))
    P = solve_continuous_are(0 * identity, identity, K @ K, identity)
    np.testing.assert_allclose(P, K, rtol=1e-8, atol=1e-10)


def _task_rows(allocator, problem, plan, horizon):
    """The task rows (samples, m) of ``plan`` under ``allocator``'s parameters."""
    p = allocator._parameters(problem, horizon, plan.inputs[0, :, 0])
    (residual,) = horizon.residual(_to_columns(plan.states), _to_columns(plan.inputs), p)
    m, samples = problem.task_value.size, SHORT["intervals"] * SHORT["resolve_every"]
    return residual[: samples * m].reshape(samples, m)


def test_the_gain_weights_multiply_each_task_row_by_its_gain_over_the_smallest():
    """One plan's task rows with and without the gain weights differ by K_r / min K, row by row
    at every sample; and the default plans as the explicit weights K / min K do."""
    problem = random_problem(np.random.default_rng(5), 4)
    weighted = get_allocator("nmpc", **SHORT)
    allocation = weighted.allocate(problem)
    assert not allocation.fell_back, allocation.status
    plan, horizon = weighted._state.plan, weighted._horizon(problem)
    alike = get_allocator("nmpc", gain_weights=False, **SHORT)
    on, off = _task_rows(weighted, problem, plan, horizon), _task_rows(alike, problem, plan, horizon)
    np.testing.assert_allclose(on, off * np.array([5, 1, 5, 1]), rtol=1e-12, atol=0)
    assert np.all(off != 0)
    explicit = get_allocator("nmpc", gain_weights=False, task_weights=(5, 1, 5, 1), **SHORT)
    np.testing.assert_array_equal(explicit.allocate(problem).velocities, allocation.velocities)


@pytest.mark.parametrize("gains", [(50.0, 10, 50, 10), (10.0, 10, 10, 10)])
def test_equal_gains_weigh_the_rows_alike(gains):
    problem = random_problem(np.random.default_rng(7), 3)
    problem = type(problem).build(
        problem.state,
        problem.task,
        problem.desired,
        problem.desired_rate,
        np.array(gains),
        problem.limits,
        problem.dt,
    )
    on = get_allocator("nmpc", **SHORT).allocate(problem)
    off = get_allocator("nmpc", gain_weights=False, **SHORT).allocate(problem)
    same = np.array_equal(on.velocities, off.velocities)
    assert same == (gains[0] == gains[1])
