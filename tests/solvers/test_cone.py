"""The exact speed cone (``cone``, ``cone-projection``): feasibility, optimality against independent solves
(IPOPT; the polygon QPs as the number of sides grows), strict priority, degenerate problems and
the fallback to the polygon."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.errors import OptionError
from platoon_opt.limits import unit_rows
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import backends as qp_backends
from platoon_opt.solvers.convex import formulation as fm
from platoon_opt.solvers.convex.allocator import FEASIBILITY_TOLERANCE, ConvexAllocator
from tests.conftest import LIMITS, degenerate_problems, random_problem, without_dual

seeds = st.integers(0, 2**32 - 1)


def assert_in_cone(problem, allocation, rate_aware=False):
    achievable = allocation.info["achievable"]
    assert np.max(np.hypot(*achievable.T)) <= LIMITS.max_speed + FEASIBILITY_TOLERANCE
    assert np.max(problem.achievable(rate_aware=rate_aware).distance(achievable)) <= FEASIBILITY_TOLERANCE


@settings(max_examples=20)
@given(seeds, st.sampled_from(["cone", "cone-projection"]), st.booleans())
def test_every_achievable_part_is_inside_its_exact_sector(seed, name, rate_aware):
    problem = random_problem(np.random.default_rng(seed), 8)
    allocation = get_allocator(name, rate_aware=rate_aware).allocate(problem)
    assert allocation.status == "optimal" and allocation.info["backend"] == "clarabel"
    assert_in_cone(problem, allocation, rate_aware)
    if name == "cone-projection":
        assert allocation.task_residual <= 1e-7 * (1 + np.linalg.norm(problem.task_velocity))


def ipopt_objective(problem, rho):
    """The achievable-first SOCP solved by IPOPT through casadi.nlpsol (independent of every
    allocator backend), with the disk as the smooth constraint ``|v_i|^2 <= v_max^2``."""
    import casadi

    n = problem.n
    normals, _ = unit_rows(problem.achievable(), "cone", 16, LIMITS.max_speed)
    v = casadi.SX.sym("v", n, 2)
    rows = problem.jacobian.rows
    residual = casadi.vertcat(*(casadi.sum1(casadi.sum2(v * rows[k])) for k in range(rows.shape[0])))
    residual -= problem.task_velocity
    objective = casadi.sumsqr(v - problem.nominal) + rho * casadi.sumsqr(residual)
    steering = [casadi.sum2(v * normals[:, j, :]) for j in range(2)]
    constraints = casadi.vertcat(*steering, casadi.sum2(v**2))
    options = {"print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes", "ipopt.tol": 1e-12}
    solver = casadi.nlpsol("ipopt", "ipopt", {"x": casadi.vec(v), "f": objective, "g": constraints}, options)
    upper = np.concatenate((np.zeros(2 * n), np.full(n, LIMITS.max_speed**2)))
    result = solver(x0=np.zeros(2 * n), lbg=-np.inf, ubg=upper)
    assert solver.stats()["success"]
    return float(result["f"])


@settings(max_examples=8)
@given(seeds, st.sampled_from([1.0, 1e3]))
def test_cone_objective_matches_an_independent_solve(seed, rho):
    problem = dataclasses.replace(
        random_problem(np.random.default_rng(seed), 3), exempt=np.zeros(3, dtype=bool)
    )
    allocation = get_allocator("cone", rho=rho).allocate(problem)
    reference = ipopt_objective(problem, rho)
    assert allocation.info["objective"] <= reference * (1 + 1e-6)
    assert abs(allocation.info["objective"] - reference) <= 1e-6 * reference


@settings(max_examples=8)
@given(seeds, st.sampled_from(["achievable-first", "task-exact"]))
def test_polygon_programs_converge_to_the_cone_from_above(seed, reading):
    """The polygon is inscribed in the disk: its optimum is never below the cone's, and approaches
    it as the number of sides grows (solved by qpOASES, an active-set method)."""
    problem = random_problem(np.random.default_rng(seed), 6)
    cone = get_allocator("cone" if reading == "achievable-first" else "cone-projection").allocate(problem)
    values = []
    for sides in (16, 128, 1024):
        polygon = get_allocator("casadi-qp", reading=reading, sides=sides, fallbacks=()).allocate(problem)
        assert polygon.status == "optimal"
        values.append(polygon.info["objective"])
    exact = cone.info["objective"]
    assert all(value >= exact * (1 - 1e-7) for value in values)
    assert values[0] >= values[1] * (1 - 1e-7) >= values[2] * (1 - 1e-7)
    assert values[2] - exact <= 1e-4 * exact


@pytest.mark.parametrize("case", ["line", "coincident", "zero"])
@pytest.mark.parametrize(
    "name,options", [("cone", {}), ("cone", {"priority": "strict"}), ("cone-projection", {})]
)
def test_degenerate_problems_are_solved(case, name, options):
    problem = degenerate_problems()[case]
    allocator = get_allocator(name, **options)
    allocation = allocator.allocate(problem)
    assert allocation.status == "optimal"
    assert_in_cone(problem, allocation)
    if name == "cone" and not options:
        projected = problem.achievable().project(problem.nominal)
        setup = allocator.setup(problem)
        assert allocation.info["objective"] <= fm.objective(problem, setup, projected, projected) + 1e-9
    if case == "zero":  # at the apex of every cone, which an interior-point method approaches
        np.testing.assert_allclose(allocation.velocities, 0.0, atol=1e-5)


@settings(max_examples=10)
@given(seeds)
def test_strict_cone_keeps_the_stage_one_task_velocity(seed):
    problem = random_problem(np.random.default_rng(seed), 8)
    allocation = get_allocator("cone", priority="strict").allocate(problem)
    assert allocation.status == "optimal"
    target = allocation.info["stage1_task_velocity"]
    scale = 1 + np.linalg.norm(target)
    np.testing.assert_allclose(problem.jacobian.apply(allocation.velocities), target, atol=1e-6 * scale)
    assert_in_cone(problem, allocation)


def test_a_failing_clarabel_falls_back_to_the_polygon_when_there_is_no_dual(monkeypatch):
    def broken(*args, **kwargs):
        raise qp_backends.BackendFailure("MaxIterations")

    monkeypatch.setattr(qp_backends, "_clarabel", broken)
    problem = random_problem(np.random.default_rng(4), 8)
    for name in ("cone", "cone-projection"):
        allocator = without_dual(get_allocator(name))
        allocation = allocator.allocate(problem)
        assert allocation.status == "fallback:clarabel:MaxIterations->osqp(polygon)"
        assert allocation.info["backend"] == "osqp(polygon)" and allocation.fell_back
        assert allocation.program_changed and allocation.info["program"] == "polygon"
        assert_in_cone(problem, allocation)
        sets = problem.achievable()
        normals, offsets = unit_rows(sets, "polygon", 16, LIMITS.max_speed)
        excess = np.einsum("ikj,ij->ik", normals, allocation.info["achievable"]) - offsets
        assert np.max(excess) <= FEASIBILITY_TOLERANCE


def test_strict_stage_two_keeps_the_polygon_of_a_stage_one_fallback(monkeypatch):
    """Clarabel fails stage 1 only: OSQP answers it on the polygon, and stage 2 stays on the
    polygon (on the cone it would serve less of the task than the cone can)."""
    solve = qp_backends._clarabel
    calls = []

    def first_fails(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise qp_backends.BackendFailure("MaxIterations")
        return solve(*args, **kwargs)

    monkeypatch.setattr(qp_backends, "_clarabel", first_fails)
    problem = random_problem(np.random.default_rng(4), 8)
    allocation = without_dual(get_allocator("cone", priority="strict")).allocate(problem)
    assert allocation.info["backend"] == "osqp(polygon)+clarabel(polygon)", allocation.info["backend"]
    assert allocation.program_changed
    normals, offsets = unit_rows(problem.achievable(), "polygon", 16, LIMITS.max_speed)
    excess = np.einsum("ikj,ij->ik", normals, allocation.velocities) - offsets
    assert np.max(excess) <= FEASIBILITY_TOLERANCE


def test_the_cone_needs_clarabel_or_the_dual():
    with pytest.raises(
        OptionError, match="cone: the speed cone needs backend 'clarabel' or 'dual', got 'osqp'"
    ):
        get_allocator("cone", backend="osqp")
    with pytest.raises(ValueError, match="the speed cone needs backend 'clarabel' or 'dual'"):
        ConvexAllocator(speed="cone", backend="osqp")
    assert get_allocator("cone-projection", backend="dual").name == "cone-projection(eps=0.0001, dual)"
