"""The dual allocator: projections, the dual's derivatives, and exactness against Clarabel and OSQP."""

from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from platoon_opt import (
    AllocationProblem,
    MeanVarianceTask,
    PlatoonState,
    VehicleLimits,
    load_scenario,
    simulate,
)
from platoon_opt.limits import AchievableSets
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import formulation
from platoon_opt.solvers.dual import allocator as dual
from platoon_opt.solvers.dual.sets import PolygonSets, SectorSets, make_sets
from platoon_opt.solvers.programs import READINGS, SPEED_MODELS, STRICT_BAND
from platoon_opt.study import problems as family
from platoon_opt.tasks import TaskJacobian
from tests.conftest import random_problem, random_state

# The QP allocators that pose the same problem: (reading, speed) -> name.
REFERENCES = {
    ("achievable-first", "polygon"): "qp",
    ("achievable-first", "cone"): "cone",
    ("task-exact", "polygon"): "qp-projection",
    ("task-exact", "cone"): "cone-projection",
}
CASES = list(REFERENCES)
# The bar for the objective against an independent solver.
RELATIVE_GAP = 1e-7


def spread_problem(rng: np.random.Generator, n: int, exempt_share: float = 0.1) -> AllocationProblem:
    """A random problem with units at a density that leaves most of them free, and about
    ``exempt_share`` of them under the precedence rule."""
    state = random_state(rng, n, spread=2.0 * np.sqrt(n))
    task = MeanVarianceTask()
    value = task.value(state.positions)
    problem = AllocationProblem.build(
        state,
        task,
        value + rng.normal(0, 0.5, 4) * np.array([1, 0.3 * n, 1, 0.3 * n]),
        rng.normal(0, 0.5, 4),
        np.array([50.0, 10, 50, 10]),
        VehicleLimits(),
        0.01,
    )
    return dataclasses.replace(problem, exempt=rng.random(n) < exempt_share)


def reference(problem: AllocationProblem, reading: str, speed: str, backend: str = "clarabel", **options):
    """The QP allocators' answer (Clarabel, or OSQP for the polygon)."""
    name = REFERENCES[(reading, speed)]
    if speed == "polygon":
        options["backend"] = backend
    allocation = get_allocator(name, **options).allocate(problem)
    assert allocation.status == "optimal", allocation.status
    return allocation


def assert_same_objective(ours, theirs) -> None:
    mine, ref = ours.info["objective"], theirs.info["objective"]
    assert abs(mine - ref) <= RELATIVE_GAP * max(abs(ref), 1e-9), (mine, ref)


def brute_polygon_projection(w: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Projection onto {v : normals v <= offsets} by enumeration: w itself, the feet on every
    edge line and every pairwise intersection; the nearest feasible candidate wins."""
    n, k = offsets.shape
    candidates = [w]
    for j in range(k):
        normal = normals[:, j]
        length2 = np.sum(normal**2, axis=1)
        safe = np.where(length2 > 0, length2, 1.0)
        excess = (np.einsum("ij,ij->i", w, normal) - offsets[:, j]) / safe
        candidates.append(w - np.where(length2 > 0, excess, 0.0)[:, None] * normal)
    for j, other in itertools.combinations(range(k), 2):
        matrix = np.stack((normals[:, j], normals[:, other]), axis=1)
        regular = np.abs(np.linalg.det(matrix)) > 1e-12
        matrix[~regular] = np.eye(2)
        corner = np.linalg.solve(matrix, np.stack((offsets[:, j], offsets[:, other]), axis=1)[..., None])[
            ..., 0
        ]
        corner[~regular] = np.nan
        candidates.append(corner)
    best, chosen = np.full(n, np.inf), np.zeros_like(w)
    for candidate in candidates:
        feasible = np.max(np.einsum("ikj,ij->ik", normals, candidate) - offsets, axis=1) <= 1e-9
        distance = np.where(feasible, np.sum((candidate - w) ** 2, axis=1), np.inf)
        better = distance < best
        best, chosen = np.where(better, distance, best), np.where(better[:, None], candidate, chosen)
    return chosen


@pytest.mark.parametrize("rate_aware", [False, True])
def test_sector_projection_matches_the_model(rng, rate_aware):
    state = random_state(rng, 2000)
    sets = AchievableSets.for_gear(state, state.gear, VehicleLimits(), rate_aware=rate_aware, dt=0.01)
    w = rng.normal(0, 1.5, (2000, 2))
    p = SectorSets.of(sets).project(w[:, 0], w[:, 1])
    np.testing.assert_allclose(np.column_stack((p.vx, p.vy)), sets.project(w), atol=1e-13)


@pytest.mark.parametrize(
    ("sides", "rate_aware"), [(16, False), (16, True), (3, False), (5, True), (32, True)]
)
def test_polygon_projection_is_the_nearest_point_of_the_polygon(rng, sides, rate_aware):
    state = random_state(rng, 1500)
    sets = AchievableSets.for_gear(state, state.gear, VehicleLimits(), rate_aware=rate_aware, dt=0.01)
    normals, offsets = sets.polygon(sides)
    w = rng.normal(0, 1.5, (1500, 2))
    p = PolygonSets.of(sets, sides).project(w[:, 0], w[:, 1])
    v = np.column_stack((p.vx, p.vy))
    assert np.max(np.einsum("ikj,ij->ik", normals, v) - offsets) <= 1e-12
    np.testing.assert_allclose(v, brute_polygon_projection(w, normals, offsets), atol=1e-12)


@pytest.mark.parametrize("xp", [np, jnp])
def test_a_kept_and_a_rebuilt_polygon_boundary_project_alike(rng, xp):
    """``PolygonSets`` keeps its boundary up to ``KEEP_BOUNDARY_UP_TO`` units and rebuilds it in
    each pass beyond: the same operations, so the same projections and support points, bit for
    bit (in numpy, and compiled)."""
    state = random_state(rng, 500)
    sets = AchievableSets.for_gear(state, state.gear, VehicleLimits(), rate_aware=True, dt=0.01)
    w = rng.normal(0, 1.5, (500, 2)) * rng.choice([0.1, 1.0, 100.0], (500, 1))

    def both(sets, wx, wy):
        kept = PolygonSets.of(sets, 16)
        assert kept.boundary is not None
        rebuilt = dataclasses.replace(kept, boundary=None)
        return [(*p.project(wx, wy), *p.support(wx, wy)) for p in (kept, rebuilt)]

    kept, rebuilt = (jax.jit(both) if xp is jnp else both)(sets, w[:, 0], w[:, 1])
    for a, b in zip(kept, rebuilt):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("speed", SPEED_MODELS)
def test_projection_jacobian_matches_finite_differences(rng, speed):
    state = random_state(rng, 3000)
    sets = AchievableSets.for_gear(state, state.gear, VehicleLimits(), rate_aware=True, dt=0.01)
    projector = make_sets(sets, speed, 16)
    w = rng.normal(0, 1.5, (3000, 2))
    p = projector.project(w[:, 0], w[:, 1])
    h = 1e-7
    errors = []
    dxx, dxy, dyy = p.jacobian
    for axis, column in ((0, (dxx, dxy)), (1, (dxy, dyy))):
        shift = np.zeros((3000, 2))
        shift[:, axis] = h
        up, down = (projector.project(*(w + sign * shift).T) for sign in (1, -1))
        fd = np.column_stack(((up.vx - down.vx) / (2 * h), (up.vy - down.vy) / (2 * h)))
        errors.append(np.max(np.abs(fd - np.column_stack(column)), axis=1))
    # Points within h of a kink of the projection may differ; they are a handful at most.
    assert np.count_nonzero(np.maximum(*errors) > 1e-5) <= 3


@pytest.mark.parametrize("speed", SPEED_MODELS)
def test_dual_gradient_and_gap_identity(rng, speed):
    problem = spread_problem(rng, 50, exempt_share=0.0)
    sets = make_sets(problem.achievable(), speed, 16)
    jacobian = problem.jacobian
    d, u, rho = problem.nominal, problem.task_velocity, 100.0

    def dual_value(lam):
        t = jacobian.apply_transpose(lam)
        p = sets.project(d[:, 0] - t[:, 0] / 2, d[:, 1] - t[:, 1] / 2)
        residual = jacobian.apply(np.column_stack((p.vx, p.vy))) - u
        deviation = np.sum((p.vx - d[:, 0]) ** 2 + (p.vy - d[:, 1]) ** 2)
        primal = deviation + rho * residual @ residual
        return deviation + lam @ residual - lam @ lam / (4 * rho), residual - lam / (2 * rho), primal

    lam = rng.normal(0, 20, 4)
    value, grad, primal = dual_value(lam)
    h = 1e-5
    numeric = [(dual_value(lam + h * e)[0] - dual_value(lam - h * e)[0]) / (2 * h) for e in np.eye(4)]
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-7)
    assert primal - value == pytest.approx(rho * grad @ grad, rel=1e-9)


@pytest.mark.parametrize(("reading", "speed"), CASES)
@pytest.mark.parametrize("n", [2, 3, 8, 64, 512])
def test_matches_clarabel(n, reading, speed):
    rng = np.random.default_rng(n)
    for _ in range(2 if n <= 8 else 1):
        problem = spread_problem(rng, n, exempt_share=0.0 if n <= 8 else 0.1)
        ours = get_allocator("dual", reading=reading, speed=speed, warm_start=False).allocate(problem)
        assert ours.status == "optimal"
        assert ours.info["relative_gap"] <= 1e-9
        assert_same_objective(ours, reference(problem, reading, speed))


@pytest.mark.parametrize("speed", SPEED_MODELS)
@pytest.mark.parametrize("case", ["random", "line"])
def test_closed_form_task_directions_match_the_eigendecomposition(speed, case):
    """With the mean/variance task's closed-form Gram (no unit under the precedence rule) the
    task-exact reading skips the eigendecomposition; the same Jacobian without it must give the
    same velocities (units on a vertical line: the var_x row degenerate)."""
    problem = spread_problem(np.random.default_rng(8), 8, exempt_share=0.0)
    if case == "line":
        problem = AllocationProblem.build(
            dataclasses.replace(problem.state, x=np.zeros(8), y=np.linspace(0.0, 14.0, 8)),
            problem.task,
            problem.desired,
            problem.desired_rate,
            np.full(4, 10.0),
            problem.limits,
            problem.dt,
        )
    assert problem.jacobian.orthogonal_gram is not None and not problem.exempt.any()
    assert problem.jacobian.degenerate == (1 if case == "line" else 0)
    general = dataclasses.replace(
        problem, jacobian=TaskJacobian.of(problem.jacobian.rows, problem.jacobian.rcond)
    )
    allocator = get_allocator("dual", reading="task-exact", speed=speed, warm_start=False)
    fast, slow = allocator.allocate(problem), allocator.allocate(general)
    assert fast.status == slow.status == "optimal"
    np.testing.assert_allclose(fast.velocities, slow.velocities, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.info["achievable"], slow.info["achievable"], rtol=0, atol=1e-12)


@pytest.mark.parametrize("reading", READINGS)
def test_polygon_matches_osqp(reading):
    rng = np.random.default_rng(5)
    for n in (3, 40):
        problem = spread_problem(rng, n)
        ours = get_allocator("dual", reading=reading).allocate(problem)
        assert_same_objective(ours, reference(problem, reading, "polygon", backend="osqp"))


@pytest.mark.parametrize("speed", SPEED_MODELS)
def test_matches_clarabel_at_4096_units(speed):
    problem = spread_problem(np.random.default_rng(4096), 4096)
    ours = get_allocator("dual", speed=speed).allocate(problem)
    assert_same_objective(ours, reference(problem, "achievable-first", speed))


@pytest.mark.parametrize(("reading", "speed"), [("achievable-first", "polygon"), ("task-exact", "cone")])
def test_options_rho_eps_sides_rate_aware(reading, speed):
    problem = spread_problem(np.random.default_rng(11), 30)
    options = {"rate_aware": True, **({"rho": 37.0} if reading == "achievable-first" else {"eps": 1e-2})}
    if speed == "polygon":
        options["sides"] = 7
    ours = get_allocator("dual", reading=reading, speed=speed, **options).allocate(problem)
    assert_same_objective(ours, reference(problem, reading, speed, **options))


def line_state(rng: np.random.Generator, n: int) -> PlatoonState:
    """All units on one vertical line: var_x = 0, so the second row of J vanishes."""
    return PlatoonState(
        x=np.full(n, 1.5),
        y=np.linspace(-3, 3, n),
        theta=rng.uniform(-np.pi, np.pi, n),
        alpha=np.zeros(n),
        gear=np.ones(n),
    )


def coincident_state(rng: np.random.Generator, n: int) -> PlatoonState:
    """All units at one point: both variances 0."""
    return PlatoonState(
        x=np.zeros(n), y=np.zeros(n), theta=rng.uniform(-np.pi, np.pi, n), alpha=np.zeros(n), gear=np.ones(n)
    )


def degenerate_problems(n: int):
    rng = np.random.default_rng(n + 100)
    task = MeanVarianceTask()
    for state in (line_state(rng, n), coincident_state(rng, n)):
        problem = AllocationProblem.build(
            state,
            task,
            task.value(state.positions) + np.array([1.0, 0.5, -0.5, 0.4]),
            np.array([0.3, 0.0, 0.2, 0.0]),
            np.array([50.0, 10, 50, 10]),
            VehicleLimits(),
            0.01,
        )
        # Precedence off: every coincident unit would be exempt; the rule has its own test.
        yield dataclasses.replace(problem, exempt=np.zeros(n, dtype=bool))
    state = random_state(rng, n, spread=2.0 * np.sqrt(n))
    problem = AllocationProblem.build(
        state, task, task.value(state.positions) + 0.5, np.zeros(4), np.full(4, 10.0), VehicleLimits(), 0.01
    )
    # Zero nominal velocity while the task asks for motion.
    yield dataclasses.replace(problem, nominal=np.zeros((n, 2)), exempt=np.zeros(n, dtype=bool))


@pytest.mark.parametrize(("reading", "speed"), CASES)
@pytest.mark.parametrize("n", [2, 9, 300])
def test_degenerate_problems_match_clarabel(n, reading, speed):
    for problem in degenerate_problems(n):
        ours = get_allocator("dual", reading=reading, speed=speed, warm_start=False).allocate(problem)
        assert ours.status == "optimal"
        assert np.all(np.isfinite(ours.velocities))
        assert_same_objective(ours, reference(problem, reading, speed))


# --- strict priority ----------------------------------------------------------------------


def stage_two_by_clarabel(problem: AllocationProblem, speed: str, target: np.ndarray) -> tuple[float, float]:
    """The deviation ``sum ||v - q'_d||^2`` of the QP allocators' second strict stage (J v within
    their band around ``target``), by Clarabel, and its relative accuracy: Clarabel's default
    tolerances, or 1e-7 where it ends "AlmostSolved" on them (the band is thin)."""
    name = REFERENCES[("achievable-first", speed)]
    for accuracy, options in (
        (1e-7, {}),
        (1e-6, {"tol_gap_rel": 1e-7, "tol_gap_abs": 1e-7, "tol_feas": 1e-7}),
    ):
        extra = {"fallbacks": ()} if speed == "polygon" else {}
        allocator = get_allocator(name, priority="strict", solver_options=options, **extra)
        setup, failures = allocator.setup(problem), []
        solved = allocator._solve(problem, {speed: setup}, "deviation", target, failures)
        if solved is not None:
            program, x, _, _ = solved
            _, velocities, achievable = allocator._unpack(problem, program, x, {speed: setup})
            return formulation.objective(problem, setup, velocities, achievable, "deviation"), accuracy
    raise AssertionError(failures)


def assert_strict_is_exact(problem: AllocationProblem, speed: str, allocation) -> None:
    """Stage 1: the task residual no larger than Clarabel's. Stage 2: J v within the band of the
    stage-1 task velocity t*, and v_i = P_C(q'_d,i - J_i^T lambda / 2) for the reported
    multipliers (the optimality conditions of the least deviation for the task velocity J v, so v
    is exact for it), or, for Wolfe's stage-1 point, a certified bound within the band's accuracy.
    The deviation is at least Clarabel's over the whole band. Above it the band itself leaves
    room: where t* is on a curved part of J(C)'s boundary (the cone, the task far out of reach)
    Clarabel's value moves by 2e-4 as the band shrinks from 1e-7 to 1e-10, so the check above
    is loose (1e-3), a guard against gross errors only."""
    info = allocation.info
    assert allocation.status == "optimal", allocation.status
    qp = get_allocator(REFERENCES[("achievable-first", speed)], priority="strict")
    reference = qp.allocate(problem)
    mine, theirs = problem.task_residual(allocation.velocities), problem.task_residual(reference.velocities)
    assert mine <= theirs * (1 + 1e-9) + 1e-12, (mine, theirs)
    assert info["band_residual"] <= info["band"]
    free = ~problem.exempt
    np.testing.assert_array_equal(allocation.velocities[~free], qp.setup(problem).precedence[~free])
    banded, accuracy = stage_two_by_clarabel(problem, speed, info["stage1_task_velocity"])
    assert banded * (1 - accuracy) <= info["objective"] <= banded * (1 + 1e-3), (info["objective"], banded)
    if "stage2_bound" in info:  # Wolfe's stage-1 point, certified by the penalized rounds
        assert info["stage2_bound"] <= STRICT_BAND
        return
    pulled = problem.nominal - 0.5 * np.einsum(
        "k,kij->ij", np.asarray(info["multipliers"]), problem.jacobian.rows
    )
    sets = make_sets(problem.achievable().take(free.nonzero()[0]), speed, 16)
    projected = sets.project(pulled[free, 0], pulled[free, 1])
    rounding = 1e-9 + 1e-15 * float(np.max(np.abs(info["multipliers"])))  # J^T lambda's, |lambda| to 1e8
    np.testing.assert_allclose(allocation.velocities[free, 0], projected.vx, atol=rounding)
    np.testing.assert_allclose(allocation.velocities[free, 1], projected.vy, atol=rounding)


@pytest.mark.parametrize("speed", SPEED_MODELS)
@pytest.mark.parametrize("n", [3, 8, 64, 512])
def test_strict_priority_is_exact_in_both_stages(n, speed):
    rng = np.random.default_rng(n)
    for problem in (random_problem(rng, n), spread_problem(rng, n)):  # the task out of reach, in reach
        allocation = get_allocator("dual", speed=speed, priority="strict", warm_start=False).allocate(problem)
        assert_strict_is_exact(problem, speed, allocation)


@pytest.mark.parametrize("speed", SPEED_MODELS)
@pytest.mark.parametrize("n", [8, 512])
def test_strict_priority_with_the_task_far_out_of_reach(n, speed):
    """t* at a corner of J(C): the second stage's multipliers grow without bound."""
    rng = np.random.default_rng(n + 1)
    for _ in range(3):
        problem = random_problem(rng, n)
        problem = dataclasses.replace(problem, task_velocity=1e3 * problem.task_velocity)
        allocation = get_allocator("dual", speed=speed, priority="strict", warm_start=False).allocate(problem)
        assert_strict_is_exact(problem, speed, allocation)


@pytest.mark.parametrize("speed", SPEED_MODELS)
def test_strict_priority_on_degenerate_problems(speed):
    for problem in degenerate_problems(9):
        allocation = get_allocator("dual", speed=speed, priority="strict", warm_start=False).allocate(problem)
        assert np.all(np.isfinite(allocation.velocities))
        assert_strict_is_exact(problem, speed, allocation)


def test_strict_priority_warm_starts_along_a_closed_loop():
    scenario = load_scenario("paper_obstacles")
    trajectory = simulate(scenario, get_allocator("dual", priority="strict"), duration=1.0)
    assert set(trajectory.status) == {"optimal"}
    assert np.all(np.isfinite(trajectory.x))


@pytest.mark.parametrize(("precedence", "anchor_weight"), [("pin", 1.0), ("anchor", 1.0), ("anchor", 10.0)])
def test_precedence_rule_follows_the_formulation(rng, precedence, anchor_weight):
    problem = spread_problem(rng, 40, exempt_share=0.4)
    options = {"precedence": precedence, "anchor_weight": anchor_weight}
    for reading, speed in CASES:
        ours = get_allocator("dual", reading=reading, speed=speed, **options).allocate(problem)
        theirs = reference(problem, reading, speed, **options)
        assert_same_objective(ours, theirs)
        if precedence == "pin":
            held = problem.exempt
            np.testing.assert_allclose(ours.velocities[held], theirs.velocities[held], atol=1e-12)


@pytest.mark.parametrize("reading", READINGS)
@pytest.mark.parametrize("precedence", ["pin", "anchor"])
def test_every_unit_under_the_precedence_rule(rng, reading, precedence):
    problem = dataclasses.replace(spread_problem(rng, 6), exempt=np.ones(6, dtype=bool))
    ours = get_allocator("dual", reading=reading, precedence=precedence).allocate(problem)
    theirs = reference(problem, reading, "polygon", precedence=precedence)
    assert ours.status == "optimal"
    assert_same_objective(ours, theirs)
    np.testing.assert_allclose(ours.velocities, theirs.velocities, atol=1e-8)


def test_handed_velocities_are_achievable_or_meet_the_task(rng):
    problem = spread_problem(rng, 200, exempt_share=0.0)
    sets = problem.achievable()
    normals, offsets = sets.polygon(16)
    first = get_allocator("dual").allocate(problem)
    assert np.max(np.einsum("ikj,ij->ik", normals, first.velocities) - offsets) <= 1e-12
    exact = get_allocator("dual", reading="task-exact", speed="cone").allocate(problem)
    assert exact.task_residual <= 1e-9 * (1 + np.linalg.norm(problem.task_velocity))
    assert np.max(sets.distance(exact.info["achievable"])) <= 1e-12


def test_warm_start_reuses_the_multipliers(rng):
    problem = spread_problem(rng, 100)
    allocator = get_allocator("dual", reading="task-exact")
    first = allocator.allocate(problem)
    again = allocator.allocate(problem)
    assert again.iterations == 0
    np.testing.assert_allclose(again.velocities, first.velocities, atol=1e-12)
    cold = get_allocator("dual", reading="task-exact", warm_start=False).allocate(problem)
    assert cold.iterations > 0


def test_a_failure_falls_back_without_raising(rng, monkeypatch):
    problem = spread_problem(rng, 20)

    def broken(*args, **kwargs):
        raise np.linalg.LinAlgError("broken")

    monkeypatch.setattr(dual, "solve_host", broken)
    allocation = get_allocator("dual").allocate(problem)
    assert allocation.fell_back and allocation.status.startswith("fallback:error:LinAlgError")
    assert np.all(np.isfinite(allocation.velocities))
    normals, offsets = problem.achievable().polygon(16)
    assert np.max(np.einsum("ikj,ij->ik", normals, allocation.velocities) - offsets) <= 1e-12


def test_an_iteration_cap_keeps_an_achievable_iterate(rng):
    problem = spread_problem(rng, 64, exempt_share=0.0)
    allocation = get_allocator("dual", max_iterations=0, warm_start=False).allocate(problem)
    assert allocation.status in ("optimal", "inaccurate") or allocation.status.startswith(
        "fallback:max_iterations"
    )
    assert allocation.info["duality_gap"] >= 0
    normals, offsets = problem.achievable().polygon(16)
    assert np.max(np.einsum("ikj,ij->ik", normals, allocation.velocities) - offsets) <= 1e-12


@pytest.mark.parametrize(
    "options",
    [
        {"reading": "exact"},
        {"speed": "disk"},
        {"rho": 0.0},
        {"eps": -1.0},
        {"sides": 2},
        {"tolerance": np.nan},
        {"priority": "lexicographic"},
        {"priority": "strict", "reading": "task-exact"},
        {"priority": "strict", "precedence": "anchor"},
    ],
)
def test_bad_options_are_rejected(options):
    with pytest.raises(ValueError, match=next(iter(options))):
        get_allocator("dual", **options)


def test_closed_loop_runs_the_paper_scenario():
    scenario = load_scenario("paper_obstacles")
    trajectory = simulate(scenario, get_allocator("dual", reading="task-exact"), duration=1.0)
    assert set(trajectory.status) == {"optimal"}
    assert np.all(np.isfinite(trajectory.x))


def test_the_relative_gap_of_a_zero_optimum_is_small():
    """Soak seed 3, problem 956: the task is met exactly (optimum 0, objective 2.6e-29 at the
    answer) and the gap is 6e-27; relative to the objective alone that read 239 with status
    "optimal" (up to 8.7e274 in the soak). Relative to a scale that cannot vanish it is tiny."""
    problem = next(itertools.islice(family.specs(3, 957), 956, None)).build()
    for speed in ("polygon", "cone"):
        allocation = get_allocator("dual", reading="task-exact", speed=speed).allocate(problem)
        gap, objective = allocation.info["duality_gap"], allocation.info["objective"]
        assert allocation.status == "optimal" and 0 <= objective <= 1e-20
        assert gap > 1e-3 * objective  # the old figure, gap / objective, was not small
        assert 0 <= allocation.info["relative_gap"] <= 1e-12
        unit = problem.limits.max_speed**2 * 1e-4  # eps v_max^2
        assert allocation.info["relative_gap"] == pytest.approx(gap / unit, rel=1e-12)


def test_the_dual_projection_fallback_is_a_change_of_program(monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("injected")

    monkeypatch.setattr(dual, "solve_host", broken)
    allocation = get_allocator("dual").allocate(random_problem(np.random.default_rng(1), 4))
    assert allocation.status == "fallback:error:RuntimeError->projection" and allocation.fell_back
    assert allocation.program_changed and allocation.info["program"] == "projection"
