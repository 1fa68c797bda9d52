"""``nmpc``'s task rows between the horizon's nodes (``task_samples="steps"``, docs/nmpc.md,
Eq. 2.1): they compare the task of the units where the vehicle model moves them, step by step,
with f_d at those steps."""

import math
from dataclasses import replace

import numpy as np
import pytest

from platoon_opt import load_scenario
from platoon_opt.host_loop import scenario_controller
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc.residuals import ERROR_SCALE
from platoon_opt.solvers.nmpc.solve import _to_columns
from platoon_opt.vehicle import step_vehicles, unit_controller
from tests.conftest import random_problem

# Three intervals of three steps: two task samples on the way through each interval.
SHORT = {"intervals": 3, "resolve_every": 3}


@pytest.mark.parametrize("steering", ["linear", "rate"])
def test_the_task_rows_between_the_nodes_are_the_task_of_the_driven_units(steering):
    """The plan, handed interval by interval to the unit controllers and driven by the vehicle
    model, puts the units at every step where the task rows evaluate the task: the rows equal
    the weighted error of f at the driven positions against f_d extrapolated to that step."""
    allocator = get_allocator("nmpc", task_samples="steps", preview=False, steering=steering, **SHORT)
    problem = random_problem(np.random.default_rng(11), 4)
    allocation = allocator.allocate(problem)
    assert not allocation.fell_back, allocation.status
    plan, horizon = allocator._state.plan, allocator._horizon(problem)
    N, S, m = SHORT["intervals"], SHORT["resolve_every"], problem.task_value.size
    state, errors = problem.state, []
    for k in range(N):
        interval = replace(plan, inputs=plan.inputs[k:], alpha0=state.alpha)
        for substep in range(S):
            velocity = interval.hand(replace(problem, state=state), substep)
            command = unit_controller(state, velocity, problem.limits, problem.dt)
            state = step_vehicles(state, command, problem.limits, problem.dt)
            tau = (k * S + substep + 1) * problem.dt
            target = problem.desired + tau * problem.desired_rate
            errors.append(problem.task.value(state.positions) - target)
        np.testing.assert_allclose(state.positions, plan.states[k][:, :2], rtol=0, atol=1e-9)
    p = allocator._parameters(problem, horizon, plan.inputs[0, :, 0])
    (residual,) = horizon.residual(_to_columns(plan.states), _to_columns(plan.inputs), p)
    rows = problem.jacobian.rows
    weights = 1 / (math.sqrt(problem.n) * np.sqrt(np.einsum("kij,kij->k", rows, rows)))
    weights *= problem.gains / problem.gains.min()  # the gain weights (Eq. 2.9)
    expected = weights * np.array(errors) / (ERROR_SCALE * math.sqrt(N * S))
    # The task is MeanVarianceTask, compiled exactly into the horizon.
    np.testing.assert_allclose(residual[: N * S * m], expected.ravel(), rtol=1e-9, atol=1e-9)


def test_the_closed_loop_hands_the_reference_at_the_nodes_when_the_task_is_sampled_there():
    allocator = get_allocator("nmpc", task_samples="nodes", **SHORT)
    sc = load_scenario("figure_eight")
    state, obstacles = sc.initial(0)
    controller, goal = scenario_controller(sc, allocator, obstacles), sc.goal(sc.task().names)
    desired, rate, _ = goal.at(0.0)
    ahead = controller.step(state, desired, rate, sc.dt, 0.0).problem.desired_ahead
    h = SHORT["resolve_every"] * sc.dt
    expected = np.stack([goal.at(h * k)[0] for k in range(1, SHORT["intervals"] + 1)])
    np.testing.assert_array_equal(ahead, expected)


def test_the_node_samples_weigh_as_a_share_of_the_steps():
    """Sampled at every step, a task error that is the same at every step costs what it costs
    sampled at the nodes alone: each sample's rows are scaled by 1 / sqrt(samples) (Eq. 2.1)."""
    problem = random_problem(np.random.default_rng(2), 3)
    costs = []
    for samples in ("steps", "nodes"):
        allocator = get_allocator("nmpc", task_samples=samples, preview=False, **SHORT)
        horizon = allocator._horizon(problem)
        # Units standing still in the horizon, with a target standing still: a constant error.
        still = replace(problem, desired_rate=np.zeros_like(problem.desired_rate))
        p = allocator._parameters(still, horizon, np.zeros(problem.n))
        z = np.column_stack((still.state.x, still.state.y, still.state.theta, still.state.alpha))
        Z = np.broadcast_to(z, (SHORT["intervals"], problem.n, 4))
        U = np.zeros((SHORT["intervals"], problem.n, 2))
        U[:, :, 1] = still.state.alpha
        (residual,) = horizon.residual(_to_columns(Z), _to_columns(U), p)
        task_rows = SHORT["intervals"] * (SHORT["resolve_every"] if samples == "steps" else 1) * 4
        costs.append(float(residual[:task_rows] @ residual[:task_rows]))
    assert costs[0] == pytest.approx(costs[1], rel=1e-12)
