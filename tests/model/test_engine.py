"""The compiled engine runs the model of the host loop: the same trajectories, one platoon or a
batch, and the same scores."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from platoon_opt.engine import Plant, compiled_step, run_batch
from platoon_opt.metrics import integrated_errors, score
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate, simulate_batch
from platoon_opt.solvers import get_allocator

FIELDS = ("x", "y", "theta", "alpha", "gear")


@pytest.mark.parametrize("scenario", ["paper_no_obstacles", "paper_obstacles"])
@pytest.mark.parametrize("options", [{"max_iterations": 0}, {"max_iterations": 5}, {"gears": "model"}])
def test_compiled_run_equals_the_host_loop(scenario, options):
    allocator = get_allocator("iterative", **options)
    loaded = load_scenario(scenario)
    compiled = simulate(loaded, allocator, seed=4, duration=1.5, compiled=True)
    hosted = simulate(loaded, allocator, seed=4, duration=1.5, compiled=False)
    assert compiled.compiled and not hosted.compiled
    for field in FIELDS:
        np.testing.assert_allclose(getattr(compiled, field), getattr(hosted, field), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(compiled.status, hosted.status)
    np.testing.assert_array_equal(compiled.iterations, hosted.iterations)
    np.testing.assert_allclose(compiled.task_residual, hosted.task_residual, rtol=1e-9, atol=1e-12)
    scores, reference = integrated_errors(compiled), integrated_errors(hosted)
    for key in ("mean_position", "var_x", "var_y", "min_unit_distance", "min_clearance", "gear_flips"):
        assert scores[key] == pytest.approx(reference[key], rel=1e-12, abs=1e-14)


def test_a_batch_equals_its_platoons_run_one_by_one():
    scenario = load_scenario("paper_obstacles")
    allocators = [get_allocator("iterative", max_iterations=m) for m in (0, 2, 7)]
    steps = [compiled_step(allocator, scenario) for allocator in allocators]
    assert len({(step.kernel, step.static) for step in steps}) == 1  # m is a number, not a program
    seeds = (0, 5, 9)
    starts = [scenario.initial(seed) for seed in seeds]
    plant = Plant.of(scenario)
    batch = run_batch(
        steps[0],
        plant,
        [s for s, _ in starts],
        [o for _, o in starts],
        150,
        params=[step.params for step in steps],
        record=[0, 1, 2],
    )
    for i, (step, (state, obstacles)) in enumerate(zip(steps, starts)):
        alone = run_batch(step, plant, [state], [obstacles], 150, record=[0])
        for field in FIELDS:
            np.testing.assert_array_equal(
                getattr(batch.record.state, field)[i], getattr(alone.record.state, field)[0]
            )
        np.testing.assert_array_equal(batch.steps.iterations[i], alone.steps.iterations[0])
    # Two platoons compiled for three (the last repeated): the batch's program, the same results.
    padded = run_batch(
        steps[0],
        plant,
        [s for s, _ in starts[:2]],
        [o for _, o in starts[:2]],
        150,
        params=[step.params for step in steps[:2]],
        record=[1],
        size=3,
        record_size=2,
    )
    assert padded.record.state.x.shape[0] == 1 and padded.recorded == (1,)
    np.testing.assert_array_equal(padded.record.state.x[0], batch.record.state.x[1])
    np.testing.assert_array_equal(padded.instants.mean_distance, batch.instants.mean_distance[:2])


def test_the_scores_of_a_batch_are_those_of_its_recorded_trajectory():
    scenario = load_scenario("paper_obstacles")
    allocator = get_allocator("iterative", max_iterations=3)
    trajectory = simulate(scenario, allocator, seed=2, duration=6.0)
    step = compiled_step(allocator, scenario)
    state, obstacles = scenario.initial(2)
    batch = run_batch(step, Plant.of(scenario), [state], [obstacles], trajectory.steps)
    instants = jax.tree_util.tree_map(lambda a: a[0], batch.instants)
    count = trajectory.steps
    scores = score(
        instants,
        dt=scenario.dt,
        transient=4.0,
        names=trajectory.task_names,
        gear_flips=int(batch.steps.flips[0].sum()),
        fell_back=batch.steps.fell_back[0],
        program_changed=batch.steps.program_changed[0],
        slack=np.zeros(count),
        solved=np.ones(count, dtype=bool),
        solve_time=np.full(count, np.nan),
    )
    reference = integrated_errors(trajectory)
    # Sampled inside the loop or afterwards from the record, the same arithmetic compiled apart.
    for key in ("mean_position", "mean_position_after_transient", "var_x", "var_y_after_transient"):
        assert scores[key] == pytest.approx(reference[key], rel=1e-12)
    for key in ("min_clearance", "min_unit_distance"):
        assert scores[key] == pytest.approx(reference[key], rel=1e-14)
    for key in ("gear_flips", "time_inside_obstacles", "fallback_steps"):
        assert scores[key] == reference[key]


def test_a_batch_needs_one_obstacle_set_per_platoon():
    scenario = load_scenario("paper_obstacles")
    step = compiled_step(get_allocator("iterative"), scenario)
    state, obstacles = scenario.initial(0)
    with pytest.raises(ValueError, match="one obstacle set per initial state"):
        run_batch(step, Plant.of(scenario), [state, state], [obstacles], 10)


def test_host_solvers_and_host_tasks_have_no_kernel():
    scenario = load_scenario("paper_obstacles")
    assert compiled_step(get_allocator("qp"), scenario) is None
    symbolic = dataclasses.replace(load_scenario("paper_covariance"), task_kind="symbolic_covariance")
    assert compiled_step(get_allocator("iterative"), symbolic) is None
    with pytest.raises(ValueError, match="no compiled kernel"):
        simulate(scenario, get_allocator("qp"), duration=0.1, compiled=True)


def test_simulate_batch_scores_each_seed_as_simulate_does():
    scenario = load_scenario("paper_obstacles")
    for allocator in (get_allocator("iterative", max_iterations=2), get_allocator("qp")):
        batch = simulate_batch(scenario, allocator, seeds=[3, 1], duration=0.5)
        for seed, scores in zip((3, 1), batch):
            alone = integrated_errors(
                simulate(scenario, allocator, seed=seed, duration=0.5), scenario.transient
            )
            for key in ("mean_position", "var_x", "var_y", "min_unit_distance", "gear_flips"):
                assert scores[key] == pytest.approx(alone[key], rel=1e-12), key
