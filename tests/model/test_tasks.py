import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from platoon_opt import MeanVarianceTask, TaskJacobian

seeds = st.integers(0, 2**32 - 1)
sizes = st.integers(2, 40)


def positions_for(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 2.0, (n, 2))


@given(seeds, sizes)
def test_jacobian_matches_finite_differences(seed, n):
    task = MeanVarianceTask()
    positions = positions_for(seed, n)
    dense = task.jacobian(positions).to_dense()
    q = np.concatenate((positions[:, 0], positions[:, 1]))
    step = 1e-6
    numeric = np.empty_like(dense)
    for j in range(2 * n):
        dq = np.zeros(2 * n)
        dq[j] = step
        plus = task.value(np.column_stack(np.split(q + dq, 2)))
        minus = task.value(np.column_stack(np.split(q - dq, 2)))
        numeric[:, j] = (plus - minus) / (2 * step)
    np.testing.assert_allclose(dense, numeric, atol=1e-7)


@given(seeds, sizes)
def test_gram_is_the_stated_diagonal(seed, n):
    positions = positions_for(seed, n)
    jacobian = MeanVarianceTask().jacobian(positions)
    var = positions.var(axis=0, ddof=1)
    expected = np.diag([1 / n, 4 * var[0] / (n - 1), 1 / n, 4 * var[1] / (n - 1)])
    np.testing.assert_allclose(jacobian.gram, expected, atol=1e-12)
    np.testing.assert_allclose(jacobian.gram, jacobian.to_dense() @ jacobian.to_dense().T, atol=1e-12)


@given(seeds, sizes)
def test_null_space_projection_and_pseudoinverse(seed, n):
    rng = np.random.default_rng(seed)
    positions = positions_for(seed, n)
    jacobian = MeanVarianceTask().jacobian(positions)
    v = rng.normal(size=(n, 2))
    assert np.linalg.norm(jacobian.apply(jacobian.null_project(v))) <= 1e-9 * (1 + np.linalg.norm(v))
    u = rng.normal(size=4)
    np.testing.assert_allclose(jacobian.apply(jacobian.pinv_apply(u)), u, atol=1e-9)
    # J^+ agrees with numpy's dense pseudoinverse.
    dense_pinv = np.linalg.pinv(jacobian.to_dense())
    np.testing.assert_allclose(
        np.concatenate((jacobian.pinv_apply(u)[:, 0], jacobian.pinv_apply(u)[:, 1])),
        dense_pinv @ u,
        atol=1e-9,
    )
    assert jacobian.degenerate == 0


def test_zero_variance_is_damped_and_reported():
    n = 6
    positions = np.column_stack((np.zeros(n), np.linspace(0, 5, n)))  # one vertical line: var_x = 0
    jacobian = MeanVarianceTask().jacobian(positions)
    assert jacobian.degenerate == 1
    velocity = jacobian.pinv_apply(np.array([0.0, 1.0, 0.0, 0.0]))
    assert np.all(np.isfinite(velocity))
    np.testing.assert_allclose(velocity, 0.0)  # the vanished row contributes nothing
    # The other rows are still met exactly.
    u = np.array([0.3, 0.0, -0.2, 0.1])
    np.testing.assert_allclose(jacobian.apply(jacobian.pinv_apply(u)), u, atol=1e-12)


def test_nearly_zero_variance_gives_bounded_velocity():
    n = 5
    positions = np.column_stack((np.linspace(0, 1e-9, n), np.linspace(0, 5, n)))
    jacobian = MeanVarianceTask().jacobian(positions)
    assert jacobian.degenerate == 1
    assert np.abs(jacobian.pinv_apply(np.array([0.0, 1.0, 0.0, 0.0]))).max() < 1e-3


def test_general_jacobian_with_correlated_rows():
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(3, 10, 2))
    jacobian = TaskJacobian.of(rows)
    dense = jacobian.to_dense()
    u = rng.normal(size=3)
    np.testing.assert_allclose(
        np.concatenate((jacobian.pinv_apply(u)[:, 0], jacobian.pinv_apply(u)[:, 1])),
        np.linalg.pinv(dense) @ u,
        atol=1e-10,
    )


@given(st.integers(0, 10_000), st.integers(2, 40))
def test_closed_form_gram_equals_the_eigendecomposition(seed, n):
    rng = np.random.default_rng(seed)
    positions = rng.normal(size=(n, 2)) * rng.uniform(1e-4, 10)
    if seed % 3 == 0:
        positions[:, 0] = positions[0, 0]  # a vanishing variance row: damped on both paths
    hinted = MeanVarianceTask().jacobian(positions)
    generic = TaskJacobian.of(hinted.rows)
    np.testing.assert_allclose(hinted.gram_inverse, generic.gram_inverse, rtol=1e-9, atol=1e-12)
    assert hinted.degenerate == generic.degenerate
