"""What a receding-horizon solve returns: states that belong to its inputs.

A model (its CasADi Functions and their output buffers) is shared by every allocator of one
formulation in the process, so a solution must not hold views into those buffers.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.nmpc import allocator as nmpc
from platoon_opt.solvers.nmpc import solve
from platoon_opt.solvers.nmpc.model import Model
from tests.conftest import random_problem

# A short horizon keeps the tests quick: 4 intervals of 2 steps (the rate rows are present).
SMALL = {"intervals": 4, "resolve_every": 2}


def rollout(model: Model, problem, inputs: np.ndarray) -> np.ndarray:
    """The node states (N, n, 4) of ``inputs`` (N, n, 2), from the rollout Function called on
    DM (its own outputs, no shared buffer)."""
    z0 = solve._state_array(problem)
    states = np.array(model.rollout.function(z0.T, solve._to_columns(inputs)))
    return solve._from_columns(states, model.N, problem.n)


def assert_states_of(model: Model, problem, states: np.ndarray, inputs: np.ndarray) -> None:
    """``states`` are the simulation of ``inputs`` from ``problem``'s state (to rounding)."""
    np.testing.assert_allclose(states, rollout(model, problem, inputs), rtol=0, atol=1e-12)


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
    """A re-solve runs two starts (the shifted plan, the controllers' rollout) on one model:
    both solutions, and the plan kept, hold the simulation of their own inputs. (Before the fix,
    the first start's states were the second start's last rollout: off by up to 1.4.)"""
    problem = random_problem(np.random.default_rng(seed), 5)
    allocator = get_allocator("nmpc", **SMALL)
    allocator.allocate(problem)
    solutions = recording(monkeypatch)
    later = replace(problem, t=problem.t + SMALL["resolve_every"] * problem.dt)
    assert not allocator.allocate(later).fell_back
    assert len(solutions) == 2
    model = allocator._model(later)
    for solution in solutions:
        assert_states_of(model, later, solution.states, solution.inputs)
    plan = allocator._state.plan
    assert_states_of(model, later, plan.states, plan.inputs)
    # Another allocator solving on the same (shared) model leaves this plan alone.
    get_allocator("nmpc", **SMALL).allocate(random_problem(np.random.default_rng(seed + 100), 5))
    assert_states_of(model, later, plan.states, plan.inputs)


@pytest.mark.parametrize("seed", [1, 4])
def test_a_stalled_solve_returns_the_states_of_the_inputs_it_returns(seed):
    """Run to a stall (no tolerance, many iterations): the line search's rejected trials are
    simulated after the last accepted iterate, and the solution holds that iterate's states,
    not the last trial's."""
    problem = random_problem(np.random.default_rng(seed), 5)
    allocator = get_allocator("nmpc", **SMALL)
    model = allocator._model(problem)
    low, high = allocator._input_bounds(problem)
    start = np.clip(allocator._rollout_inputs(problem, model), low, high)
    p = allocator._parameters(problem, model, start[0, :, 0])
    solution = solve.sqp(problem, model, start, p, low, high, max_iterations=60, step_tolerance=0.0)
    assert solution.status == "stalled"
    assert_states_of(model, problem, solution.states, solution.inputs)
