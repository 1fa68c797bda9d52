import dataclasses
import subprocess
import sys

import casadi as ca
import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from platoon_opt import CovarianceTask, MeanVarianceTask, load_scenario, simulate
from platoon_opt.scenarios import SCENARIO_DIR, TASKS
from platoon_opt.solvers.symbolic import SymbolicTask, covariance_task, symbolic_mean_variance_task
from tests.conftest import NominalAllocator

seeds = st.integers(0, 2**32 - 1)
sizes = st.integers(2, 30)
# One instance of each: the compiled Functions are cached per n across examples.
SYMBOLIC_MEAN_VARIANCE = symbolic_mean_variance_task()
COVARIANCE = covariance_task()


def positions_for(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 2.0, (n, 2))


def numeric_jacobian(task, positions: np.ndarray, t: float = 0.0, step: float = 1e-6) -> np.ndarray:
    """Central differences of task.value over q = [x..., y...]: (m, 2n)."""
    n = positions.shape[0]
    q = np.concatenate((positions[:, 0], positions[:, 1]))
    columns = []
    for j in range(2 * n):
        dq = np.zeros(2 * n)
        dq[j] = step
        plus = task.value(np.column_stack(np.split(q + dq, 2)), t)
        minus = task.value(np.column_stack(np.split(q - dq, 2)), t)
        columns.append((plus - minus) / (2 * step))
    return np.column_stack(columns)


@given(seeds, sizes)
@pytest.mark.parametrize(
    ("reference", "symbolic"),
    [(MeanVarianceTask(), SYMBOLIC_MEAN_VARIANCE), (CovarianceTask(), COVARIANCE)],
    ids=["mean_variance", "covariance"],
)
def test_a_symbolic_task_equals_the_hand_written_one(reference, symbolic, seed, n):
    m = len(reference.names)
    # Five rows over 2 n = 4 coordinates: J J^T is singular and its damped directions not unique.
    assume(2 * n > m)
    positions = positions_for(seed, n)
    assert symbolic.names == reference.names
    np.testing.assert_allclose(symbolic.value(positions), reference.value(positions), rtol=1e-12, atol=1e-12)
    expected, got = reference.jacobian(positions), symbolic.jacobian(positions)
    assert got.rows.shape == (m, n, 2)
    np.testing.assert_allclose(got.rows, expected.rows, atol=1e-12)
    np.testing.assert_allclose(got.gram_inverse, expected.gram_inverse, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(symbolic.time_derivative(positions), np.zeros(m))


@given(seeds, st.integers(3, 12))
@pytest.mark.parametrize("task", [COVARIANCE, CovarianceTask()], ids=["symbolic", "hand-written"])
def test_covariance_task_values_and_jacobian_match_finite_differences(task, seed, n):
    positions = positions_for(seed, n)
    (var_x, cov_xy), (_, var_y) = np.cov(positions.T, ddof=1)
    mean_x, mean_y = positions.mean(axis=0)
    np.testing.assert_allclose(task.value(positions), [mean_x, var_x, mean_y, var_y, cov_xy], atol=1e-12)
    dense = task.jacobian(positions).to_dense()
    np.testing.assert_allclose(dense, numeric_jacobian(task, positions), atol=1e-7)


def test_time_explicit_task_and_casadi_function_input():
    # f(q, t): the mean relative to a point moving at (0.5, -0.2) m/s, and a spread growing in t.
    def drifting(x, y, t):
        n = x.numel()
        return ca.vertcat(ca.sum1(x) / n - 0.5 * t, ca.sum1(y) / n + 0.2 * t, ca.sumsqr(x) * ca.sin(t))

    task = SymbolicTask(("ex", "ey", "s"), drifting)
    positions = positions_for(7, 5)
    t, h = 0.7, 1e-6
    numeric = (task.value(positions, t + h) - task.value(positions, t - h)) / (2 * h)
    np.testing.assert_allclose(task.time_derivative(positions, t), numeric, atol=1e-7)
    np.testing.assert_allclose(
        task.jacobian(positions, t).to_dense(), numeric_jacobian(task, positions, t), atol=1e-7
    )
    # The same task handed as a casadi.Function of a fixed n.
    x, y, s = ca.SX.sym("x", 5), ca.SX.sym("y", 5), ca.SX.sym("t")
    function_task = SymbolicTask(("ex", "ey", "s"), ca.Function("f", [x, y, s], [drifting(x, y, s)]))
    np.testing.assert_allclose(function_task.value(positions, t), task.value(positions, t), atol=1e-14)
    np.testing.assert_allclose(function_task.jacobian(positions, t).rows, task.jacobian(positions, t).rows)
    with pytest.raises(ValueError, match="n = 5 units, got n = 6"):
        function_task.value(positions_for(1, 6))


def test_bad_definitions_raise():
    with pytest.raises(ValueError, match="returns 4 components for 2 names"):
        SymbolicTask(("a", "b"), lambda x, y: ca.vertcat(x[0], x[1], y[0], y[1])).value(np.ones((3, 2)))
    with pytest.raises(ValueError, match="distinct"):
        SymbolicTask(("a", "a"), lambda x, y: ca.vertcat(x[0], y[0]))
    with pytest.raises(TypeError, match="callable"):
        SymbolicTask(("a",), 3.0)
    with pytest.raises(ValueError, match=r"shape \(n, 2\)"):
        covariance_task().value(np.ones(4))


def test_compiled_once_per_size_and_linear_in_n():
    task = covariance_task()
    assert task.compiled(10) is task.compiled(10)
    small, large = task.compiled(100).jacobian, task.compiled(1000).jacobian
    # The expression graph grows linearly with n (no n^2 term): 10x the units, ~10x the work.
    assert large.n_instructions() < 11 * small.n_instructions()
    assert large.nnz_out(0) + large.nnz_out(1) <= 5 * 2 * 1000


def test_a_scenario_names_the_symbolic_task_and_runs():
    # paper_covariance with its task built by CasADi instead of by hand (kind "covariance").
    scenario = dataclasses.replace(load_scenario("paper_covariance"), task_kind="symbolic_covariance")
    assert isinstance(scenario.task(), SymbolicTask) and "covariance" in TASKS
    trajectory = simulate(scenario, NominalAllocator(), seed=0, duration=1.5)
    cov_xy, desired = trajectory.component("cov_xy")
    assert cov_xy[0] == pytest.approx(0.0, abs=1e-12)
    # The formation turns toward the commanded orientation (gain 10 /s on cov_xy).
    assert abs(cov_xy[-1] - desired[-1]) < 0.1 * abs(desired[-1])


def test_a_scenario_file_names_the_symbolic_kinds_once_the_allocators_are_imported(tmp_path):
    # The kinds are registered by platoon_opt.solvers (the floor that may use CasADi); the model
    # alone rejects them with a line that says where they live.
    text = (
        (SCENARIO_DIR / "paper_covariance.toml")
        .read_text()
        .replace('kind = "covariance"', 'kind = "symbolic_covariance"')
    )
    path = tmp_path / "symbolic.toml"
    path.write_text(text)
    model_only = f"from platoon_opt.scenarios import load_scenario; load_scenario({str(path)!r})"
    failed = subprocess.run([sys.executable, "-c", model_only], capture_output=True, text=True)
    assert failed.returncode != 0 and "import the allocators' package, solvers, first" in failed.stderr
    assert load_scenario(path).task_kind == "symbolic_covariance"
