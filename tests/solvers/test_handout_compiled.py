"""The safety handout traced (``solvers/safety.filtered`` and ``safe_handout`` in a capacity, as
the compiled engine runs them for the iteration and the task-exact reading with barriers): the
host's velocities, held and escaping units, blocked units' ways out included."""

from __future__ import annotations

import jax
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt import AllocationProblem
from platoon_opt.arrays import unchecked
from platoon_opt.barrier_constraints import Capacity
from platoon_opt.solvers.safety import filtered
from tests.conftest import padded_safe_state, safe_problem

# Enough for every state of ``safe_problem``: at most 3 obstacles and 8 units.
ROOMY = Capacity(obstacles=3, neighbours=7, rows=40)


def _filtered(state, obstacles, velocity, limits, dt, params):
    # What the handout reads of a problem: the state, the obstacles, the vehicles and the step.
    problem = unchecked(AllocationProblem, state=state, obstacles=obstacles, limits=limits, dt=dt)
    handout, safe = filtered(problem, params, velocity, capacity=ROOMY)
    return handout, safe.overflow


FILTERED = jax.jit(_filtered, static_argnames=("limits", "dt", "params"))


def _both(seed):
    """The host's handout of a random velocity on a crowded ``safe_problem`` and the compiled
    one (its far padding units cut off)."""
    problem = safe_problem(seed, crowded=True)
    n = problem.n
    velocity = np.random.default_rng(seed).normal(0, 1.0, (n, 2))
    host, _ = filtered(problem, problem.safety, velocity)
    state, obstacles, _ = padded_safe_state(problem.state, problem, problem.state.gear)
    padded = np.concatenate((velocity, np.zeros((8 - n, 2))))
    compiled, overflow = FILTERED(state, obstacles, padded, problem.limits, problem.dt, problem.safety)
    assert not np.any(overflow) and not compiled.overflow
    return host, compiled._replace(velocities=np.asarray(compiled.velocities)[:n])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_the_compiled_handout_is_the_hosts(seed):
    """The same velocities to rounding (the sets differ in their last bits: numpy against XLA),
    the same counts of held and escaping units."""
    host, compiled = _both(seed)
    np.testing.assert_allclose(compiled.velocities, host.velocities, rtol=0, atol=1e-12)
    assert int(compiled.held) == host.held and int(compiled.escaping) == host.escaping


def test_blocked_units_escape_among_the_compared():
    """The comparison above meets blocked units given a way out (``escape``), traced over every
    unit."""
    escaping = 0
    for seed in range(40):
        host, compiled = _both(seed)
        np.testing.assert_allclose(compiled.velocities, host.velocities, rtol=0, atol=1e-12)
        escaping += int(compiled.escaping)
    assert escaping > 0
