from dataclasses import replace

import numpy as np
import pytest

from platoon_opt import integrated_errors, load_scenario, simulate
from platoon_opt.host_loop import scenario_controller
from platoon_opt.scenarios import PAPER_SCENARIOS, TargetPath
from platoon_opt.solvers import get_allocator
from tests.conftest import NominalAllocator, scenario_text


@pytest.mark.parametrize("name", PAPER_SCENARIOS)
def test_paper_scenarios_load_and_start_as_specified(name):
    scenario = load_scenario(name)
    for seed in range(3):
        state, obstacles = scenario.initial(seed)
        assert state.n == 8
        np.testing.assert_allclose(state.positions.var(axis=0, ddof=1), [0.6384, 0.5536], rtol=1e-12)
        np.testing.assert_allclose(state.positions.mean(axis=0), scenario.center, atol=1e-12)
        np.testing.assert_array_equal(state.alpha, 0.0)
    assert (len(obstacles) > 0) == (name == "paper_obstacles")
    if name == "paper_no_obstacles":
        np.testing.assert_allclose(state.theta, np.pi / 2)


def test_seed_varies_only_what_the_scenario_says():
    scenario = load_scenario("paper_obstacles")
    a, obstacles_a = scenario.initial(1)
    b, obstacles_b = scenario.initial(2)
    assert not np.allclose(a.theta, b.theta)
    assert not np.allclose(obstacles_a.centers, obstacles_b.centers)
    np.testing.assert_array_equal(obstacles_a.radii, obstacles_b.radii)
    again, _ = scenario.initial(1)
    np.testing.assert_array_equal(a.x, again.x)


def test_target_path_moves_at_constant_speed_and_holds_at_the_end():
    path = TargetPath(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]), 0.5)
    assert path.length == 7.0
    np.testing.assert_allclose(path.at(2.0)[0], [1.0, 0.0])
    np.testing.assert_allclose(path.at(8.0)[0], [3.0, 1.0])
    np.testing.assert_allclose(path.at(8.0)[1], [0.0, 0.5])
    np.testing.assert_allclose(path.at(100.0)[0], [3.0, 4.0])
    np.testing.assert_allclose(path.at(100.0)[1], 0.0)


@pytest.mark.parametrize("name", PAPER_SCENARIOS)
def test_smoke_short_horizon_and_determinism(name):
    scenario = load_scenario(name)
    allocator = NominalAllocator()
    first = simulate(scenario, allocator, seed=3, duration=2.0)
    second = simulate(scenario, allocator, seed=3, duration=2.0)
    np.testing.assert_array_equal(first.x, second.x)
    np.testing.assert_array_equal(first.theta, second.theta)
    assert first.steps == 200
    metrics = integrated_errors(first, scenario.transient)
    for key in (
        "mean_position",
        "var_x",
        "var_y",
        "mean_position_after_transient",
        "gear_flips",
        "min_clearance",
    ):
        assert key in metrics
    assert metrics["mean_position_after_transient"] == 0.0  # 2 s is all transient
    assert np.isfinite(metrics["mean_position"]) and metrics["mean_position"] > 0
    assert np.all(np.abs(first.alpha) <= scenario.limits.max_steering + 1e-12)


@pytest.mark.parametrize("name, allocator", [("paper_obstacles", "iterative"), ("paper_covariance", "nmpc")])
def test_the_host_loop_is_the_controllers_step_after_step(name, allocator):
    """The host loop's one compiled call per step (move, then pose the next problem) gives the
    run that ``PlatoonController.step`` gives step after step (pose, allocate, move), with an
    allocator that plans ahead too (its f_d ahead). The iteration and the plan are exact
    arithmetic: the two agree to rounding."""
    scenario = load_scenario(name)
    chosen = get_allocator(allocator)
    run = simulate(scenario, chosen, seed=1, duration=1.0, compiled=False)
    state, obstacles = scenario.initial(1)
    controller = scenario_controller(scenario, chosen, obstacles)
    goal = scenario.goal(controller.task.names)
    for k in range(run.steps):
        t = k * scenario.dt
        np.testing.assert_allclose(state.x, run.x[k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(state.y, run.y[k], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(state.gear, run.gear[k])
        desired, rate, _ = goal.at(t)
        result = controller.step(state, desired, rate, scenario.dt, t)
        assert result.allocation.status == run.status[k]
        state = result.state
    np.testing.assert_allclose(state.theta, run.theta[-1], rtol=0, atol=1e-12)


def test_integrated_errors_on_a_known_signal():
    scenario = load_scenario("paper_no_obstacles")
    trajectory = simulate(scenario, NominalAllocator(), duration=0.5)
    # Replace the run by a platoon that sits 0.2 m east of the target with var_x off by 0.1.
    shifted = replace(
        trajectory,
        x=trajectory.target[:, [0]] + 0.2 + np.zeros_like(trajectory.x),
        y=trajectory.target[:, [1]] + np.zeros_like(trajectory.y),
        task_value=trajectory.desired + np.array([0.0, 0.1, 0.0, 0.0]),
    )
    metrics = integrated_errors(shifted, transient=0.2)
    np.testing.assert_allclose(metrics["mean_position"], 0.2 * 0.5)
    np.testing.assert_allclose(metrics["mean_position_after_transient"], 0.2 * 0.3)
    np.testing.assert_allclose(metrics["var_x"], 0.1 * 0.5)
    np.testing.assert_allclose(metrics["var_y"], 0.0)


def test_compute_time_per_step_and_per_solve():
    """Per step: every step's allocation time; per solve: the steps that ran a solve alone (an
    allocator reusing its last solve, as nmpc handing its plan, marks the others)."""
    trajectory = simulate(load_scenario("paper_no_obstacles"), NominalAllocator(), duration=0.1)
    assert trajectory.solved.shape == (10,) and trajectory.solved.all()
    solved = np.arange(10) % 5 == 0
    reused = replace(trajectory, solve_time=np.where(solved, 0.02, 1e-5), solved=solved)
    metrics = integrated_errors(reused)
    assert metrics["solve_time_median"] == 1e-5 and metrics["solve_time_p95"] == pytest.approx(0.02)
    assert metrics["solve_steps"] == 2
    assert metrics["solve_time_per_solve_median"] == metrics["solve_time_per_solve_p95"] == 0.02
    # A trajectory built without the record (None): every step solved.
    legacy = replace(reused, solved=None)
    assert legacy.solved.shape == (10,) and legacy.solved.all()
    assert integrated_errors(legacy)["solve_time_per_solve_median"] == metrics["solve_time_median"]
    nothing = integrated_errors(replace(reused, solved=np.zeros(10, dtype=bool)))
    assert nothing["solve_steps"] == 0 and np.isnan(nothing["solve_time_per_solve_median"])


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("[avoidance]", "[avoidance]\nbogus = 1", "unknown key avoidance.bogus"),
        ("n = 8", 'n = "eight"', "platoon.n must be an integer"),
        ("n = 8", "n = 1", "platoon.n must be >= 2"),
        ("speed = 0.8", "", "missing key target.speed"),
        ("d_mino = 3.0", "d_mino = 0.0", "avoidance.d_mino must be > 0"),
        ("var_y = 0.5536", "", "missing key task.desired.var_y"),
        ('kind = "mean_variance"', 'kind = "nope"', "task.kind must be one of"),
    ],
)
def test_scenario_errors_name_file_key_and_value(tmp_path, old, new, message):
    from platoon_opt import ScenarioError

    path = tmp_path / "s.toml"
    text = scenario_text("paper_no_obstacles")
    assert old in text
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ScenarioError, match=message) as info:
        load_scenario(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
