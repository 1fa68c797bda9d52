"""The convex allocators (platoon_opt.solvers.convex: allocator, formulation, backends): feasibility,
optimality (KKT, cross-backend agreement, the limit of the paper's iteration), precedence rule,
gears, strict priority, sparsity, warm start and failure behaviour. The cone variants are in
test_cone.py."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls

from platoon_opt import AllocationProblem
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import backends as qp_backends
from platoon_opt.solvers.convex import formulation as fm
from platoon_opt.solvers.convex.allocator import FEASIBILITY_TOLERANCE
from tests.conftest import (
    LIMITS,
    agree,
    assert_inside,
    build_problem,
    degenerate_problems,
    free_problem,
    random_problem,
)

seeds = st.integers(0, 2**32 - 1)
BACKENDS = ("clarabel", "osqp", "casadi:qpoases")


POLYGON_ALLOCATORS = {
    "qp": {},
    "qp-strict": {"priority": "strict"},
    "qp-osqp": {"backend": "osqp"},
    "qp-projection": {},
    "qp-projection-osqp": {"backend": "osqp"},
    "casadi-qp": {},
    "casadi-qp-projection": {"reading": "task-exact"},
}


def make(label: str):
    name = label.removesuffix("-osqp").removesuffix("-strict")
    if label == "casadi-qp-projection":
        name = "casadi-qp"
    return get_allocator(name, **POLYGON_ALLOCATORS[label])


@settings(max_examples=15)
@given(seeds, st.sampled_from(sorted(POLYGON_ALLOCATORS)), st.booleans())
def test_every_achievable_part_is_inside_its_polygon(seed, label, rate_aware):
    allocator = dataclasses.replace(make(label), rate_aware=rate_aware)
    problem = random_problem(np.random.default_rng(seed), 8)
    allocation = allocator.allocate(problem)
    assert allocation.status == "optimal" and not allocation.fell_back
    assert np.all(np.isfinite(allocation.velocities))
    assert_inside(allocator, problem, allocation)
    if allocator.reading == "achievable-first":
        np.testing.assert_array_equal(allocation.velocities, allocation.info["achievable"])
    else:  # task-exact: J a = u to round-off
        assert allocation.task_residual <= 1e-7 * (1 + np.linalg.norm(problem.task_velocity))


def kkt_residual(program: fm.Program, x: np.ndarray) -> float:
    """Relative stationarity residual of x with nonnegative multipliers on the active rows (an
    independent optimality certificate computed by NNLS from the primal point alone)."""
    gradient = program.P @ x + program.q
    kx = program.K @ x
    K = program.K.toarray()
    # Interior-point solutions leave active rows a slack of up to ~1e-6 (inactive ones here have 0.1).
    active = np.flatnonzero(program.upper[program.n_eq :] - kx[program.n_eq :] <= 1e-5) + program.n_eq
    equality = K[: program.n_eq].T
    basis = np.hstack((equality, -equality, K[active].T))
    _, residual = nnls(basis, -gradient, maxiter=50 * basis.shape[1])
    return residual / (1.0 + np.linalg.norm(gradient))


@settings(max_examples=10)
@given(
    seeds, st.sampled_from(["qp", "qp-projection"]), st.sampled_from(["clarabel", "osqp", "casadi:qpoases"])
)
def test_solutions_meet_the_kkt_conditions(seed, name, backend):
    allocator = get_allocator(name)
    problem = random_problem(np.random.default_rng(seed), 8)
    program = fm.build(problem, allocator.setup(problem))
    x = qp_backends.solve(program, backend, qp_backends.Workspaces(), {}).x
    equality, inside = program.violation(x)
    assert inside <= FEASIBILITY_TOLERANCE and equality <= 1e-7 * (
        1 + np.abs(program.upper[: program.n_eq]).max()
    )
    assert kkt_residual(program, x) <= 1e-6


def objectives(name, problem, **options):
    """The objective of ``name`` under every backend of BACKENDS (strict: both stages)."""
    results = []
    for backend in BACKENDS:
        allocator = get_allocator(name, backend=backend, fallbacks=(), **options)
        allocation = allocator.allocate(problem)
        assert allocation.status == "optimal", (backend, allocation.status)
        stage1 = problem.task_residual(allocation.velocities) ** 2
        results.append((allocation.info["objective"], stage1))
    return [r[0] for r in results], [r[1] for r in results]


@settings(max_examples=12)
@given(seeds, st.sampled_from([{}, {"priority": "strict"}, {"rho": 10.0}]))
def test_backends_agree_on_the_achievable_first_objective(seed, options):
    problem = random_problem(np.random.default_rng(seed), 8)
    values, task = objectives("qp", problem, **options)
    assert agree(values), values
    if options.get("priority") == "strict":
        assert agree(task), task


@settings(max_examples=12)
@given(seeds)
def test_backends_agree_on_the_task_exact_objective(seed):
    problem = random_problem(np.random.default_rng(seed), 8)
    values, _ = objectives("qp-projection", problem)
    assert agree(values), values


@pytest.mark.parametrize("case", ["line", "coincident", "zero"])
@pytest.mark.parametrize("name,options", [("qp", {}), ("qp", {"priority": "strict"}), ("qp-projection", {})])
def test_backends_agree_on_degenerate_problems(case, name, options):
    problem = degenerate_problems()[case]
    values, task = objectives(name, problem, **options)
    assert agree(values), values
    assert agree(task), task
    if case == "zero":
        assert np.allclose(values, 0.0, atol=1e-9)


@settings(max_examples=25)
@given(seeds, st.sampled_from([{}, {"rho": 1.0}, {"rate_aware": True}, {"priority": "strict"}]))
def test_achievable_first_never_loses_to_the_projected_nominal(seed, options):
    """The QP's objective is at most that of the nominal velocity projected per unit (feasible)."""
    allocator = get_allocator("qp", **options)
    problem = random_problem(np.random.default_rng(seed), 8)
    allocation = allocator.allocate(problem)
    setup = allocator.setup(problem)
    projected = setup.precedence  # every unit's nominal velocity projected onto its polygon
    if options.get("priority") == "strict":
        assert problem.task_residual(allocation.velocities) <= problem.task_residual(projected) + 1e-7
    else:
        mine = allocation.info["objective"]
        assert mine <= fm.objective(problem, setup, projected, projected) + 1e-7 * (1 + abs(mine))


def slow_translation() -> AllocationProblem:
    """A platoon translating slowly along its headings: every nominal velocity is achievable."""
    n = 6
    return build_problem(2.0 * np.arange(n), np.arange(n) % 2 * 3.0, 0.0, rate=[0.3, 0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    "name,options",
    [("qp", {}), ("qp", {"priority": "strict"}), ("qp", {"backend": "osqp"}), ("qp-projection", {})]
    + [("casadi-qp", {}), ("cone", {}), ("cone-projection", {})],
)
def test_without_an_active_limit_the_nominal_velocity_is_returned(name, options):
    problem = slow_translation()
    assert np.all(problem.achievable().contains(problem.nominal))
    allocation = get_allocator(name, **options).allocate(problem)
    assert allocation.status == "optimal"
    np.testing.assert_allclose(allocation.velocities, problem.nominal, atol=1e-6)


@settings(max_examples=10)
@given(seeds)
def test_task_exact_qp_is_the_limit_of_the_papers_iteration(seed):
    """With a fixed gear and no flagged unit, the iteration (exact sectors) converges to the
    task-exact program; against the polygon, up to the polygon's inner approximation."""
    problem = free_problem(seed)
    iterated = get_allocator("iterative", max_iterations=300, gears="model").allocate(problem).velocities
    scale = np.max(np.abs(iterated))
    # eps pulls the answer toward q'_d by about 2 eps (relative).
    exact = get_allocator("cone-projection", eps=1e-6).allocate(problem)
    assert exact.status == "optimal"
    assert np.max(np.abs(exact.velocities - iterated)) <= 2e-5 * scale
    default = get_allocator("cone-projection").allocate(problem).velocities
    assert np.max(np.abs(default - iterated)) <= 4e-4 * scale
    polygon = get_allocator("qp-projection", sides=256, eps=1e-6).allocate(problem).velocities
    assert np.max(np.abs(polygon - iterated)) <= 3e-3 * scale


# --- precedence rule -------------------------------------------------------------------------


def flagged_problem(seed: int, count: int = 3) -> tuple[AllocationProblem, np.ndarray]:
    rng = np.random.default_rng(seed)
    problem = random_problem(rng, 8)
    flagged = np.zeros(8, dtype=bool)
    flagged[rng.choice(8, count, replace=False)] = True
    return dataclasses.replace(problem, exempt=flagged), flagged


@settings(max_examples=10)
@given(seeds, st.sampled_from([("qp", {}), ("qp-projection", {"precedence": "pin"}), ("cone", {})]))
def test_pinned_units_keep_their_projected_nominal_velocity(seed, allocator_spec):
    problem, flagged = flagged_problem(seed)
    allocator = get_allocator(allocator_spec[0], **allocator_spec[1])
    allocation = allocator.allocate(problem)
    assert allocation.status == "optimal"
    setup = allocator.setup(problem)
    np.testing.assert_array_equal(allocation.velocities[flagged], setup.precedence[flagged])
    assert np.max(problem.achievable().distance(allocation.velocities)[flagged]) <= 1e-9
    # The free units solve the program with the pinned units' task contribution moved to the
    # right-hand side: check it by KKT on that reduced program.
    program = fm.build(problem, setup)
    assert program.free.tolist() == np.flatnonzero(~flagged).tolist()
    if allocator.speed == "polygon":
        x = qp_backends.solve(program, "casadi:qpoases", qp_backends.Workspaces(), {}).x
        np.testing.assert_allclose(program.unpack(x)[0], allocation.velocities, atol=1e-5)
        assert kkt_residual(program, x) <= 1e-6


@settings(max_examples=6)
@given(seeds)
def test_anchored_units_are_drawn_to_their_avoidance_velocity(seed):
    """Task-exact default: flagged units stay in J a = u, drawn to p_i with anchor_weight; the
    heavier the anchor, the closer to p_i, and the limit is pinning."""
    problem, flagged = flagged_problem(seed)
    setup = get_allocator("qp-projection").setup(problem)
    assert not setup.pinned.any() and np.array_equal(setup.anchored, flagged)
    drift = []
    for weight in (0.1, 1.0, 10.0, 1e3):
        allocation = get_allocator("qp-projection", anchor_weight=weight).allocate(problem)
        assert allocation.status == "optimal"
        assert allocation.task_residual <= 1e-7 * (1 + np.linalg.norm(problem.task_velocity))
        drift.append(np.linalg.norm(allocation.velocities[flagged] - setup.precedence[flagged]))
    assert all(a >= b * (1 - 1e-6) for a, b in zip(drift, drift[1:]))
    pinned = get_allocator("qp-projection", precedence="pin").allocate(problem)
    heavy = get_allocator("qp-projection", anchor_weight=1e3).allocate(problem)
    free = ~flagged
    gap = np.max(np.abs(heavy.velocities[free] - pinned.velocities[free]))
    light = get_allocator("qp-projection", anchor_weight=0.1).allocate(problem)
    assert gap <= np.max(np.abs(light.velocities[free] - pinned.velocities[free]))


def test_all_units_flagged():
    problem = random_problem(np.random.default_rng(2), 8)
    problem = dataclasses.replace(problem, exempt=np.ones(8, dtype=bool))
    for name in ("qp", "cone", "qp-projection"):
        allocator = get_allocator(name)
        allocation = allocator.allocate(problem)
        assert allocation.status == "optimal"
        assert_inside(allocator, problem, allocation)
        if allocator.precedence == "pin":
            assert allocation.info["backend"] == "pinned"
            np.testing.assert_array_equal(allocation.velocities, allocator.setup(problem).precedence)


@pytest.mark.parametrize("options", [{"priority": "strict", "precedence": "anchor"}, {"anchor_weight": 0.0}])
def test_precedence_options_are_checked(options):
    with pytest.raises(ValueError):
        get_allocator("qp", **options)


# --- gears, rate-aware sector, strict priority -------------------------------------------------


@pytest.mark.parametrize(
    "angle,gear_before,gear_after", [(100, 1, 1), (150, 1, -1), (80, -1, -1), (30, -1, 1)]
)
def test_the_sector_follows_the_gear_rule_with_hysteresis(angle, gear_before, gear_after):
    """Unit 0 heads east and its nominal velocity points ``angle`` degrees off: with a 30-degree
    hysteresis a forward unit keeps its gear up to 120 degrees, a backing one up to 60."""
    n = 5
    x, y = 3.0 * np.arange(n), np.zeros(n)
    theta = np.full(n, np.pi / 2)
    theta[0] = 0.0
    gear = np.ones(n)
    gear[0] = gear_before
    problem = build_problem(x, y, theta, gear=gear)
    direction = np.radians(angle)
    nominal = problem.nominal.copy()
    nominal[0] = 0.5 * np.array([np.cos(direction), np.sin(direction)])
    from platoon_opt.vehicle import choose_gear

    problem = dataclasses.replace(
        problem, nominal=nominal, gear=choose_gear(nominal, problem.state.theta, problem.state.gear, LIMITS)
    )
    assert problem.gear[0] == gear_after
    for name in ("qp", "qp-projection", "cone"):
        allocation = get_allocator(name).allocate(problem)
        sets = problem.achievable()
        expected = type(sets).for_gear(problem.state, problem.gear, LIMITS)
        assert expected.contains(allocation.info["achievable"], tol=1e-7)[0]


def test_rate_aware_sector_narrows_to_one_steering_step():
    n = 6
    problem = build_problem(
        2.0 * np.arange(n),
        np.zeros(n),
        np.pi / 2,
        desired=[6.0, 3.5, 0.0, 0.0],
        alpha=np.linspace(-0.5, 0.5, n),
    )
    narrowed = problem.achievable(rate_aware=True)
    assert np.any(narrowed.upper - narrowed.lower < 2 * LIMITS.max_steering - 1e-9)
    for rate_aware in (False, True):
        velocity = get_allocator("qp", rate_aware=rate_aware).allocate(problem).velocities
        inside = narrowed.contains(velocity, tol=1e-7)
        if rate_aware:
            assert np.all(inside)
        else:
            assert not np.all(inside)  # the narrowing is active in this problem


@settings(max_examples=15)
@given(seeds)
def test_strict_priority_keeps_the_stage_one_task_velocity(seed):
    problem = random_problem(np.random.default_rng(seed), 8)
    strict = get_allocator("qp", priority="strict").allocate(problem)
    weighted = get_allocator("qp", rho=1e6).allocate(problem)
    assert strict.status == "optimal"
    target = strict.info["stage1_task_velocity"]
    scale = 1 + np.linalg.norm(target)
    np.testing.assert_allclose(problem.jacobian.apply(strict.velocities), target, atol=1e-6 * scale)
    stage1_deviation = np.sum((strict.info["stage1"] - problem.nominal) ** 2)
    assert strict.info["objective"] <= stage1_deviation * (1 + 1e-9)
    # Stage 1 is the best achievable task velocity: no weighted solution does better.
    assert strict.task_residual <= weighted.task_residual + 1e-6 * scale


def test_strict_priority_picks_the_smallest_deviation_when_the_task_is_achievable():
    problem = slow_translation()
    nominal = problem.nominal.copy()
    nominal[0] += [0.0, 0.4]  # a sideways wish the task does not need
    problem = dataclasses.replace(problem, nominal=nominal)
    strict = get_allocator("qp", priority="strict").allocate(problem)
    assert strict.task_residual <= 1e-6
    # The same point as the task-exact reading (up to its eps, which pulls toward q'_d).
    task_exact = get_allocator("qp-projection").allocate(problem)
    np.testing.assert_allclose(strict.velocities, task_exact.velocities, atol=1e-4)


@pytest.mark.parametrize(
    "name,options,stage",
    [
        ("qp", {}, "joint"),
        ("qp", {"priority": "strict"}, "task"),
        ("qp", {"precedence": "anchor", "anchor_weight": 3.0}, "joint"),
        ("qp-projection", {}, "joint"),
        ("qp-projection", {"precedence": "pin"}, "joint"),
        ("cone-projection", {"anchor_weight": 0.5}, "joint"),
    ],
)
def test_program_objective_is_the_readings_objective(name, options, stage):
    """At any point (anchored units' unused c_i at their interior point), the sparse program's
    objective, which the backends see scaled, equals the reading's objective over all units."""
    problem, _ = flagged_problem(3)
    allocator = get_allocator(name, **options)
    setup = allocator.setup(problem)
    program = fm.build(problem, setup, stage)
    x = np.random.default_rng(0).normal(size=program.variables)
    if allocator.reading == "task-exact":
        held = program.achievable_columns[setup.anchored[program.free]]
        x[held] = setup.interior[program.free][setup.anchored[program.free]]
    else:  # s = J v - u
        velocity = program.unpack(program.scaled(x))[0]
        x[2 * program.free.size :] = problem.jacobian.apply(velocity) - problem.task_velocity
    y = program.scaled(x)
    np.testing.assert_allclose(program.original(y), x, rtol=1e-13, atol=1e-13)
    velocity, achievable = program.unpack(y)
    expected = fm.objective(problem, setup, velocity, achievable, stage)
    assert program.objective(y) == pytest.approx(expected, rel=1e-12)
    assert program.violation(y)[0] <= 1e-12 or allocator.reading == "task-exact"


# --- structure, sparsity, warm start -----------------------------------------------------------
