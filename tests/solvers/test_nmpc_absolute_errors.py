"""``nmpc``'s task rows reweighed by their errors now (``absolute_errors``, docs/nmpc.md, Eq. 2.10)."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc.residuals import ERROR_SCALE, absolute_error_weights
from tests.conftest import random_problem
from tests.solvers.test_nmpc_gain_weights import SHORT, _task_rows


@settings(max_examples=50, deadline=None)
@given(st.floats(-10, 10))
def test_a_squared_row_costs_its_error_in_proportion_above_the_scale_and_squared_below(error):
    """w^2 e^2 = |e| ERROR_SCALE for |e| >= ERROR_SCALE (the absolute error, in proportion),
    and e^2 (w = 1) below it."""
    (w,) = absolute_error_weights(np.array([error]))
    if abs(error) >= ERROR_SCALE:
        assert math.isclose(w**2 * error**2, abs(error) * ERROR_SCALE, rel_tol=1e-12)
    else:
        assert w == 1.0


def test_each_task_row_is_divided_by_the_root_of_its_scaled_error_now():
    """One plan's task rows with and without the option differ row by row by the factor of
    Eq. 2.10, computed from the problem's errors now in Eq. 2.8's scale, at every sample."""
    problem = random_problem(np.random.default_rng(5), 4)
    reweighed = get_allocator("nmpc", absolute_errors=True, **SHORT)
    allocation = reweighed.allocate(problem)
    assert not allocation.fell_back, allocation.status
    plan, horizon = reweighed._state.plan, reweighed._horizon(problem)
    squared = get_allocator("nmpc", **SHORT)
    on, off = _task_rows(reweighed, problem, plan, horizon), _task_rows(squared, problem, plan, horizon)
    rows = problem.jacobian.rows
    scale = math.sqrt(problem.n) * np.sqrt(np.einsum("kij,kij->k", rows, rows))
    factor = absolute_error_weights((problem.task_value - problem.desired) / scale)
    assert np.any(factor < 1), "the random problem's errors should reach past the scale"
    np.testing.assert_allclose(on, off * factor, rtol=1e-12, atol=0)
