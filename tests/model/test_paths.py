"""Target paths of every kind (``paths``, ``curves``): continuous positions, a velocity that is the
exact derivative of the position (against central differences), the asked speed, the same numbers
in numpy and compiled, and holding still at the end."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt import ScenarioError, curves, paths
from platoon_opt.arrays import COMPARE_ALL, searchsorted
from platoon_opt.obstacle_fields import segment_distance
from platoon_opt.scenario_checks import Checks
from platoon_opt.scenario_target import target

# One path of each kind, as a [target] table; the polyline and the rounded path with a speed per leg.
KINDS = {
    "polyline": {"waypoints": [[0, 0], [4, 0], [4, 3], [1, 3], [3, 3]], "speeds": [0.8, 0.5, 0.6, 0.8]},
    "rounded": {
        "kind": "rounded",
        "waypoints": [[0, 0], [6, 0], [6, 5], [1, 7], [3, 1]],
        "turn_radius": 1.2,
        "speeds": [0.8, 0.5, 0.6, 0.7],
    },
    "circle": {"kind": "circle", "center": [1, 2], "radius": 3, "laps": 1.3, "speed": 0.7, "clockwise": True},
    "figure_eight": {"kind": "figure_eight", "center": [0, 0], "size": [12, 5], "laps": 1.5, "speed": 0.8},
    "spline": {
        "kind": "spline",
        "waypoints": [[0, 0], [5, 1], [8, 4], [6, 8], [1, 7]],
        "speeds": [0.8, 0.6, 0.8, 0.5],
    },
}
# The speed of a curve is right to the arc-length table's tolerance; a line or an arc's to rounding.
SPEED_TOLERANCE = {"figure_eight": 2 * curves.SPEED_TOLERANCE, "spline": 2 * curves.SPEED_TOLERANCE}
# Central differences over +-H: the truncation error is H^2 / 6 |p'''| <= 1e-8 * v^3 kappa^2 / 6
# (below 1e-9 m/s here) and the rounding error about 1e-16 |p| / H (1e-11 m/s): 1e-7 m/s bounds both.
H = 1e-4
FD_TOLERANCE = 1e-7


def build(table: dict) -> paths.Path:
    table = {"speed": 0.8, **table} if "speeds" not in table else table
    return target(Checks("test.toml"), table)


def boundaries(path: paths.Path) -> np.ndarray:
    """The times at which the piece (and maybe the speed or the curvature) changes."""
    if isinstance(path, paths.TargetPath):
        legs = np.linalg.norm(np.diff(path.waypoints, axis=0), axis=1)
        return np.concatenate(([0.0], np.cumsum(legs / path.speeds)))
    return np.asarray(path.times)


def evaluate(path: paths.Path, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pairs = [path.at(float(t)) for t in times]
    return np.reshape([p for p, _ in pairs], (-1, 2)), np.reshape([v for _, v in pairs], (-1, 2))


def sample_times(path: paths.Path, count: int = 400) -> np.ndarray:
    """Times spread over the run and the hold after it, away from the pieces' boundaries by 2 H."""
    end = boundaries(path)[-1]
    times = np.linspace(0.0, 1.05 * end, count)
    edges = boundaries(path)
    return times[np.min(np.abs(times[:, None] - edges[None]), axis=1) > 2 * H]


@pytest.mark.parametrize("kind", KINDS)
def test_velocity_is_the_derivative_of_the_position(kind):
    path = build(KINDS[kind])
    times = sample_times(path)
    ahead, _ = evaluate(path, times + H)
    behind, _ = evaluate(path, times - H)
    _, velocity = evaluate(path, times)
    np.testing.assert_allclose((ahead - behind) / (2 * H), velocity, rtol=0, atol=FD_TOLERANCE)


@pytest.mark.parametrize("kind", KINDS)
def test_speed_is_the_asked_speed_on_each_piece_and_zero_after_the_end(kind):
    path = build(KINDS[kind])
    edges = boundaries(path)
    times = sample_times(path)
    _, velocity = evaluate(path, times)
    moving = times < edges[-1]
    piece = np.searchsorted(edges, times[moving], side="right") - 1
    asked = np.asarray(path.speeds)[piece]
    np.testing.assert_allclose(
        np.linalg.norm(velocity[moving], axis=1), asked, rtol=SPEED_TOLERANCE.get(kind, 1e-13)
    )
    np.testing.assert_array_equal(velocity[~moving], 0.0)
    end, _ = path.at(edges[-1] + 10.0)
    np.testing.assert_allclose(path.at(edges[-1] * (1 - 1e-12))[0], end, atol=1e-9)


@pytest.mark.parametrize("kind", KINDS)
def test_position_is_continuous_and_the_direction_is_where_it_should_be(kind):
    path = build(KINDS[kind])
    edges = boundaries(path)
    times = np.linspace(0.0, edges[-1] + 1.0, 20_001)
    position, _ = evaluate(path, times)
    step = np.linalg.norm(np.diff(position, axis=0), axis=1)
    fastest = np.max(path.speeds)
    assert np.all(step <= fastest * np.diff(times) * (1 + 1e-9) + 1e-12)
    # At every inner boundary the position does not jump; the direction does not either, but on a
    # polyline (its corners).
    before, v_before = evaluate(path, edges[1:-1] - 1e-9)
    after, v_after = evaluate(path, edges[1:-1] + 1e-9)
    np.testing.assert_allclose(before, after, atol=1e-8)
    unit_before = v_before / np.linalg.norm(v_before, axis=1, keepdims=True)
    unit_after = v_after / np.linalg.norm(v_after, axis=1, keepdims=True)
    turn = np.linalg.norm(unit_after - unit_before, axis=1)
    if kind == "polyline":
        assert np.all(turn > 0.5)
    else:
        np.testing.assert_allclose(turn, 0.0, atol=1e-7)


@pytest.mark.parametrize("kind", KINDS)
def test_the_path_compiled_answers_as_numpy(kind):
    path = build(KINDS[kind])
    times = np.linspace(-1.0, boundaries(path)[-1] + 2.0, 997)
    compiled = jax.jit(jax.vmap(lambda p, t: p.at(t), in_axes=(None, 0)))
    position, velocity = compiled(path, times)
    host_position, host_velocity = evaluate(path, times)
    np.testing.assert_allclose(np.asarray(position), host_position, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(velocity), host_velocity, rtol=0, atol=1e-12)


def test_lengths_are_the_geometric_ones():
    circle = build(KINDS["circle"])
    assert circle.length == pytest.approx(2 * math.pi * 3 * 1.3, rel=1e-14)
    # Rounded: each corner's two cuts r tan(|theta| / 2) replaced by its arc r |theta|.
    table = KINDS["rounded"]
    points, radius = np.array(table["waypoints"], float), table["turn_radius"]
    theta = np.abs(paths.turns(points))
    legs = np.linalg.norm(np.diff(points, axis=0), axis=1).sum()
    expected = legs - np.sum(2 * radius * np.tan(theta / 2)) + np.sum(radius * theta)
    assert build(table).length == pytest.approx(expected, rel=1e-14)
    # Curves: against the chord length of the curve sampled at a million points.
    for kind in ("figure_eight", "spline"):
        path = build(KINDS[kind])
        u = np.linspace(path.knots[0], path.knots[-1], 1_000_001)
        chords = np.linalg.norm(
            np.diff(curves.curve(path.shape, path.coefficients, path.knots, u)[0], axis=0), axis=1
        )
        lap = path.arcs[-1]
        assert lap == pytest.approx(chords.sum(), rel=1e-10)


def test_a_circle_starts_where_asked_and_turns_the_way_asked():
    path = build({**KINDS["circle"], "start_angle_deg": 0.0, "clockwise": False})
    position, velocity = path.at(0.0)
    np.testing.assert_allclose(position, [4.0, 2.0], atol=1e-14)
    np.testing.assert_allclose(velocity, [0.0, 0.7], atol=1e-14)
    quarter = (math.pi / 2 * 3) / 0.7
    np.testing.assert_allclose(path.at(quarter)[0], [1.0, 5.0], atol=1e-12)


def test_a_spline_passes_through_its_waypoints_and_a_figure_eight_through_its_centre():
    spline = build(KINDS["spline"])
    times = np.asarray(spline.times)
    for point, t in zip(KINDS["spline"]["waypoints"], times):
        np.testing.assert_allclose(spline.at(float(t))[0], point, atol=1e-9)
    eight = build(KINDS["figure_eight"])
    lap = eight.arcs[-1] / 0.8
    for t in (0.0, lap / 2, lap):
        np.testing.assert_allclose(eight.at(t)[0], [0.0, 0.0], atol=1e-9)


def test_a_polyline_with_one_speed_is_todays_path():
    one = build({"waypoints": [[0, 0], [3, 0], [3, 4]], "speed": 0.5})
    legs = build({"waypoints": [[0, 0], [3, 0], [3, 4]], "speeds": [0.5, 0.5]})
    for t in np.linspace(0, 16, 33):
        np.testing.assert_allclose(one.at(t)[0], legs.at(t)[0], atol=1e-15)
        np.testing.assert_allclose(one.at(t)[1], legs.at(t)[1], atol=1e-15)


coordinate = st.floats(-20, 20, allow_nan=False).map(lambda v: round(v, 3))


@settings(max_examples=40, deadline=None)
@given(
    points=st.lists(st.tuples(coordinate, coordinate), min_size=2, max_size=6, unique=True),
    radius=st.floats(0.05, 5.0),
    fraction=st.floats(0.0, 1.0),
)
def test_any_rounded_path_is_exact(points, radius, fraction):
    waypoints = np.array(points, float)
    legs = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    theta = np.abs(paths.turns(waypoints))
    if np.min(legs) < 0.1 or np.any(theta > math.pi - 0.05):
        return  # a leg too short to matter, or a reversal (refused for this kind)
    cuts = paths.corner_cuts(waypoints, radius)
    radius *= min(1.0, np.min(legs / (cuts[:-1] + cuts[1:] + 1e-300)))  # the largest that fits
    path = paths.rounded(waypoints, radius, np.full(len(legs), 0.7))
    t = fraction * path.times[-1]
    if np.min(np.abs(path.times - t)) < 2 * H:
        return  # a difference across a change of curvature has an error of order H / radius
    ahead, behind, (_, velocity) = path.at(t + H)[0], path.at(t - H)[0], path.at(t)
    # Truncation H^2 / 6 v^3 / radius^2 on an arc, rounding 1e-16 |p| / H: within the bound below.
    assert np.linalg.norm((ahead - behind) / (2 * H) - velocity) < 1e-9 + H**2 * 0.7**3 / radius**2
    assert np.linalg.norm(velocity) == pytest.approx(0.7, rel=1e-12)
    np.testing.assert_allclose(path.at(path.times[-1] + 1)[0], waypoints[-1], atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    points=st.lists(st.tuples(coordinate, coordinate), min_size=2, max_size=6, unique=True),
    fraction=st.floats(0.0, 1.0),
)
def test_any_spline_keeps_its_speed(points, fraction):
    waypoints = np.array(points, float)
    if np.min(np.linalg.norm(np.diff(waypoints, axis=0), axis=1)) < 0.1:
        return
    try:
        path = build({"kind": "spline", "waypoints": points, "speed": 0.6})
    except ScenarioError:
        return  # a cusp, or a curve so near one that its table cannot resolve it: refused
    error = curves.tabulate("spline", path.coefficients, path.knots)[3]
    t = fraction * path.times[-1] * (1 - 1e-6)
    assert np.linalg.norm(path.at(t)[1]) == pytest.approx(0.6, rel=max(10 * float(error), 1e-11))
    np.testing.assert_allclose(path.at(path.times[-1] + 1)[0], waypoints[-1], atol=1e-9)


@pytest.mark.parametrize("kind", KINDS)
def test_the_outline_keeps_the_path_within_its_margin(kind):
    """What an obstacle field relies on: every point of the path lies within the margin of the
    outline, so an obstacle that keeps its gap plus the margin from the outline keeps it from the
    path."""
    path = build(KINDS[kind])
    outline, margin = path.outline()
    points, _ = evaluate(path, np.linspace(0.0, boundaries(path)[-1], 5001))
    assert np.max(segment_distance(points, outline)) <= margin + 1e-12
    assert margin < 2e-3  # small beside any gap worth asking for


@pytest.mark.parametrize("size", [2, 7, COMPARE_ALL, COMPARE_ALL + 1, 8193])
@pytest.mark.parametrize("side", ["left", "right"])
def test_the_compiled_piece_search_finds_numpys_index(size, side):
    # Short tables are compared whole, long ones searched by an unrolled bisection: both must
    # answer numpy's index, at the entries themselves (ties) and between and beyond them.
    table = np.cumsum(np.random.default_rng(size).uniform(0.0, 1.0, size))
    values = np.concatenate((table, (table[1:] + table[:-1]) / 2, [table[0] - 1.0, table[-1] + 1.0]))
    compiled = jax.jit(jax.vmap(lambda v: searchsorted(jnp.asarray(table), v, side=side)))
    np.testing.assert_array_equal(compiled(values), np.searchsorted(table, values, side=side))
