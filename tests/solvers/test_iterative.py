import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from platoon_opt import AllocationProblem, CircularObstacles, MeanVarianceTask, PlatoonState, VehicleLimits
from platoon_opt.solvers import available_allocators, get_allocator
from tests.conftest import random_problem

seeds = st.integers(0, 2**32 - 1)


@given(seeds)
def test_zero_iterations_is_eq5(seed):
    problem = random_problem(np.random.default_rng(seed), 8)
    allocation = get_allocator("iterative", max_iterations=0).allocate(problem)
    jacobian = problem.jacobian
    eq5 = jacobian.pinv_apply(problem.task_velocity) + jacobian.null_project(problem.secondary)
    np.testing.assert_allclose(allocation.velocities, eq5, atol=1e-12)
    assert allocation.status == "nominal" and allocation.iterations == 0


@given(seeds, st.integers(1, 8))
def test_corrections_keep_the_task_velocity(seed, m):
    problem = random_problem(np.random.default_rng(seed), 8)
    allocation = get_allocator("iterative", max_iterations=m).allocate(problem)
    scale = 1 + np.linalg.norm(problem.task_velocity)
    assert allocation.task_residual <= 1e-9 * scale
    assert problem.task_residual(problem.nominal) <= 1e-9 * scale


def test_without_an_active_limit_every_m_gives_the_same_velocities():
    # A platoon translating slowly along its headings: every desired velocity is achievable.
    n = 6
    state = PlatoonState(2.0 * np.arange(n), np.arange(n) % 2 * 3.0, np.zeros(n), np.zeros(n))
    task = MeanVarianceTask()
    value = task.value(state.positions)
    problem = AllocationProblem.build(
        state,
        task,
        value,
        np.array([0.3, 0.0, 0.0, 0.0]),
        np.array([50.0, 10, 50, 10]),
        VehicleLimits(),
        0.01,
    )
    results = [get_allocator("iterative", max_iterations=m).allocate(problem) for m in range(9)]
    for result in results:
        np.testing.assert_allclose(result.velocities, results[0].velocities, atol=1e-12)
    assert results[4].status == "converged" and results[4].iterations == 0


@given(seeds)
def test_a_sweep_is_an_alternating_projection(seed):
    """One sweep maps a to P_A(P_C(a)) on the units not under the precedence rule."""
    problem = random_problem(np.random.default_rng(seed), 8)
    one = get_allocator("iterative", max_iterations=1).allocate(problem).velocities
    jacobian = problem.jacobian
    from platoon_opt.limits import project_either_gear

    a = problem.nominal
    c = np.where(problem.exempt[:, None], a, project_either_gear(a, problem.state, problem.limits))
    expected = jacobian.pinv_apply(problem.task_velocity) + jacobian.null_project(c)
    np.testing.assert_allclose(one, expected, atol=1e-10)


def test_exempt_units_receive_no_correction():
    rng = np.random.default_rng(1)
    problem = random_problem(rng, 8)
    object.__setattr__(problem, "exempt", np.ones(8, dtype=bool))
    allocation = get_allocator("iterative", max_iterations=5).allocate(problem)
    np.testing.assert_allclose(allocation.velocities, problem.nominal, atol=1e-12)


def test_more_iterations_bring_velocities_closer_to_achievable():
    rng = np.random.default_rng(7)
    gaps = []
    for m in (0, 1, 4, 16):
        problem = random_problem(np.random.default_rng(7), 8)
        velocities = get_allocator("iterative", max_iterations=m, gears="model").allocate(problem).velocities
        gaps.append(np.linalg.norm(problem.achievable().distance(velocities)))
    assert gaps == sorted(gaps, reverse=True) and gaps[-1] < gaps[0]
    del rng


def test_registry_errors():
    assert "iterative" in available_allocators()
    with pytest.raises(ValueError, match="unknown allocator 'nope'"):
        get_allocator("nope")
    with pytest.raises(ValueError, match="max_iterations"):
        get_allocator("iterative", max_iterations=-1)


def test_large_platoon_allocation_step_is_o_n():
    """n = 20,000 units, m = 4: anything 2n x 2n would need 12.8 GB."""
    problem = random_problem(np.random.default_rng(0), 20_000)
    allocation = get_allocator("iterative", max_iterations=4).allocate(problem)
    assert allocation.velocities.shape == (20_000, 2)
    assert np.all(np.isfinite(allocation.velocities))


@pytest.fixture(scope="module")
def compiled_sweeps():
    """The iteration's kernel compiled, as the engine runs it (m and the problem traced)."""
    import jax

    from platoon_opt.solvers.iterative import sweeps

    return jax.jit(sweeps, static_argnames=("gears",))


@given(seeds, st.integers(0, 8), st.sampled_from(["either", "model"]))
def test_the_compiled_kernel_answers_as_the_host(compiled_sweeps, seed, m, gears):
    # One shape (8 units, 2 obstacles), so that the kernel compiles once per gears.
    rng = np.random.default_rng(seed)
    obstacles = CircularObstacles(rng.uniform(-3, 3, (2, 2)), rng.uniform(0.2, 1.0, 2))
    problem = random_problem(rng, 8, obstacles=obstacles)
    host = get_allocator("iterative", max_iterations=m, gears=gears).allocate(problem)
    velocities, _, info = compiled_sweeps(gears, m, problem, ())
    np.testing.assert_allclose(np.asarray(velocities), host.velocities, rtol=1e-9, atol=1e-12)
    assert int(info.iterations) == host.iterations
