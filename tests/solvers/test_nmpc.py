from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

from platoon_opt import AchievableSets, CircularObstacles, load_scenario
from platoon_opt.errors import OptionError
from platoon_opt.host_loop import scenario_controller
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc import allocator as nmpc
from platoon_opt.solvers.nmpc import solve
from platoon_opt.solvers.nmpc.box_qp import BoxSolution
from platoon_opt.solvers.nmpc.residuals import ERROR_SCALE, shadow
from platoon_opt.solvers.nmpc.solve import HorizonSolution
from platoon_opt.vehicle import step_vehicles, unit_controller
from tests.conftest import random_problem

# A short horizon keeps the tests quick: 4 intervals of 2 steps.
SMALL = {"intervals": 4, "resolve_every": 2}


def run(allocator, steps: int, scenario: str = "paper_obstacles", seed: int = 3):
    """Closed loop of ``steps`` steps; the allocations and the final state."""
    sc = load_scenario(scenario)
    state, obstacles = sc.initial(seed)
    controller = scenario_controller(sc, allocator, obstacles)
    task = controller.task
    allocations = []
    for k in range(steps):
        desired, rate, _ = sc.desired_at(task.names, k * sc.dt)
        result = controller.step(state, desired, rate, sc.dt, k * sc.dt)
        allocations.append(result.allocation)
        state = result.state
    return allocations, state


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_first_move_is_achievable_and_reproduced_by_the_units(seed):
    problem = random_problem(np.random.default_rng(seed), 5)
    allocator = get_allocator("nmpc", **SMALL)
    allocation = allocator.allocate(problem)
    assert not allocation.fell_back, allocation.status
    velocity, limits, state = allocation.velocities, problem.limits, problem.state
    assert np.all(np.isfinite(velocity))
    assert np.all(np.hypot(velocity[:, 0], velocity[:, 1]) <= limits.max_speed + 1e-12)
    # The unit controller reproduces the plan's first substep: speed s_0 and the planned steering.
    command = unit_controller(state, velocity, limits, problem.dt)
    plan = allocator._state.plan
    speed, steering = plan.inputs[0, :, 0], plan.inputs[0, :, 1]
    moving = np.abs(speed) > 1e-6
    np.testing.assert_allclose(command.speed[moving], speed[moving], atol=1e-12)
    reach = limits.max_steering_rate * problem.dt  # the default steering="rate" (Eq. 1.6')
    planned = state.alpha + np.clip(steering - state.alpha, -reach, reach)
    np.testing.assert_allclose(
        (state.alpha + command.steering_rate * problem.dt)[moving], planned[moving], atol=1e-12
    )
    # ... so the velocity lies in each unit's rate-aware achievable set for the gear it drives in.
    sets = AchievableSets.for_gear(state, command.gear, limits, rate_aware=True, dt=problem.dt)
    assert np.all(sets.contains(velocity, tol=1e-9)[moving])


@pytest.mark.parametrize("steering", ["linear", "rate"])
def test_model_matches_the_simulation_over_an_interval(steering):
    """The units handed the plan move as the horizon's model predicts, with the steering moving
    linearly or at its rate limit (some units' first change exceeds one step's reach)."""
    allocator = get_allocator("nmpc", **SMALL, steering=steering)
    problem = random_problem(np.random.default_rng(7), 4)
    allocator.allocate(problem)
    plan = allocator._state.plan
    state = problem.state
    reach = problem.limits.max_steering_rate * problem.dt
    assert np.any(np.abs(plan.inputs[0, :, 1] - state.alpha) > reach)
    for substep in range(SMALL["resolve_every"]):
        moved = replace(problem, state=state, t=problem.t + substep * problem.dt)
        velocity = plan.hand(moved, substep)
        command = unit_controller(state, velocity, problem.limits, problem.dt)
        state = step_vehicles(state, command, problem.limits, problem.dt)
    predicted = plan.states[0]
    np.testing.assert_allclose(
        np.column_stack((state.x, state.y, state.alpha)), predicted[:, [0, 1, 3]], atol=1e-9
    )


def test_a_speed_within_the_solvers_resolution_keeps_the_gear():
    """Planned speeds of either sign within step_tolerance v_max are a standstill: each unit keeps
    its gear through the unit controller and barely moves; a speed beyond it still backs."""
    allocator = get_allocator("nmpc", **SMALL)
    problem = random_problem(np.random.default_rng(3), 4)
    allocator.allocate(problem)
    plan = allocator._state.plan
    resolution = allocator.step_tolerance * problem.limits.max_speed
    assert plan.standstill == resolution
    gears = np.array([1.0, -1.0, 1.0, -1.0])
    state = replace(problem.state, gear=gears)
    standing = replace(problem, state=state)
    inputs = plan.inputs.copy()
    inputs[0, :, 0] = np.array([-1, 1, -0.5, 0.5]) * resolution  # against each gear
    inputs[0, :, 1] = state.alpha
    velocity = replace(plan, inputs=inputs).hand(standing, 0)
    after = step_vehicles(
        state, unit_controller(state, velocity, problem.limits, problem.dt), problem.limits, problem.dt
    )
    np.testing.assert_array_equal(after.gear, gears)
    np.testing.assert_allclose(np.hypot(after.x - state.x, after.y - state.y), 0, atol=1e-10)
    inputs[0, :, 0] = np.array([-2, 2, -2, 2]) * resolution
    velocity = replace(plan, inputs=inputs).hand(standing, 0)
    after = step_vehicles(
        state, unit_controller(state, velocity, problem.limits, problem.dt), problem.limits, problem.dt
    )
    np.testing.assert_array_equal(after.gear, [-1, 1, -1, 1])


def test_plan_is_handed_between_solves_and_a_new_run_starts_cold():
    allocator = get_allocator("nmpc", **SMALL)
    allocations, _ = run(allocator, 6)
    statuses = [a.status for a in allocations]
    assert statuses[1] == statuses[3] == statuses[5] == "plan"
    assert all(s in ("converged", "max_iterations") for s in statuses[0::2]), statuses
    # A step handing the plan reuses the last solve: it is not a solve.
    assert [a.solved for a in allocations] == [s != "plan" for s in statuses]
    # Time going back (a new run): a cold start equal to a fresh allocator's.
    again, _ = run(allocator, 2)
    fresh, _ = run(get_allocator("nmpc", **SMALL), 2)
    np.testing.assert_array_equal(again[0].velocities, fresh[0].velocities)
    np.testing.assert_array_equal(again[1].velocities, fresh[1].velocities)


def test_deterministic():
    first, state_a = run(get_allocator("nmpc", **SMALL), 8)
    second, state_b = run(get_allocator("nmpc", **SMALL), 8)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a.velocities, b.velocities)
    np.testing.assert_array_equal(state_a.x, state_b.x)


def test_without_the_nominal_rows_the_plan_is_solved_not_a_fallback():
    """``nominal_weight = 0`` leaves rows of one unit with no state derivative at all: the
    linearization's sums over them must still be floats (it fell back on every step)."""
    allocations, _ = run(get_allocator("nmpc", nominal_weight=0.0, **SMALL), 6, "paper_no_obstacles", 0)
    assert not any(allocation.fell_back for allocation in allocations), [a.status for a in allocations]


def test_falls_back_when_the_solver_fails(monkeypatch):
    problem = random_problem(np.random.default_rng(4), 5)
    allocator = get_allocator("nmpc", **SMALL)

    def failing(*args, **kwargs):
        U = np.zeros((SMALL["intervals"], problem.n, 2))
        return HorizonSolution(U, np.zeros((SMALL["intervals"], problem.n, 4)), "failed:qp test", 1, 0.0)

    monkeypatch.setattr(nmpc, "sqp", failing)
    allocation = allocator.allocate(problem)
    assert allocation.fell_back and allocation.status == "fallback:qp test"
    # A one-step program answered in place of the horizon's: a change of program, named.
    assert allocation.program_changed and allocation.info["program"] == allocation.info["fallback"]
    reference = get_allocator("iterative", max_iterations=4).allocate(problem)
    if allocation.info["fallback"] == reference.allocator:
        np.testing.assert_array_equal(allocation.velocities, reference.velocities)
    assert allocator._state.plan is None

    def raising(*args, **kwargs):
        raise FloatingPointError("boom")

    monkeypatch.setattr(nmpc, "sqp", raising)
    allocation = allocator.allocate(problem)
    assert allocation.fell_back and allocation.status == "fallback:FloatingPointError: boom"


def test_dense_qp_answers_when_the_active_set_method_cycles(monkeypatch):
    """If the active-set Newton method cycles, DAQP on the dense Hessian takes the step: the
    same plan to the QPs' accuracy. (0.05 s intervals: the rate rows are redundant, so the
    active-set method is the first solver, as at the default options.)"""
    problem = random_problem(np.random.default_rng(8), 5)
    options = {"intervals": 4, "resolve_every": 5}
    structured = get_allocator("nmpc", **options)
    structured.allocate(problem)
    calls = []

    def cycling(hessian, gradient, lower, upper, guess=None):
        calls.append(guess)
        held = np.zeros(gradient.size, dtype=bool)
        return BoxSolution(None, 30, held, held)

    monkeypatch.setattr(solve, "active_set_newton", cycling)
    dense = get_allocator("nmpc", **options)
    allocation = dense.allocate(problem)
    assert calls and not allocation.fell_back
    np.testing.assert_allclose(dense._state.plan.inputs, structured._state.plan.inputs, atol=1e-8)


@pytest.mark.parametrize(
    "resolve_every, steering, task_samples, gain_weights",
    [
        (2, "linear", "nodes", True),
        (2, "rate", "nodes", True),
        (5, "linear", "steps", True),
        (5, "rate", "steps", False),
    ],
)
def test_ipopt_failure_falls_back_and_ipopt_agrees_with_the_sqp(
    resolve_every, steering, task_samples, gain_weights
):
    """With 0.02 s intervals the SQP's steps are DAQP's (rate rows); with 0.05 s intervals the
    active-set method's (box constraints alone). With 0.02 s intervals and the rate steering two
    steering changes of the solution lie on their rate rows' bound: the model is smooth there
    (no clip at an interval's last substep), or IPOPT's line search stalls on the kink. There
    the task is sampled at the nodes: sampled at every step, the SQP stalls on this problem at
    a cost 0.5 % above IPOPT's optimum, with other first inputs (measured: 193.5 against 192.7).
    With 0.05 s intervals, the rate steering and the gain weights, IPOPT stops at a stationary
    point of higher cost than the SQP's plan (434.9 against 423.9; measured), with other first
    inputs, so that case weighs the task rows alike."""
    problem = random_problem(np.random.default_rng(5), 3)
    options = {"intervals": 4, "resolve_every": resolve_every, "steering": steering}
    options.update(task_samples=task_samples, gain_weights=gain_weights)
    failed = get_allocator("nmpc", backend="ipopt", max_iterations=1, **options).allocate(problem)
    assert failed.fell_back and failed.status.startswith("fallback:Maximum_Iterations")
    sqp = get_allocator("nmpc", max_iterations=30, step_tolerance=1e-9, **options)
    ipopt = get_allocator("nmpc", backend="ipopt", **options)
    sqp.allocate(problem)
    ipopt.allocate(problem)
    np.testing.assert_allclose(sqp._state.plan.inputs[0], ipopt._state.plan.inputs[0], atol=1e-4)


def test_second_start_keeps_the_better_of_two_local_solutions():
    """With ``second_start`` a re-solve also starts from the unit controllers' rollout of the
    nominal velocity and keeps the lower cost: never above the shifted plan's alone."""
    problem = random_problem(np.random.default_rng(6), 5)
    later = replace(problem, t=problem.t + SMALL["resolve_every"] * problem.dt)
    one, two = get_allocator("nmpc", second_start=False, **SMALL), get_allocator("nmpc", **SMALL)
    for allocator in (one, two):
        allocator.allocate(problem)  # cold: both start from the rollout alone
    np.testing.assert_array_equal(one._state.plan.inputs, two._state.plan.inputs)
    single, double = one.allocate(later), two.allocate(later)
    assert not single.fell_back and not double.fell_back
    assert double.info["cost"] <= single.info["cost"] * (1 + 1e-12)
    assert double.iterations > single.iterations


def test_units_under_the_precedence_rule_at_an_obstacle_follow_their_nominal_velocity_first():
    """``precedence_weight`` weights the nominal-velocity rows of the exempt units within
    2 penalty_margin of an obstacle alone: it draws such a unit's first move toward q'_d, and
    changes nothing for an exempt unit farther away."""
    rng = np.random.default_rng(4)
    problem = random_problem(rng, 5)
    position = problem.state.positions[0]
    # Unit 0's nominal velocity: 0.3 m/s, 0.3 rad off its heading (within reach of its steering).
    nominal = problem.nominal.copy()
    heading = problem.state.theta[0] + 0.3
    nominal[0] = 0.3 * np.array([np.cos(heading), np.sin(heading)])
    exempt = np.arange(5) == 0

    def moves(clearance: float) -> list:
        # An obstacle on unit 0's right, away from q'_d, at ``clearance`` from its surface.
        side = np.array([np.sin(heading), -np.cos(heading)])
        obstacles = CircularObstacles(position + (0.5 + clearance) * side, np.array([0.5]))
        posed = replace(problem, nominal=nominal, exempt=exempt, obstacles=obstacles)
        return [get_allocator("nmpc", precedence_weight=w, **SMALL).allocate(posed) for w in (1.0, 1e4)]

    near, far = moves(0.1), moves(1.0)
    assert not any(move.fell_back for move in near + far)
    np.testing.assert_array_equal(far[0].velocities, far[1].velocities)
    miss = [np.linalg.norm(move.velocities[0] - nominal[0]) for move in near]
    # Measured: the weight halves the miss (0.42 -> 0.21 m/s); with the linear steering, whose
    # unweighted move missed by 1.28 m/s, it cut it to a sixth.
    assert miss[1] < 0.6 * miss[0], miss


def test_chain_rule_over_the_sparse_jacobians_matches_the_dense_product():
    """``Chain`` (dr/dU|_Z + dr/dZ dZ/dU from the Jacobians' nonzeros) equals the dense product
    with dZ/dU holding G on each unit's diagonal, on the rows it keeps, split into the rows of one
    unit (its block alone, by unit) and the coupling rows; the rows it drops are zero, residual
    and derivative. The gradient, product and Hessian blocks of the split are the dense
    matrix's. Units crowd an obstacle, so that hinge rows are active."""
    rng = np.random.default_rng(7)
    obstacles = CircularObstacles(np.array([[0.0, 0.0], [3.0, 0.0]]), np.array([0.5, 0.4]))
    problem = random_problem(rng, 5, obstacles=obstacles)
    allocator = get_allocator("nmpc", **SMALL)
    horizon = allocator._horizon(problem)
    N, n = SMALL["intervals"], problem.n
    Z, U = rng.uniform(-0.7, 0.7, (4, N * n)), rng.uniform(-0.5, 0.5, (2, N * n))
    p = allocator._parameters(problem, horizon, np.zeros(n))
    G = np.tril(np.ones((N, N)))[:, :, None, None, None] * rng.normal(size=(N, N, n, 4, 2))
    linearization = horizon.chain(*horizon.residual_jacobian(Z, U, p), G)

    r, J_z, J_u = (np.array(out) for out in horizon.residual_jacobian.function(Z, U, p))
    sensitivity = np.zeros((N, n, 4, N, n, 2))
    units = np.arange(n)
    sensitivity[:, units, :, :, units, :] = G.transpose(2, 0, 3, 1, 4)
    full = J_u + J_z @ sensitivity.reshape(4 * N * n, 2 * N * n)
    # The chain's columns are unit-major: position i 2N + 2k + side holds column 2 (k n + i) + side.
    full = full[:, np.arange(2 * N * n).reshape(N, n, 2).transpose(1, 0, 2).ravel()]
    r = r.ravel()
    keep = (r != 0) | np.any(full != 0, axis=1)
    assert 0 < np.count_nonzero(keep) < r.size
    # The kept rows that touch one unit's block of columns alone, by unit, then the others.
    block = 2 * N
    touched = (full.reshape(-1, n, block) != 0).any(axis=2)
    alone = touched.sum(axis=1) == 1
    own_rows = np.flatnonzero(keep & alone)
    own_units = touched[own_rows].argmax(axis=1)
    order = np.argsort(own_units, kind="stable")
    own_rows, own_units = own_rows[order], own_units[order]
    coupled_rows = np.flatnonzero(keep & ~alone)
    assert own_rows.size and coupled_rows.size
    np.testing.assert_array_equal(linearization.own_unit, own_units)
    np.testing.assert_array_equal(linearization.own_residual, r[own_rows])
    np.testing.assert_array_equal(linearization.coupled_residual, r[coupled_rows])
    own = full[own_rows].reshape(-1, n, block)[np.arange(own_rows.size), own_units]
    np.testing.assert_allclose(linearization.own, own, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(linearization.coupling, full[coupled_rows], rtol=1e-12, atol=1e-12)
    # The products the SQP takes of it, against the dense matrix of the kept rows.
    R = full[np.concatenate((own_rows, coupled_rows))]
    residual = r[np.concatenate((own_rows, coupled_rows))]
    x = rng.normal(size=n * block)
    np.testing.assert_allclose(linearization.gradient(), R.T @ residual, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(linearization.product(x), R @ x, rtol=1e-10, atol=1e-12)
    own_part = R[: own_rows.size]
    hessian = own_part.T @ own_part
    for i, unit_block in enumerate(linearization.blocks()):
        columns = slice(i * block, (i + 1) * block)
        np.testing.assert_allclose(unit_block, hessian[columns, columns], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_controller_rollout_matches_the_unit_controller(seed):
    """The compiled rollout of the second start equals the Python controller stepping the
    simulation, gear switches included (nominal velocities in every direction)."""
    problem = random_problem(np.random.default_rng(seed), 6)
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-np.pi, np.pi, problem.n)
    nominal = rng.uniform(0.0, 1.5, problem.n)[:, None] * np.column_stack((np.cos(angles), np.sin(angles)))
    nominal[0] = 0.0  # a unit told to stand holds its steering
    problem = replace(problem, nominal=nominal)
    allocator = get_allocator("nmpc", intervals=6, resolve_every=5)
    inputs = allocator._rollout_inputs(problem, allocator._horizon(problem))
    state, expected = problem.state, np.empty_like(inputs)
    for k in range(6):
        for _ in range(5):
            command = unit_controller(state, nominal, problem.limits, problem.dt)
            state = step_vehicles(state, command, problem.limits, problem.dt)
        expected[k, :, 0], expected[k, :, 1] = command.speed, state.alpha
    assert np.any(expected[:, :, 0] < 0) and np.any(expected[:, :, 0] > 0)
    np.testing.assert_allclose(inputs, expected, rtol=0, atol=1e-12)


def test_shadow_is_the_depth_in_the_strip_behind_an_obstacle():
    """``shadow``: moving along +x past an obstacle at (1, 0) of radius 0.5 (strip half-width
    0.6 with the 0.1 m margin), a unit's depth inside the strip times the gate that rises from 0
    at ``shadow_length`` (2 m) behind the centre to 1 at it and falls to 0 at 0.6 m beyond."""
    margin, length = 0.1, 2.0
    x = ca.DM([0.0, 0.0, -1.5, 1.3, 1.0, 0.0])
    y = ca.DM([0.2, -0.7, 0.0, 0.0, -0.3, -0.2])
    center, radius = ca.DM([1.0, 0.0]), 0.5
    depth = np.array(shadow(x, y, center, radius, ca.DM([1.0, 0.0]), margin, length)).ravel()
    # along -1: gate 0.5, depth 0.4; outside the strip; 2.5 m behind; 0.3 m beyond the centre:
    # gate 0.5, depth 0.6; beside the centre: gate 1, depth 0.3; as the first, mirrored.
    expected = np.array([0.5 * 0.4, 0.0, 0.0, 0.5 * 0.6, 0.3, 0.5 * 0.4]) / ERROR_SCALE
    # atol: |lateral| is smoothed by 1e-6 m (1e-4 in units of ERROR_SCALE).
    np.testing.assert_allclose(depth, expected, rtol=0, atol=1e-3)
    # Travel along -y turns the strip: the unit at (1, 0.5) is 0.5 m behind the centre.
    turned = np.array(shadow(ca.DM([1.0]), ca.DM([0.5]), center, radius, ca.DM([0.0, -1.0]), margin, length))
    np.testing.assert_allclose(turned.ravel(), [0.75 * 0.6 / ERROR_SCALE], rtol=0, atol=1e-3)
    # A platoon told to hold still has no direction of travel and no shadows.
    assert not np.any(np.array(shadow(x, y, center, radius, ca.DM([0.0, 0.0]), margin, length)))


def test_options_are_validated():
    with pytest.raises(OptionError, match="option intervals of nmpc must be an integer >= 1, got 0"):
        get_allocator("nmpc", intervals=0)
    with pytest.raises(ValueError, match="gears"):
        get_allocator("nmpc", gears="both")
    with pytest.raises(ValueError, match="shadow_length"):
        get_allocator("nmpc", shadow_length=0.0)
    with pytest.raises(ValueError, match="backend"):
        get_allocator("nmpc", backend="snopt")
    with pytest.raises(OptionError, match="unknown option 'horizon' for nmpc; valid: intervals, "):
        get_allocator("nmpc", horizon=3)
