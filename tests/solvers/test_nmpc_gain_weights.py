"""``nmpc``'s task rows weighed by the tracking gains (``gain_weights``, docs/nmpc.md, Eq. 2.9)."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import solve_continuous_are

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc.residuals import faded, gain_weights, saturation
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


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.one_of(st.just(0.0), st.floats(1, 100)), min_size=1, max_size=6),
    st.floats(1, 1e6),
)
def test_faded_weights_lie_between_the_gains_and_equal_rows(weights, s):
    """Eq. 2.9': the gains' weights at s = 1, every positive weight between its gain weight and
    1 and in the same order, a zero weight 0."""
    w = np.array(weights)
    np.testing.assert_array_equal(faded(w, 1.0), w)
    fade = faded(w, s)
    positive = w > 0
    assert np.all(fade[~positive] == 0)
    assert np.all((fade[positive] >= 1 - 1e-12) & (fade[positive] <= w[positive] + 1e-12))
    order = np.argsort(w[positive], kind="stable")
    assert np.all(np.diff(fade[positive][order]) >= -1e-12)
    np.testing.assert_allclose(fade[positive] - 1, (w[positive] - 1) / s, rtol=1e-12, atol=1e-12)


def _catching_up_at(problem, speed):
    """``problem`` with the mean rows' feedback K_mu (f_d,mu - mu) of ``speed`` (m/s), the target
    moved; the variance rows' feedback and every unit's nominal velocity as they were."""
    feedback = problem.task_velocity - problem.desired_rate
    scale = speed / float(np.hypot(feedback[0], feedback[2]))
    feedback[[0, 2]] *= scale
    desired = problem.desired.copy()
    desired[[0, 2]] = problem.task_value[[0, 2]] + feedback[[0, 2]] / problem.gains[[0, 2]]
    return dataclasses.replace(problem, desired=desired, task_velocity=problem.desired_rate + feedback)


def test_the_saturation_is_the_feedback_speed_over_the_top_speed_at_least_one():
    """s of Eq. 2.9' is the mean's catching up alone: the nominal speeds do not enter it."""
    problem = random_problem(np.random.default_rng(5), 4)
    top = problem.limits.max_speed
    assert saturation(_catching_up_at(problem, 0.5 * top)) == 1.0
    assert saturation(_catching_up_at(problem, 7.0 * top)) == pytest.approx(7.0, rel=1e-12)
    fast = dataclasses.replace(problem, nominal=problem.nominal * 1e3)
    assert saturation(fast) == saturation(problem)


@pytest.mark.parametrize("speed_over_top", [0.5, 7.0])
def test_the_faded_gains_multiply_each_task_row_by_the_faded_weight(speed_over_top):
    """One plan's task rows with ``fade_gains`` are the rows alike times 1 + (K_r / min K - 1) / s,
    row by row at every sample; within reach (s = 1) the allocation is the default's, bit for bit."""
    base = random_problem(np.random.default_rng(5), 4)
    problem = _catching_up_at(base, speed_over_top * base.limits.max_speed)
    fading = get_allocator("nmpc", fade_gains=True, **SHORT)
    allocation = fading.allocate(problem)
    assert not allocation.fell_back, allocation.status
    plan, horizon = fading._state.plan, fading._horizon(problem)
    alike = get_allocator("nmpc", gain_weights=False, **SHORT)
    on, off = _task_rows(fading, problem, plan, horizon), _task_rows(alike, problem, plan, horizon)
    s = max(1.0, speed_over_top)
    expected = 1 + (np.array([5.0, 1, 5, 1]) - 1) / s
    np.testing.assert_allclose(on, off * expected, rtol=1e-12, atol=0)
    default = get_allocator("nmpc", **SHORT).allocate(problem)
    assert np.array_equal(default.velocities, allocation.velocities) == (s == 1.0)
