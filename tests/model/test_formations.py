"""Initial formations, headings, the target's start offset and random obstacle fields
(``formations``, ``obstacle_fields``, ``Scenario.initial``): what a seed draws, that it draws it
the same way every time, and that the promised variances and gaps hold."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt import ScenarioError, curves, load_scenario
from platoon_opt.scenarios import parse_scenario, tomllib
from tests.conftest import scenario_text

BASE = """
name = "t"
[simulation]
dt = 0.01
duration = 10.0
[platoon]
n = {n}
{platoon}
[target]
{target}
[task]
kind = "mean_variance"
gains = [50.0, 10.0, 50.0, 10.0]
[task.desired]
var_x = 0.6
var_y = 0.5
{extra}
"""
PATH = 'kind = "spline"\nspeed = 0.7\nwaypoints = [[0.0, 0.0], [8.0, 2.0], [14.0, -3.0], [20.0, 1.0]]'


def scenario(platoon="center = [0.0, 0.0]\nvariance = [0.6, 0.5]", target=PATH, extra="", n=12):
    text = BASE.format(n=n, platoon=platoon, target=target, extra=extra)
    return parse_scenario(tomllib.loads(text), "t.toml")


@pytest.mark.parametrize("formation", ["ring", "disk", "grid", "line"])
@pytest.mark.parametrize("n", [3, 12, 50])
def test_every_formation_meets_the_variances_around_the_centre(formation, n):
    sc = scenario(f'formation = "{formation}"\ncenter = [1.0, -2.0]\nvariance = [0.6, 2.5]', n=n)
    for seed in range(3):
        positions = sc.initial(seed)[0].positions
        np.testing.assert_allclose(positions.mean(axis=0), [1.0, -2.0], atol=1e-12)
        np.testing.assert_allclose(positions.var(axis=0, ddof=1), [0.6, 2.5], rtol=1e-12)
        distance = np.linalg.norm(positions[:, None] - positions[None], axis=2) + np.eye(n)
        assert distance.min() > 1e-3


def test_a_seed_draws_a_disk_the_same_way_and_others_differently():
    sc = scenario('formation = "disk"\ncenter = [0.0, 0.0]\nvariance = [0.6, 0.5]', n=40)
    a, b, again = sc.initial(1)[0], sc.initial(2)[0], sc.initial(1)[0]
    np.testing.assert_array_equal(a.positions, again.positions)
    assert not np.allclose(a.positions, b.positions)
    grid = scenario('formation = "grid"\ncenter = [0.0, 0.0]\nvariance = [0.6, 0.5]', n=40)
    np.testing.assert_array_equal(grid.initial(1)[0].positions, grid.initial(2)[0].positions)


def test_a_line_lies_on_one_line_and_a_grid_on_rows():
    line = scenario('formation = "line"\ncenter = [0.0, 0.0]\nvariance = [0.6, 0.5]', n=7).initial(0)[0]
    offsets = line.positions - line.positions.mean(axis=0)
    cross = offsets[:, 0] * np.sqrt(0.5) - offsets[:, 1] * np.sqrt(0.6)
    np.testing.assert_allclose(cross, 0.0, atol=1e-12)
    grid = scenario('formation = "grid"\ncenter = [0.0, 0.0]\nvariance = [0.6, 0.5]', n=7).initial(0)[0]
    assert len(np.unique(np.round(grid.y, 9))) == 3 and len(np.unique(np.round(grid.x, 9))) == 3


def test_explicit_positions_are_used_as_given():
    sc = scenario('formation = "explicit"\npositions = [[0.0, 0.0], [1.0, 0.5], [-1.0, 2.0]]', n=3)
    state, _ = sc.initial(5)
    np.testing.assert_array_equal(state.positions, [[0.0, 0.0], [1.0, 0.5], [-1.0, 2.0]])
    np.testing.assert_allclose(sc.center, [0.0, 2.5 / 3])
    np.testing.assert_allclose(sc.variance, state.positions.var(axis=0, ddof=1))


def test_headings_fixed_random_and_toward_the_target():
    fixed = scenario("center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nheading = 0.3").initial(0)[0]
    np.testing.assert_array_equal(fixed.theta, 0.3)
    toward = scenario('center = [-3.0, 1.0]\nvariance = [0.6, 0.5]\nheadings = "toward_target"').initial(0)[0]
    facing = np.column_stack((np.cos(toward.theta), np.sin(toward.theta)))
    to_start = -toward.positions / np.linalg.norm(toward.positions, axis=1, keepdims=True)
    np.testing.assert_allclose(facing, to_start, atol=1e-12)
    # "random" is what seed.headings = true always meant: the same draws.
    old = scenario("center = [0.0, 0.0]\nvariance = [0.6, 0.5]", extra="[seed]\nheadings = true")
    new = scenario('center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nheadings = "random"')
    for seed in range(3):
        np.testing.assert_array_equal(old.initial(seed)[0].theta, new.initial(seed)[0].theta)


def test_a_start_offset_places_the_platoon_behind_the_target_start():
    target = 'kind = "circle"\ncenter = [0.0, 5.0]\nradius = 5.0\nspeed = 0.7\nstart_offset = [2.0, -1.0]'
    sc = scenario("variance = [0.6, 0.5]", target=target)
    start = np.array([0.0, 0.0])  # the circle's lowest point (start_angle_deg = -90)
    np.testing.assert_allclose(sc.center, start - [2.0, -1.0], atol=1e-14)
    np.testing.assert_allclose(sc.initial(4)[0].positions.mean(axis=0), sc.center, atol=1e-12)
    # The same as giving the centre.
    same = scenario("center = [-2.0, 1.0]\nvariance = [0.6, 0.5]", target=target.rsplit("\n", 1)[0])
    np.testing.assert_allclose(same.initial(4)[0].positions, sc.initial(4)[0].positions, atol=1e-14)


def test_the_paper_offset_files_are_the_paper_files_moved():
    for name in ("paper_no_obstacles", "paper_obstacles"):
        paper, moved = load_scenario(name), load_scenario(f"{name}_offset")
        for seed in range(3):
            (a, oa), (b, ob) = paper.initial(seed), moved.initial(seed)
            np.testing.assert_allclose(b.positions, a.positions - [1.0, 0.0], atol=1e-14)
            np.testing.assert_array_equal(b.theta, a.theta)
            np.testing.assert_array_equal(ob.centers, oa.centers)


FIELD = """
[obstacle_field]
count = {count}
radius_range = [0.3, 0.6]
region = [-2.0, -6.0, 22.0, 6.0]
path_gap = 0.5
start_gap = 1.5
obstacle_gap = 0.8
"""
FIXED = "[[obstacles]]\ncenter = [10.0, 4.0]\nradius = 0.5\n"


def _path_distance(sc, points):
    """Distance from ``points`` to the spline sampled at 200,000 parameter values (< 0.2 mm apart)."""
    path = sc.target
    u = np.linspace(path.knots[0], path.knots[-1], 200_000)
    curve = curves.curve(path.shape, path.coefficients, path.knots, u)[0]
    return np.array([np.min(np.linalg.norm(curve - p, axis=1)) for p in points])


def test_an_obstacle_field_keeps_its_gaps_and_its_count_for_every_seed():
    sc = scenario(extra=FIELD.format(count=12) + FIXED + "[seed]\nobstacle_jitter = 0.2\n")
    for seed in range(4):
        state, obstacles = sc.initial(seed)
        assert len(obstacles) == 13
        centers, radii = obstacles.centers[1:], obstacles.radii[1:]
        assert np.all((radii >= 0.3) & (radii <= 0.6))
        assert np.all(centers - radii[:, None] >= [-2.0, -6.0]) and np.all(
            centers + radii[:, None] <= [22.0, 6.0]
        )
        to_units = np.linalg.norm(centers[:, None] - state.positions[None], axis=2).min(axis=1)
        assert np.all(to_units - radii >= 1.5)
        gaps = np.linalg.norm(obstacles.centers[:, None] - obstacles.centers[None], axis=2)
        gaps -= obstacles.radii[:, None] + obstacles.radii[None]
        assert np.all(gaps + np.eye(13) * 1e9 >= 0.8 - 1e-12)
        assert np.all(_path_distance(sc, centers) - radii >= 0.5 - 1e-3)  # the path's sampling
    np.testing.assert_array_equal(sc.initial(2)[1].centers, sc.initial(2)[1].centers)
    assert not np.allclose(sc.initial(2)[1].centers, sc.initial(3)[1].centers)


def test_a_field_leaves_the_seeds_other_draws_alone():
    plain = scenario(extra=FIXED + "[seed]\nobstacle_jitter = 0.2\nheadings = true\n")
    field = scenario(extra=FIELD.format(count=5) + FIXED + "[seed]\nobstacle_jitter = 0.2\nheadings = true\n")
    (a, oa), (b, ob) = plain.initial(7), field.initial(7)
    np.testing.assert_array_equal(a.theta, b.theta)
    np.testing.assert_array_equal(oa.centers, ob.centers[:1])


def test_a_field_that_does_not_fit_is_refused_naming_its_keys():
    with pytest.raises(
        ScenarioError, match=r"^t\.toml: obstacle_field\.count must be small enough .*got 600$"
    ):
        scenario(extra=FIELD.format(count=600))
    # Room by area, none by the gaps: refused when a seed draws it.
    crowded = scenario(extra=FIELD.format(count=150))
    with pytest.raises(
        ScenarioError,
        match=r"^t\.toml: obstacle_field\.count must be placeable: obstacle \d+ .*seed 0.*got 150$",
    ):
        crowded.initial(0)


def test_the_shipped_fields_are_drawn_for_many_seeds():
    for name in ("field_sparse", "field_dense", "curved_field_16"):
        sc = load_scenario(name)
        counts = {len(sc.initial(seed)[1]) for seed in range(20)}
        assert counts == {sc.obstacle_field.count + len(sc.obstacles)}


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(2, 60),
    variance=st.tuples(st.floats(1e-3, 1e3), st.floats(1e-3, 1e3)),
    seed=st.integers(0, 2**32),
)
def test_a_disk_of_any_size_meets_its_variances(n, variance, seed):
    sc = scenario(
        f'formation = "disk"\ncenter = [0.0, 0.0]\nvariance = [{variance[0]!r}, {variance[1]!r}]', n=n
    )
    positions = sc.initial(seed)[0].positions
    np.testing.assert_allclose(positions.var(axis=0, ddof=1), variance, rtol=1e-10)


def test_paper_covariance_still_starts_on_the_ring():
    text = scenario_text("paper_covariance")
    sc = parse_scenario(tomllib.loads(text), "c.toml")
    assert sc.formation == "ring" and sc.vary_ring_phase and sc.headings == "fixed"
