"""The shipped scenario files (platoon_opt/scenario_files/): each loads, says in its header what it
tests, and runs in the compiled engine under the paper's iteration; the engine and the host loop
agree on a curved path through a random field."""

from __future__ import annotations

import numpy as np
import pytest

from platoon_opt.engine import compiled_step
from platoon_opt.scenarios import SCENARIO_DIR, load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator

SHIPPED = sorted(path.stem for path in SCENARIO_DIR.glob("*.toml"))


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_file_loads_and_says_what_it_tests(name):
    scenario = load_scenario(name)
    header = (SCENARIO_DIR / f"{name}.toml").read_text().splitlines()[0]
    assert header.startswith("# ") and scenario.name == name
    state, obstacles = scenario.initial(0)
    assert state.n == scenario.n and np.all(np.isfinite(state.positions))
    assert 10.0 <= scenario.duration <= 90.0  # tens of seconds


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_file_draws_something_per_seed(name):
    # Otherwise its seeds are one run repeated and a study's intervals over them are empty.
    scenario = load_scenario(name)
    (first, first_obstacles), (second, second_obstacles) = scenario.initial(0), scenario.initial(1)
    same_start = np.array_equal(first.positions, second.positions) and np.array_equal(
        first.theta, second.theta
    )
    same_field = np.array_equal(first_obstacles.centers, second_obstacles.centers)
    assert not (same_start and same_field)


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_file_runs_compiled_under_the_papers_iteration(name):
    scenario = load_scenario(name)
    allocator = get_allocator("iterative")
    assert compiled_step(allocator, scenario) is not None
    trajectory = simulate(scenario, allocator, duration=2.0, compiled=True)
    assert trajectory.compiled and trajectory.steps == 200
    assert np.all(np.isfinite(trajectory.x)) and np.all(np.isfinite(trajectory.target))


def test_the_engine_and_the_host_loop_agree_on_a_spline_through_a_field():
    scenario = load_scenario("curved_field_16")
    allocator = get_allocator("iterative")
    compiled = simulate(scenario, allocator, seed=3, duration=1.0, compiled=True)
    hosted = simulate(scenario, allocator, seed=3, duration=1.0, compiled=False)
    for field in ("x", "y", "theta", "target", "desired"):
        np.testing.assert_allclose(getattr(compiled, field), getattr(hosted, field), rtol=0, atol=1e-12)
