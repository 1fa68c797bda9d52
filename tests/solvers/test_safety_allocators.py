"""Every allocator with ``safety="barrier"``: after its allocation and one step of the real vehicle
model every unit is still outside every inflated obstacle and every pair at least the safety
distance apart (docs/safety.md); the options and the scenario table."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.errors import OptionError
from platoon_opt.safety import SafetyParams
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.safety import BLOCKED_SHARE, clear_of_obstacles, keeps_barriers
from platoon_opt.vehicle import STANDING_SPEED, choose_gear
from tests.conftest import barrier_margin, safe_problem

# One allocator object per configuration: their workspaces and warm starts carry over between
# examples, as between the steps of a run.
CONFIGURATIONS = {
    "qp": {},
    "qp rate-aware": {"rate_aware": True},
    "qp-projection": {},
    "qp-projection rate-aware": {"rate_aware": True},
    "cone": {},
    "cone-projection": {},
    "cone-projection rate-aware": {"rate_aware": True},
    "qp-projection rate-aware either gear": {"rate_aware": True, "gears": "either"},
    "casadi-qp": {},
    "dual": {},
    "dual task-exact cone": {"reading": "task-exact", "speed": "cone"},
    "dual rate-aware": {"rate_aware": True},
    "dual task-exact either gear": {"reading": "task-exact", "gears": "either"},
    "iterative": {"max_iterations": 4},
    "nmpc": {"intervals": 4},
}
ALLOCATORS = {
    name: get_allocator(name.split()[0], safety="barrier", **options)
    for name, options in CONFIGURATIONS.items()
}


@pytest.mark.parametrize("name", list(ALLOCATORS))
@settings(max_examples=1000)
@given(seed=st.integers(0, 2**32 - 1), crowded=st.booleans())
def test_the_allocation_keeps_every_barrier_through_the_vehicle_model(name, seed, crowded):
    problem = safe_problem(seed, crowded=crowded, safety=SafetyParams(barrier_rate=[0.1, 0.5, 1.0][seed % 3]))
    allocation = ALLOCATORS[name].allocate(problem)
    assert np.isfinite(allocation.velocities).all()
    assert allocation.info["slack_units"] == 0
    if not name.startswith(("nmpc", "dual")):
        # Every convex program is feasible from a safe state: it is solved as asked (by its backend,
        # or where Clarabel ends "AlmostSolved", by the dual's exact solve of the same program).
        assert not allocation.program_changed, allocation.status
    assert barrier_margin(problem, allocation.velocities, ALLOCATORS[name].safety_for(problem)) >= -1e-12


def test_the_scenario_table_switches_barriers_on_and_an_option_overrides_it():
    problem = safe_problem(3, safety=SafetyParams(mode="barrier", safety_distance=0.4))
    assert get_allocator("qp").safety_for(problem).safety_distance == 0.4
    assert get_allocator("qp").safety_for(problem).enabled
    assert not get_allocator("qp", safety="none").safety_for(problem).enabled
    assert get_allocator("iterative", safety_distance=0.35).safety_for(problem).safety_distance == 0.35


def test_a_bad_safety_option_is_one_line():
    with pytest.raises(
        OptionError, match=r"option barrier_rate of qp must be a number > 0 and <= 1 or None, got 2"
    ):
        get_allocator("qp", barrier_rate=2)
    allocator = get_allocator("qp", safety="barrier", neighbour_cutoff=0.31)
    with pytest.raises(OptionError, match="option safety.neighbour_cutoff must be >= "):
        allocator.allocate(safe_problem(0))


def check_handout(allocation, problem, params, kept, wanted, held):
    """Units ``kept`` get ``wanted``, the others ``held``; except blocked ones (``held`` keeps at
    most ``BLOCKED_SHARE`` of ``wanted``'s speed), which stand (zero) or escape: another velocity
    in the safe set of either gear, counted in ``info["escaping_units"]``."""
    velocities = allocation.velocities
    assert np.array_equal(velocities[kept], wanted[kept])
    assert allocation.info["held_units"] == np.count_nonzero(~kept)
    wanted_speed = np.hypot(*wanted.T)
    blocked = (
        ~kept
        & (np.hypot(*held.T) <= np.maximum(STANDING_SPEED, BLOCKED_SHARE * wanted_speed))
        & (wanted_speed > STANDING_SPEED)
    )
    escaped = blocked & np.any(velocities != 0, axis=1)
    assert np.array_equal(velocities[~kept & ~blocked], held[~kept & ~blocked])
    assert not np.any(velocities[blocked & ~escaped])
    assert allocation.info["escaping_units"] == np.count_nonzero(escaped)
    inside = [problem.safe_sets(params, gear=g * problem.gear).violation(velocities) <= 1e-9 for g in (1, -1)]
    assert np.all((inside[0] | inside[1])[escaped])


@pytest.mark.parametrize("name", ["qp-projection", "dual"])
def test_a_task_exact_allocation_with_barriers_hands_out_a_where_its_step_keeps_the_barriers(name):
    """a (``task_exact_velocity``) where no obstacle's rows reach the unit and the executed step
    keeps its barrier rows, else its safe achievable part c (or a blocked unit's way out); both
    happen on crowded problems."""
    allocator = get_allocator(name, safety="barrier", **({"reading": "task-exact"} if name == "dual" else {}))
    counts = np.zeros(2, dtype=int)
    for seed in range(30):
        problem = safe_problem(seed, crowded=True)
        allocation = allocator.allocate(problem)
        a, c = allocation.info["task_exact_velocity"], np.asarray(allocation.info["achievable"])
        params = allocator.safety_for(problem)
        safe = problem.safe_sets(params, speed="polygon")
        kept = clear_of_obstacles(problem, params) & keeps_barriers(problem, safe, a)
        check_handout(allocation, problem, params, kept, a, c)
        counts += np.count_nonzero(kept), np.count_nonzero(~kept)
    assert counts.min() > 0, counts


def test_the_safety_filter_passes_a_velocity_whose_step_keeps_the_barriers():
    """The iteration's answer reaches a unit unchanged where no obstacle's rows reach it and its
    executed step keeps its barrier rows; elsewhere it is projected onto the safe set."""
    guarded, plain = get_allocator("iterative", safety="barrier"), get_allocator("iterative", safety="none")
    counts = np.zeros(2, dtype=int)
    for seed in range(30):
        problem = safe_problem(seed, crowded=True)
        allocation, wanted = guarded.allocate(problem), plain.allocate(problem).velocities
        params, state = guarded.safety_for(problem), problem.state
        safe = problem.safe_sets(params, gear=choose_gear(wanted, state.theta, state.gear, problem.limits))
        kept = clear_of_obstacles(problem, params) & keeps_barriers(problem, safe, wanted)
        check_handout(allocation, problem, params, kept, wanted, safe.project(wanted))
        counts += np.count_nonzero(kept), np.count_nonzero(~kept)
    assert counts.min() > 0, counts


def test_the_name_says_barrier():
    assert get_allocator("qp", safety="barrier").name == "qp(rho=1000, clarabel, barrier)"
    assert get_allocator("iterative", safety="barrier").name == "iterative(m=4, barrier)"


@pytest.mark.parametrize(
    "convex, reading, speed",
    [
        ("qp", "achievable-first", "polygon"),
        ("cone", "achievable-first", "cone"),
        ("qp-projection", "task-exact", "polygon"),
        ("cone-projection", "task-exact", "cone"),
    ],
)
@pytest.mark.parametrize("rate_aware", [False, True])
def test_the_dual_solves_the_safe_programs_as_clarabel_does(convex, reading, speed, rate_aware):
    """Objectives to 1e-7 relative (on the scale of one unit off by v_max) wherever Clarabel solved;
    the dual's Newton method reaches its tolerance on every one of these crowded problems (its
    last iterate, handed out if it did not, would still be safe: every iterate is in the sets)."""
    clarabel = get_allocator(convex, safety="barrier", rate_aware=rate_aware, fallbacks=())
    dual = get_allocator("dual", safety="barrier", rate_aware=rate_aware, reading=reading, speed=speed)
    unit = dual.objective_unit(safe_problem(0))
    for seed in range(150):
        problem = safe_problem(seed, crowded=seed % 2 == 0)
        first, second = clarabel.allocate(problem), dual.allocate(problem)
        assert barrier_margin(problem, second.velocities, dual.safety_for(problem)) >= -1e-12
        assert second.status == "optimal", seed
        if first.status == "optimal":
            difference = abs(first.info["objective"] - second.info["objective"])
            assert difference <= 1e-7 * max(abs(first.info["objective"]), unit), seed
