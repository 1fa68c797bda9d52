"""``nmpc`` given the reference over its horizon (``AllocationProblem.desired_ahead``): what the
closed loop hands it, and that its task rows track it (docs/nmpc.md, Eq. 1.7)."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt import load_scenario
from platoon_opt.host_loop import scenario_controller
from platoon_opt.solvers import get_allocator
from tests.conftest import random_problem
from tests.solvers.test_allocator_properties import LIMIT, check_common, problem_specs

# A short horizon keeps the tests quick: 4 intervals of 2 steps.
SMALL = {"intervals": 4, "resolve_every": 2}


def controller_for(allocator, scenario: str = "figure_eight", seed: int = 0):
    """The closed loop's controller of ``scenario`` (with its reference), its goal, initial
    state and time step."""
    sc = load_scenario(scenario)
    state, obstacles = sc.initial(seed)
    return scenario_controller(sc, allocator, obstacles), sc.goal(sc.task().names), state, sc.dt


def test_the_closed_loop_hands_the_reference_at_each_solve_only():
    """At every step of the horizon (the default ``task_samples``); tests/solvers/
    test_nmpc_task_samples.py has the nodes."""
    allocator = get_allocator("nmpc", **SMALL)
    controller, goal, state, dt = controller_for(allocator)
    steps = SMALL["intervals"] * SMALL["resolve_every"]
    for k in range(5):
        t = k * dt
        desired, rate, _ = goal.at(t)
        result = controller.step(state, desired, rate, dt, t)
        ahead = result.problem.desired_ahead
        if k % SMALL["resolve_every"]:
            assert result.allocation.status == "plan" and ahead is None
        else:
            assert result.allocation.solved
            expected = np.stack([goal.at(t + tau)[0] for tau in dt * np.arange(1, steps + 1)])
            np.testing.assert_array_equal(ahead, expected)
        state = result.state
    # Without preview, or for an allocator that does not plan ahead, the problem carries none.
    others = (get_allocator("nmpc", preview=False, **SMALL), get_allocator("iterative", max_iterations=4))
    for other in others:
        controller, goal, state, dt = controller_for(other)
        desired, rate, _ = goal.at(0.0)
        assert controller.problem(state, desired, rate, dt, 0.0).desired_ahead is None


@pytest.mark.parametrize("seed", [0, 1])
def test_a_reference_on_the_extrapolation_gives_the_extrapolating_plan(seed):
    problem = random_problem(np.random.default_rng(seed), 5)
    tau = problem.dt * np.arange(1, SMALL["intervals"] * SMALL["resolve_every"] + 1)
    line = problem.desired[None, :] + tau[:, None] * problem.desired_rate[None, :]
    previewed = get_allocator("nmpc", **SMALL).allocate(replace(problem, desired_ahead=line))
    extrapolated = get_allocator("nmpc", preview=False, **SMALL).allocate(problem)
    assert not previewed.fell_back and not extrapolated.fell_back
    np.testing.assert_allclose(previewed.velocities, extrapolated.velocities, rtol=0, atol=1e-12)


def test_the_plan_follows_a_curved_reference_closer_than_its_extrapolation():
    """On the figure-eight the linear extrapolation leaves the path within the horizon: the plan's
    mean at the nodes lies nearer the reference when the allocator is given it."""
    gaps = {}
    for preview in (True, False):
        allocator = get_allocator("nmpc", preview=preview)
        controller, goal, state, dt = controller_for(allocator)
        t = 3.0  # on a bend of the figure-eight: the platoon moved onto the target there
        desired, rate, _ = goal.at(t)
        shift = desired[[0, 2]] - state.positions.mean(axis=0)
        state = replace(state, x=state.x + shift[0], y=state.y + shift[1])
        problem = controller.problem(state, desired, rate, dt, t)
        allocator.allocate(problem)
        plan = allocator._state.plan
        h = allocator.resolve_every * dt
        means = plan.states[:, :, :2].mean(axis=1)
        reference = np.stack([goal.at(t + j * h)[0][[0, 2]] for j in range(1, allocator.intervals + 1)])
        gaps[preview] = float(np.max(np.hypot(*(means - reference).T)))
    assert gaps[True] < 0.5 * gaps[False], gaps


def test_a_preview_of_the_wrong_length_is_reported_in_the_status():
    problem = random_problem(np.random.default_rng(3), 4)
    wrong = np.tile(problem.desired, (SMALL["intervals"] + 1, 1))
    allocation = get_allocator("nmpc", **SMALL).allocate(replace(problem, desired_ahead=wrong))
    assert allocation.fell_back and "desired_ahead" in allocation.status
    with pytest.raises(ValueError, match="desired_ahead must have shape"):
        type(problem).build(
            problem.state,
            problem.task,
            problem.desired,
            problem.desired_rate,
            np.array([50.0, 10, 50, 10]),
            problem.limits,
            problem.dt,
            desired_ahead=np.zeros((3, 2)),
        )


# One instance for every example: nmpc builds its CasADi functions per platoon size and obstacle
# count (each example is a new problem at t = 0, so it starts cold).
_PREVIEWING = get_allocator("nmpc", **SMALL)


@settings(max_examples=30)
@given(spec=problem_specs(), wander=st.floats(-2.0, 2.0), turn=st.floats(-np.pi, np.pi))
def test_any_reference_keeps_the_promise(spec, wander, turn):
    """Whatever reference the horizon is handed (here the extrapolation, bent by up to 2 m
    over the horizon in any direction), the handed velocities are finite and in the sector
    of the gear each unit is handed, as without a preview (tests/solvers/test_allocator_properties.py)."""
    problem = spec.build()
    tau = problem.dt * np.arange(1, SMALL["intervals"] * SMALL["resolve_every"] + 1)
    ahead = problem.desired + tau[:, None] * problem.desired_rate
    bend = (tau / tau[-1]) ** 2 * wander
    ahead[:, 0] += bend * np.cos(turn)
    ahead[:, 2] += bend * np.sin(turn)
    previewed = replace(problem, desired_ahead=ahead)
    allocation = _PREVIEWING.allocate(previewed)
    check_common(previewed, allocation)
    excess = _PREVIEWING.promised_excess(previewed, allocation)
    assert excess is not None and excess <= LIMIT, excess
