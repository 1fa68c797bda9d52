"""What a receding-horizon solve returns: states that belong to its inputs, and failures that
are failures.

A horizon (its CasADi Functions and their output buffers) is shared by every allocator of one
formulation in the process, so a solution must not hold views into those buffers; and a DAQP
that fails must fail the step, not hand over whatever its output buffer holds.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc import allocator as nmpc
from platoon_opt.solvers.nmpc import box_qp, solve
from platoon_opt.solvers.nmpc.box_qp import BoxSolution
from platoon_opt.solvers.nmpc.compiled import Horizon
from tests.conftest import random_problem

# A short horizon keeps the tests quick: 4 intervals of 2 steps (the rate rows are present).
SMALL = {"intervals": 4, "resolve_every": 2}


def rollout(horizon: Horizon, problem, inputs: np.ndarray) -> np.ndarray:
    """The node states (N, n, 4) of ``inputs`` (N, n, 2), from the rollout Function called on
    DM (its own outputs, no shared buffer)."""
    z0 = solve._state_array(problem)
    states = np.array(horizon.rollout.function(z0.T, solve._to_columns(inputs)))
    return solve._from_columns(states, horizon.N, problem.n)


def assert_states_of(horizon: Horizon, problem, states: np.ndarray, inputs: np.ndarray) -> None:
    """``states`` are the simulation of ``inputs`` from ``problem``'s state (to rounding)."""
    np.testing.assert_allclose(states, rollout(horizon, problem, inputs), rtol=0, atol=1e-12)


def recording(monkeypatch) -> list:
    """Replace the allocator's SQP by one that records every solution it returns."""
    solutions, real = [], solve.sqp

    def sqp(*args, **kwargs):
        solutions.append(real(*args, **kwargs))
        return solutions[-1]

    monkeypatch.setattr(nmpc, "sqp", sqp)
    return solutions


@pytest.mark.parametrize("seed", range(6))
def test_each_start_solution_holds_the_states_of_its_own_inputs(monkeypatch, seed):
    """A re-solve runs two starts (the shifted plan, the controllers' rollout) on one horizon:
    both solutions, and the plan kept, hold the simulation of their own inputs. (Before the fix,
    the first start's states were the second start's last rollout: off by up to 1.4.)"""
    problem = random_problem(np.random.default_rng(seed), 5)
    allocator = get_allocator("nmpc", **SMALL)
    allocator.allocate(problem)
    solutions = recording(monkeypatch)
    later = replace(problem, t=problem.t + SMALL["resolve_every"] * problem.dt)
    assert not allocator.allocate(later).fell_back
    assert len(solutions) == 2
    horizon = allocator._horizon(later)
    for solution in solutions:
        assert_states_of(horizon, later, solution.states, solution.inputs)
    plan = allocator._state.plan
    assert_states_of(horizon, later, plan.states, plan.inputs)
    # Another allocator solving on the same (shared) horizon leaves this plan alone.
    get_allocator("nmpc", **SMALL).allocate(random_problem(np.random.default_rng(seed + 100), 5))
    assert_states_of(horizon, later, plan.states, plan.inputs)


@pytest.mark.parametrize("seed", [1, 9])
def test_a_stalled_solve_returns_the_states_of_the_inputs_it_returns(seed):
    """Run to a stall (no tolerance, many iterations; seeds whose solve stalls within 60): the
    line search's rejected trials are simulated after the last accepted iterate, and the
    solution holds that iterate's states, not the last trial's."""
    problem = random_problem(np.random.default_rng(seed), 5)
    allocator = get_allocator("nmpc", **SMALL)
    horizon = allocator._horizon(problem)
    low, high = allocator._input_bounds(problem)
    start = np.clip(allocator._rollout_inputs(problem, horizon), low, high)
    p = allocator._parameters(problem, horizon, start[0, :, 0])
    solution = solve.sqp(problem, horizon, start, p, low, high, max_iterations=60, step_tolerance=0.0)
    assert solution.status == "stalled"
    assert_states_of(horizon, problem, solution.states, solution.inputs)


class FailingDaqp:
    """DAQP's QP that solves but reports failure (exit flag -1, infeasible): what the SQP does
    with a failed DAQP, whatever its output."""

    def __init__(self, qp) -> None:
        self.qp, self.calls = qp, 0

    def __call__(self, *args):
        self.calls += 1
        return self.qp(*args)

    def stats(self) -> dict:
        return {**self.qp.stats(), "success": False, "return_status": -1}


def cycling(hessian, gradient, lower, upper, guess=None) -> BoxSolution:
    """An active-set method whose sets always cycle."""
    held = np.zeros(gradient.size, dtype=bool)
    return BoxSolution(None, 30, held, held)


def failing_daqp(monkeypatch) -> list[FailingDaqp]:
    """Make every horizon the allocator gets use a ``FailingDaqp``; the wrappers made, in order."""
    made, real = [], nmpc.horizon_for

    def horizon_for(*args):
        horizon = real(*args)
        made.append(FailingDaqp(horizon.qp))
        return replace(horizon, qp=made[-1])

    monkeypatch.setattr(nmpc, "horizon_for", horizon_for)
    return made


def test_a_failed_daqp_with_rate_rows_fails_the_solve_and_the_allocator_falls_back(monkeypatch):
    """With rate rows DAQP alone solves the step's QP: its failure is the SQP's
    (``failed:qp daqp -1 infeasible``, not a step for the line search to judge), and the
    allocator falls back as for any failed QP."""
    problem = random_problem(np.random.default_rng(5), 3)
    allocator = get_allocator("nmpc", **SMALL)
    horizon = allocator._horizon(problem)
    assert horizon.rate_rows
    low, high = allocator._input_bounds(problem)
    start = np.clip(allocator._rollout_inputs(problem, horizon), low, high)
    p = allocator._parameters(problem, horizon, start[0, :, 0])
    failing = replace(horizon, qp=FailingDaqp(horizon.qp))
    solution = solve.sqp(problem, failing, start, p, low, high, max_iterations=4, step_tolerance=1e-4)
    assert solution.status == "failed:qp daqp -1 infeasible" and solution.iterations == 1
    np.testing.assert_array_equal(solution.inputs, start)

    made = failing_daqp(monkeypatch)
    allocation = get_allocator("nmpc", **SMALL).allocate(problem)
    assert made[0].calls == 1
    assert allocation.fell_back and allocation.status == "fallback:qp daqp -1 infeasible"


def test_a_failed_daqp_on_box_constraints_hands_over_to_projected_newton(monkeypatch):
    """Box constraints alone (0.05 s intervals): when the active-set method cycles and DAQP fails,
    projected Newton takes the step, and the plan is the structured solver's to the QPs'
    accuracy."""
    problem = random_problem(np.random.default_rng(8), 5)
    options = {"intervals": 4, "resolve_every": 5}
    structured = get_allocator("nmpc", **options)
    structured.allocate(problem)
    assert not structured._horizon(problem).rate_rows

    monkeypatch.setattr(solve, "active_set_newton", cycling)
    made = failing_daqp(monkeypatch)
    allocator = get_allocator("nmpc", **options)
    allocation = allocator.allocate(problem)
    assert made[0].calls > 0 and not allocation.fell_back, allocation.status
    np.testing.assert_allclose(allocator._state.plan.inputs, structured._state.plan.inputs, atol=1e-7)


@pytest.mark.parametrize("interior_converges", [True, False])
def test_on_the_split_the_interior_points_step_in(monkeypatch, interior_converges):
    """On the split (more than ``box_qp.DENSE_UP_TO`` inputs), when the active-set method cycles,
    Mehrotra's interior point takes the step, and when it fails too, Clarabel on the lifted QP;
    both end with the exchange from their sets. Never DAQP (whose dense QP is not built there).
    The plan is the active-set method's to the QPs' accuracy."""
    problem = random_problem(np.random.default_rng(8), 5)
    options = {"intervals": 4, "resolve_every": 5}
    structured = get_allocator("nmpc", **options)
    structured.allocate(problem)
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", 0)
    monkeypatch.setattr(solve, "active_set_newton", cycling)
    if not interior_converges:
        monkeypatch.setattr(solve, "interior_point", lambda *args: None)
    made = failing_daqp(monkeypatch)
    allocator = get_allocator("nmpc", **options)
    allocation = allocator.allocate(problem)
    assert made[0].calls == 0 and not allocation.fell_back, allocation.status
    np.testing.assert_allclose(allocator._state.plan.inputs, structured._state.plan.inputs, atol=1e-7)


def test_from_interior_first_from_inputs_the_interior_point_comes_first(monkeypatch):
    """From ``solve.INTERIOR_FIRST_FROM`` inputs on, the interior point solves the QPs and the
    active-set method is not asked; the plan is the same to the QPs' accuracy."""
    problem = random_problem(np.random.default_rng(8), 5)
    options = {"intervals": 4, "resolve_every": 5}
    structured = get_allocator("nmpc", **options)
    structured.allocate(problem)
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", 0)
    monkeypatch.setattr(solve, "INTERIOR_FIRST_FROM", 0)
    asked = []
    monkeypatch.setattr(solve, "active_set_newton", lambda *args: asked.append(1))
    allocator = get_allocator("nmpc", **options)
    allocation = allocator.allocate(problem)
    assert not asked and not allocation.fell_back, allocation.status
    np.testing.assert_allclose(allocator._state.plan.inputs, structured._state.plan.inputs, atol=1e-7)


def test_each_backend_builds_only_what_it_solves_with():
    """Above ``box_qp.DENSE_UP_TO`` inputs without rate rows the SQP's horizon holds no DAQP QP
    (its dense buffers are O((n N)^2)) and no NLP; IPOPT's holds the NLP alone."""
    problem = random_problem(np.random.default_rng(3), 26)
    options = {"intervals": 4, "resolve_every": 5}  # 208 inputs, no rate rows
    horizon = get_allocator("nmpc", **options)._horizon(problem)
    assert 2 * horizon.N * horizon.n > box_qp.DENSE_UP_TO and not horizon.rate_rows
    assert horizon.qp is None and horizon.nlp is None
    with_ipopt = get_allocator("nmpc", backend="ipopt", **options)._horizon(problem)
    assert with_ipopt.nlp is not None and with_ipopt.qp is None
