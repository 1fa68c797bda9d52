"""The convex allocators' programs and backends: sparsity patterns fixed per structure, OSQP's
workspace and warm start, the qpsolvers path, and what happens when a backend fails (the next
backend, then the projected nominal velocity, with a status that says so); their names."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import qpsolvers
import scipy.sparse as sp

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import backends as qp_backends
from platoon_opt.solvers.convex import formulation as fm
from tests.conftest import agree, assert_inside, free_problem, random_problem, without_dual


@pytest.mark.parametrize("name", ["qp", "qp-projection", "cone"])
def test_programs_are_sparse_with_a_pattern_fixed_per_structure(name):
    allocator = get_allocator(name)
    n = 400
    first, second = (free_problem(seed, n) for seed in (0, 1))
    programs = [fm.build(p, allocator.setup(p)) for p in (first, second)]
    for program in programs:
        assert sp.issparse(program.P) and sp.issparse(program.K)
        assert program.P.nnz <= 8 * n and program.K.nnz <= 40 * n  # O(n m), never (2n)^2
    assert programs[0].key == programs[1].key
    for attribute in ("P", "P_upper", "K"):
        a, b = getattr(programs[0], attribute), getattr(programs[1], attribute)
        np.testing.assert_array_equal(a.indptr, b.indptr)
        np.testing.assert_array_equal(a.indices, b.indices)


def test_osqp_workspace_is_reused_and_warm_started():
    allocator = get_allocator("qp", backend="osqp")
    problem = free_problem(4)
    cold = allocator.allocate(problem)
    warm = allocator.allocate(problem)  # same structure: update + start from the last solution
    assert len(allocator._workspaces._entries) == 1
    assert warm.iterations < cold.iterations
    np.testing.assert_allclose(warm.velocities, cold.velocities, atol=1e-7)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_qpsolvers_path_matches_the_native_backends(seed):
    """At the settings the allocator gives them (qpsolvers' OSQP at its own defaults broke the
    limits by up to 6e-4 m/s and was refused)."""
    problem = random_problem(np.random.default_rng(seed), 8)
    for name in ("qp", "qp-projection"):
        native = get_allocator(name).allocate(problem).info["objective"]
        for backend in ("qpsolvers:clarabel", "qpsolvers:osqp"):
            allocation = get_allocator(name, backend=backend, fallbacks=()).allocate(problem)
            assert allocation.status == "optimal", allocation.status
            assert agree([native, allocation.info["objective"]])


# --- failure behaviour -------------------------------------------------------------------------


def test_iteration_cap_falls_back_to_the_next_backend():
    problem = random_problem(np.random.default_rng(0), 8)
    allocation = get_allocator("qp", backend="osqp", solver_options={"max_iter": 5}).allocate(problem)
    assert allocation.fell_back
    assert allocation.status.startswith(
        "fallback:osqp:maximum iterations reached"
    ) and allocation.status.endswith("->clarabel")
    assert allocation.info["backend"] == "clarabel" and np.all(np.isfinite(allocation.velocities))
    reference = get_allocator("qp").allocate(problem)
    np.testing.assert_allclose(allocation.velocities, reference.velocities, atol=1e-6)


@pytest.mark.parametrize("failure", ["none", "raise", "nan", "not-found"])
def test_a_failing_backend_falls_back_and_the_status_says_so(monkeypatch, failure):
    def broken(problem, solver, initvals=None, **options):
        if failure == "raise":
            raise RuntimeError("boom")
        if failure == "none":
            return None
        solution = qpsolvers.Solution(problem)
        solution.found = failure == "nan"
        solution.x = np.full(problem.P.shape[0], np.nan)
        return solution

    monkeypatch.setattr(qpsolvers, "solve_problem", broken)
    problem = random_problem(np.random.default_rng(1), 8)
    allocation = get_allocator("qp-projection", backend="qpsolvers:clarabel").allocate(problem)
    reason = {"none": "no solution found", "raise": "RuntimeError", "nan": "non-finite solution"}
    reason["not-found"] = reason["none"]
    assert allocation.status == f"fallback:qpsolvers:clarabel:{reason[failure]}->osqp"
    assert allocation.fell_back and np.all(np.isfinite(allocation.velocities))


def test_when_every_backend_fails_the_projected_nominal_is_used(monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(qp_backends, "_clarabel", broken)
    monkeypatch.setattr(qp_backends, "_osqp", broken)
    problem = random_problem(np.random.default_rng(6), 8)
    for name, options in (("qp", {}), ("qp", {"priority": "strict"}), ("qp-projection", {})):
        allocator = without_dual(get_allocator(name, **options))
        allocation = allocator.allocate(problem)
        assert allocation.status.endswith("->projection") and allocation.fell_back
        assert allocation.program_changed and allocation.info["program"] == "projection"
        assert "clarabel" in allocation.status and "osqp" in allocation.status
        assert allocation.status.count("RuntimeError") == 2
        assert allocation.info["backend"] == "projection"
        assert np.all(np.isfinite(allocation.velocities))
        assert_inside(allocator, problem, allocation)


def test_strict_stage_two_failure_keeps_the_stage_one_solution(monkeypatch):
    real = qp_backends.solve

    def stage_two_fails(program, backend, workspaces, options):
        if program.key[2] == "deviation":
            raise qp_backends.BackendFailure("stuck")
        return real(program, backend, workspaces, options)

    import platoon_opt.solvers.convex.allocator as qp_module

    monkeypatch.setattr(qp_module, "solve", stage_two_fails)
    problem = random_problem(np.random.default_rng(8), 8)
    allocation = without_dual(get_allocator("qp", priority="strict")).allocate(problem)
    assert allocation.status == "fallback:clarabel[deviation]:stuck; osqp[deviation]:stuck->stage1"
    assert allocation.program_changed and allocation.info["program"] == "stage 1"
    # With the dual, the strict program is answered whole.
    exact = get_allocator("qp", priority="strict").allocate(problem)
    assert exact.status.endswith("->dual") and not exact.program_changed
    np.testing.assert_allclose(
        problem.jacobian.apply(allocation.velocities), allocation.info["stage1_task_velocity"], atol=1e-12
    )


# --- options -----------------------------------------------------------------------------------


def test_names_show_the_main_options():
    assert get_allocator("qp").name == "qp(rho=1000, clarabel)"
    assert get_allocator("qp", priority="strict", backend="osqp").name == "qp(strict, osqp)"
    assert get_allocator("qp-projection", sides=32, rate_aware=True).name == (
        "qp-projection(eps=0.0001, clarabel, sides=32, rate-aware)"
    )
    assert get_allocator("casadi-qp", reading="task-exact").name == "casadi-qp(eps=0.0001, casadi:qpoases)"


@pytest.mark.parametrize(
    "name,options",
    [
        ("qp", {"rho": 0.0}),
        ("qp", {"rho": float("nan")}),
        ("qp", {"backend": "nope"}),
        ("qp", {"priority": "first"}),
        ("qp", {"sides": 2}),
        ("qp", {"fallbacks": ("osqp", "nope")}),
        ("qp-projection", {"eps": -1.0}),
        ("casadi-qp", {"reading": "task-exact", "priority": "strict"}),
        ("casadi-qp", {"plugin": "cplex"}),
    ],
)
def test_bad_options_are_rejected(name, options):
    with pytest.raises(ValueError):
        get_allocator(name, **options)


@pytest.mark.parametrize("backend", ["osqp", "qpsolvers:osqp"])
def test_solving_with_osqp_warns_nothing(backend):
    """OSQP's solve() warns PendingDeprecationWarning unless raise_error is passed: both paths
    pass it (a warning here is an error, raised through ``solve``)."""
    problem = random_problem(np.random.default_rng(2), 4)
    program = get_allocator("qp").program(problem)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solved = qp_backends.solve(program, backend, qp_backends.Workspaces(), {})
    assert np.all(np.isfinite(solved.x))
