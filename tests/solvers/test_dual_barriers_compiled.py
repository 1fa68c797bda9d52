"""The compiled engine with barrier constraints (``safety="barrier"``: the dual's programs, both
readings, and the iteration through the safety filter): the host loop's trajectories, slacks and
standing units; a run whose constraints overflow the kernel's capacity runs in the host loop; the
sizes and options the kernel does not take have no kernel."""

from __future__ import annotations

import numpy as np
import pytest
import tomllib

from platoon_opt import simulation
from platoon_opt.engine import compiled_step
from platoon_opt.metrics import integrated_errors
from platoon_opt.scenarios import load_scenario, parse_scenario
from platoon_opt.simulation import simulate, simulate_batch
from platoon_opt.solvers import get_allocator

FIELDS = ("x", "y", "theta", "alpha", "gear")


def _barrier(name: str):
    if name == "iterative":
        return get_allocator(name, safety="barrier")
    return get_allocator(name, backend="dual", safety="barrier", rate_aware=True)


def _scenario(positions, duration=1.0):
    """Units placed by hand on a straight path at 0.5 m/s, barriers from the scenario file."""
    text = f"""
name = "placed"
[simulation]
dt = 0.01
duration = {duration}
transient = 0.1
[platoon]
n = {len(positions)}
formation = "explicit"
positions = {positions}
[target]
kind = "polyline"
speed = 0.5
waypoints = [[0.0, 0.0], [10.0, 0.0]]
[task]
kind = "mean_variance"
gains = [50.0, 10.0, 50.0, 10.0]
[task.desired]
var_x = 0.5
var_y = 0.5
[safety]
mode = "barrier"
"""
    return parse_scenario(tomllib.loads(text))


def _same(compiled, hosted, atol):
    assert compiled.compiled and not hosted.compiled
    for field in FIELDS:
        np.testing.assert_allclose(getattr(compiled, field), getattr(hosted, field), rtol=0, atol=atol)
    np.testing.assert_array_equal(compiled.status, hosted.status)
    np.testing.assert_array_equal(compiled.slack, hosted.slack)


@pytest.mark.parametrize(
    ("scenario", "name"),
    [
        ("paper_obstacles", "qp"),
        ("paper_obstacles", "cone"),
        ("field_dense", "cone"),
        ("paper_obstacles", "cone-projection"),
        ("paper_obstacles", "iterative"),
    ],
)
def test_a_compiled_run_with_barriers_is_the_host_loop_run(scenario, name):
    """Both build the same safe sets (to rounding: numpy against XLA), hand out alike
    (``safe_handout``: the task-exact reading and the safety filter) and steer standing units
    alike; seed 0 of paper_obstacles has a unit standing on its first step."""
    loaded = load_scenario(scenario)
    compiled = simulate(loaded, _barrier(name), seed=0, duration=1.5)
    hosted = simulate(loaded, _barrier(name), seed=0, duration=1.5, compiled=False)
    _same(compiled, hosted, 1e-9)
    scores, reference = integrated_errors(compiled), integrated_errors(hosted)
    for key in ("mean_position", "var_x", "var_y", "min_unit_distance", "min_clearance", "slack_steps"):
        assert scores[key] == pytest.approx(reference[key], rel=1e-9, abs=1e-12)


def test_an_unsafe_start_is_relaxed_in_the_engine_as_on_the_host():
    """Two units 0.2 m apart (the safety distance is 0.3 m): their rows are relaxed (a slack)
    until they part, on the same steps in both loops."""
    scenario = _scenario([[0.0, 0.0], [0.2, 0.0], [-1.0, 1.0]])
    compiled = simulate(scenario, _barrier("qp"), seed=0)
    hosted = simulate(scenario, _barrier("qp"), seed=0, compiled=False)
    assert compiled.slack[0] == 2 and integrated_errors(compiled)["slack_steps"] > 0
    # The sets differ in their last bits (numpy against XLA), so Newton's iterates do, and its
    # answers agree to its tolerance: they part by 4e-13 rad of steering on step 37, and by the
    # end of the run are 4e-10 m and 2e-8 rad apart (3e-9 rad with the earlier projection, whose
    # rounding differed: docs/safety.md, section 4).
    _same(compiled, hosted, 1e-7)


def test_a_run_beyond_the_capacity_runs_in_the_host_loop():
    """Eight units 0.33 m apart on a grid: the middle one has seven neighbours within reach,
    whose rows (three robust rows each) are more than the kernel's 12. The run is the host loop's,
    and says so."""
    grid = [[0.33 * (i % 3), 0.33 * (i // 3)] for i in range(8)]
    scenario = _scenario(grid, duration=0.3)
    allocator = _barrier("cone")
    assert compiled_step(allocator, scenario) is not None
    run = simulate(scenario, allocator, seed=0)
    hosted = simulate(scenario, _barrier("cone"), seed=0, compiled=False)
    assert not run.compiled
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(run, field), getattr(hosted, field))


def test_simulate_batch_runs_an_overflowed_run_in_the_host_loop(monkeypatch):
    """The batch's routing, on the iteration's cheap kernel: the run marked overflowed gets the
    host loop's scores to the bit, the other its compiled ones (to rounding: a batch's program is
    compiled for 32 platoons, a single run's for one)."""
    scenario = load_scenario("paper_obstacles")
    allocator = get_allocator("iterative", max_iterations=2)
    monkeypatch.setattr(simulation, "overflowed", lambda batch, index: index == 1)
    batched = simulate_batch(scenario, allocator, [3, 1], duration=0.3)
    for seed, scores, compiled in zip((3, 1), batched, (True, False)):
        run = simulate(scenario, allocator, seed=seed, duration=0.3, compiled=compiled)
        reference = integrated_errors(run, scenario.transient)
        for key in ("mean_position", "var_x", "var_y", "min_unit_distance"):
            assert scores[key] == (pytest.approx(reference[key], rel=1e-9) if compiled else reference[key])


def test_options_that_fail_their_check_have_no_kernel():
    """They run on the host, which reports them; every reading and size has a kernel."""
    paper = load_scenario("paper_obstacles")
    for name in ("qp", "qp-projection", "iterative"):
        assert compiled_step(_barrier(name), paper) is not None
        assert compiled_step(_barrier(name), load_scenario("units_50")) is not None
    unguarded = get_allocator("iterative", safety="barrier", neighbour_cutoff=0.31)
    assert compiled_step(unguarded, paper) is None


def test_a_batch_with_barriers_scores_each_seed_as_the_host_loop():
    """In a batch a step searches standing units' targets and blocked units' ways out when some
    platoon needs them (``arrays.any_platoon``); every other platoon keeps its velocities. Seed 0
    has a unit standing on its first step."""
    scenario = load_scenario("paper_obstacles")
    assert compiled_step(_barrier("iterative"), scenario) is not None
    batched = simulate_batch(scenario, _barrier("iterative"), [0, 3], duration=1.0)
    for seed, scores in zip((0, 3), batched):
        hosted = simulate(scenario, _barrier("iterative"), seed=seed, duration=1.0, compiled=False)
        reference = integrated_errors(hosted, scenario.transient)
        for key in ("mean_position", "var_x", "var_y", "min_unit_distance", "min_clearance"):
            assert scores[key] == pytest.approx(reference[key], rel=1e-9, abs=1e-12)
