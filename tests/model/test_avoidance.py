import math

import jax
import numpy as np
import pytest

from platoon_opt import AvoidanceParams, CircularObstacles
from platoon_opt.avoidance import obstacle_repulsion, repulsion, unit_repulsion


def test_obstacle_straight_ahead_repels_fully():
    obstacles = CircularObstacles([[2.0, 0.0]], [0.5])
    velocity, distance = obstacle_repulsion(np.array([[0.0, 0.0], [0.0, 5.0]]), np.zeros(2), obstacles, 3.0)
    np.testing.assert_allclose(distance, [1.5, math.hypot(2, 5) - 0.5])
    np.testing.assert_allclose(velocity[0], [-(1 / 1.5 - 1 / 3.0), 0.0])
    np.testing.assert_allclose(velocity[1], 0.0)  # beyond d_mino


def test_path_projection_factor_and_obstacles_behind():
    obstacles = CircularObstacles([[1.0, 1.0]], [0.5])
    positions = np.zeros((3, 2))
    headings = np.array([0.0, math.pi / 4, math.pi])  # 45 degrees off, dead ahead, behind
    velocity, distance = obstacle_repulsion(positions, headings, obstacles, 3.0)
    magnitude = 1 / distance[0] - 1 / 3.0
    away = -np.array([1.0, 1.0]) / math.sqrt(2)
    np.testing.assert_allclose(velocity[0], math.cos(math.pi / 4) * magnitude * away)
    np.testing.assert_allclose(velocity[1], magnitude * away)
    np.testing.assert_allclose(velocity[2], 0.0)


def test_unit_repulsion_eq7_pushes_nearest_apart():
    positions = np.array([[0.0, 0.0], [0.5, 0.0], [5.0, 5.0]])
    velocity, distance = unit_repulsion(positions, 1.0)
    np.testing.assert_allclose(distance[:2], 0.5)
    assert np.isinf(distance[2])
    np.testing.assert_allclose(velocity[0], [-(1 / 0.5 - 1), 0.0])
    np.testing.assert_allclose(velocity[1], [(1 / 0.5 - 1), 0.0])
    np.testing.assert_allclose(velocity[2], 0.0)


def test_coincident_units_get_finite_deterministic_directions():
    positions = np.zeros((3, 2))
    first, _ = unit_repulsion(positions, 1.0)
    second, _ = unit_repulsion(positions, 1.0)
    assert np.all(np.isfinite(first))
    np.testing.assert_array_equal(first, second)
    assert np.linalg.matrix_rank(first) == 2  # not all pushed the same way


def test_precedence_flags():
    obstacles = CircularObstacles([[0.0, 0.0]], [1.0])
    positions = np.array([[1.7, 0.0], [1.8, 3.0], [5.0, 5.0], [5.1, 5.0]])
    result = repulsion(positions, np.zeros(4), obstacles, AvoidanceParams(d_minr=1.0, d_mino=3.0))
    # Unit 0 within d_mino/4 = 0.75 of the surface; units 2, 3 within d_minr/8 = 0.125.
    np.testing.assert_array_equal(result.exempt, [True, False, True, True])


def test_inside_an_obstacle_is_finite():
    obstacles = CircularObstacles([[0.0, 0.0]], [1.0])
    velocity, distance = obstacle_repulsion(
        np.array([[0.1, 0.0], [0.0, 0.0]]), np.array([math.pi, 0.0]), obstacles, 3.0
    )
    assert np.all(distance < 0) and np.all(np.isfinite(velocity))


def test_bad_obstacles_name_the_field():
    with pytest.raises(ValueError, match="radii"):
        CircularObstacles([[0.0, 0.0]], [0.0])
    with pytest.raises(ValueError, match="d_mino"):
        AvoidanceParams(d_mino=-1.0)


@pytest.mark.parametrize("n", [2, 5, 32, 100])
def test_all_pairs_and_cell_list_agree(monkeypatch, n):
    import platoon_opt.neighbours as neighbours

    rng = np.random.default_rng(n)
    batch = rng.normal(size=(20, n, 2)) * rng.uniform(0.1, 3.0, (20, 1, 1))
    batch[::5, 1] = batch[::5, 0]
    batch[1::5] = np.round(batch[1::5] * 4) / 4  # ties, and pairs exactly at d_minr

    def compiled():
        # A new function each time: jit reads BRUTE_FORCE_UNITS when it traces, once per function.
        return jax.jit(jax.vmap(lambda positions: unit_repulsion(positions, 1.0)))

    monkeypatch.setattr(neighbours, "BRUTE_FORCE_UNITS", n)
    pairs = [unit_repulsion(positions, 1.0) for positions in batch], compiled()(batch)
    monkeypatch.setattr(neighbours, "BRUTE_FORCE_UNITS", 0)
    cells = [unit_repulsion(positions, 1.0) for positions in batch], compiled()(batch)
    for by_pairs, by_cells in zip(pairs[0], cells[0]):
        np.testing.assert_array_equal(by_pairs[0], by_cells[0])
        np.testing.assert_array_equal(by_pairs[1], by_cells[1])
    np.testing.assert_array_equal(pairs[1][0], cells[1][0])
    np.testing.assert_array_equal(pairs[1][1], cells[1][1])
