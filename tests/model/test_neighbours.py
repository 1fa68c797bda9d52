"""The cell list of ``platoon_opt.neighbours`` answers exactly as all pairs: in numpy, under
``jax.jit``, ``jax.vmap`` and ``jax.lax.scan``; and ``min_pair_distance`` is the smallest pair
distance."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.neighbours import (
    BRUTE_FORCE_UNITS,
    all_pairs_nearest,
    cell_list_nearest,
    min_pair_distance,
    nearest_unit,
)

seeds = st.integers(0, 2**32 - 1)
sizes = st.integers(BRUTE_FORCE_UNITS + 1, 300)
LAYOUTS = ("uniform", "clusters", "grid", "huge", "crowd")
layouts = st.sampled_from(LAYOUTS)
# Dyadic cutoffs put grid units exactly at the cutoff and on cell boundaries; the others round.
cutoffs = st.sampled_from([1.0, 0.25, 0.1, 0.3, 2.0])


def platoon(rng: np.random.Generator, n: int, layout: str, cutoff: float) -> np.ndarray:
    """n positions (n, 2) in m: spread uniformly (0.05 to 12 units per cutoff^2), in tight
    clusters, on a grid of step cutoff / 2 (pairs exactly at the cutoff, units on cell
    boundaries), in clusters up to 10^6 or 10^12 m apart, or all within 1 or 4 cells; some
    units doubled."""
    if layout == "uniform":
        positions = rng.uniform(-1, 1, (n, 2)) * cutoff * np.sqrt(n / 2) * rng.uniform(0.2, 3)
    elif layout == "clusters":
        centres = rng.uniform(-1, 1, (rng.integers(1, 6), 2)) * cutoff * 10
        positions = centres[rng.integers(0, len(centres), n)] + rng.normal(size=(n, 2)) * cutoff / 3
    elif layout == "grid":
        positions = rng.integers(-6, 7, (n, 2)) * (cutoff / 2)
    elif layout == "huge":
        centres = rng.uniform(-1, 1, (3, 2)) * rng.choice([1e6, 1e12])
        positions = centres[rng.integers(0, 3, n)] + rng.integers(-8, 9, (n, 2)) * (cutoff / 4)
    else:
        positions = rng.uniform(0, cutoff, (n, 2)) * rng.choice([0.5, 2.0])
    doubled = rng.integers(0, n, rng.integers(0, 4))
    positions[doubled] = positions[rng.integers(0, n, doubled.size)]
    return positions


def assert_same(got: tuple, expected: tuple) -> None:
    np.testing.assert_array_equal(np.asarray(got[0]), np.asarray(expected[0]))
    np.testing.assert_array_equal(np.asarray(got[1]), np.asarray(expected[1]))


@given(seeds, sizes, layouts, cutoffs)
def test_cell_list_equals_all_pairs_in_numpy(seed, n, layout, cutoff):
    positions = platoon(np.random.default_rng(seed), n, layout, cutoff)
    result = nearest_unit(positions, cutoff)
    assert isinstance(result[0], np.ndarray)
    assert_same(result, all_pairs_nearest(positions, cutoff))


def test_cell_list_in_numpy_with_tiny_cutoffs_and_huge_spreads():
    # 10^12 m across at a cutoff of 1 mm: 10^15 cells per axis, beyond int64 keys of cutoff-sized
    # cells; the cells grow, and pairs at and just inside the cutoff are still found.
    rng = np.random.default_rng(7)
    for spread, cutoff in [(1e6, 1e-3), (1e12, 1e-3), (1e6, 1e3)]:
        positions = rng.uniform(-spread, spread, (300, 2))
        positions[100:150] = positions[:50] + [cutoff, 0.0]
        angle = rng.uniform(0, 2 * np.pi, 100)
        ring = np.column_stack((np.cos(angle), np.sin(angle))) * rng.uniform(0.9, 1, (100, 1)) * cutoff
        positions[200:] = positions[50:150] + ring
        assert_same(cell_list_nearest(positions, cutoff), all_pairs_nearest(positions, cutoff))


@pytest.mark.parametrize(
    "origin, x, y, cutoff",
    [
        # (x - origin) / cutoff rounds to 714568.9999999999 and 714570.0.
        (-42481.19485012131, 28975.70514987869, 28975.805149878688, 0.1),
        # 2.5 * 10^12 cutoffs across: (x - origin) / cutoff has an absolute error of about 10^-4.
        (-1683117254.1355264, 845338625.6246066, 845338625.6256065, 1e-3),
    ],
)
def test_pair_just_inside_the_cutoff_across_a_rounded_cell_boundary(origin, x, y, cutoff):
    # Cells of side exactly the cutoff would put the pair (y - x < cutoff) 2 cells apart.
    positions = np.column_stack((np.full(40, origin), 5.0 + np.arange(40)))
    positions[:3] = [[origin, 0.0], [x, 0.0], [y, 0.0]]
    distance, index = cell_list_nearest(positions, cutoff)
    np.testing.assert_array_equal(index[1:3], [2, 1])
    assert_same((distance, index), all_pairs_nearest(positions, cutoff))


def test_cell_keys_stay_within_int64():
    # With cells of side the cutoff, up to 2^30 per axis, the pair's cells would have the keys
    # 2^57 - 1 and 2^57 (blocks of 2 columns, 2^28 + 1 rows: the top row holds unit 2): shifted
    # past the 6 bits of 40 units' indices, the second overflows int64 and sorts first.
    side, rows = 1 + 2.0**-20, 2**28 + 1
    block, row = divmod(2**57 - 1, rows)
    positions = np.column_stack((np.arange(40) * 2.0, np.zeros(40)))
    positions[0] = [(2 * block + 0.5) * side, (row + 1) * side - 0.1]
    positions[1] = positions[0] + [0.0, 0.2]
    positions[2] = [0.0, (rows - 1.5) * side]
    distance, index = cell_list_nearest(positions, 1.0)
    np.testing.assert_array_equal(index[:2], [1, 0])
    assert_same((distance, index), all_pairs_nearest(positions, 1.0))


cell_jit = jax.jit(cell_list_nearest)
pairs_jit = jax.jit(all_pairs_nearest)


@settings(max_examples=30)
@given(seeds, st.sampled_from([40, 257]), layouts, cutoffs)
def test_cell_list_equals_all_pairs_under_jit(seed, n, layout, cutoff):
    positions = jnp.asarray(platoon(np.random.default_rng(seed), n, layout, cutoff))
    assert_same(cell_jit(positions, cutoff), pairs_jit(positions, cutoff))


def test_cell_list_equals_all_pairs_under_vmap_of_a_batch():
    rng = np.random.default_rng(3)
    cutoffs = np.array([1.0, 0.25, 0.1, 0.3, 2.0, 1.0, 0.25, 0.3])
    batch = np.stack(
        [platoon(rng, 120, LAYOUTS[b % len(LAYOUTS)], cutoff) for b, cutoff in enumerate(cutoffs)]
    )
    got = jax.jit(jax.vmap(cell_list_nearest))(batch, cutoffs)
    assert_same(got, jax.jit(jax.vmap(all_pairs_nearest))(batch, cutoffs))


def test_cell_list_inside_scan():
    rng = np.random.default_rng(4)
    start = platoon(rng, 80, "clusters", 1.0)
    moves = rng.normal(size=(5, 80, 2)) * 0.3

    def run(search):
        def step(positions, move):
            positions = positions + move
            return positions, search(positions, 1.0)

        return jax.jit(lambda start, moves: jax.lax.scan(step, start, moves)[1])(start, moves)

    assert_same(run(cell_list_nearest), run(all_pairs_nearest))


def brute_minimum(positions: np.ndarray) -> float:
    return float(all_pairs_nearest(positions, np.inf)[0].min())


@given(seeds, st.integers(2, 300), layouts, st.sampled_from([1e-6, 1e-3, 1.0, 50.0]))
def test_min_pair_distance_in_numpy(seed, n, layout, start):
    positions = platoon(np.random.default_rng(seed), n, layout, 1.0)
    assert min_pair_distance(positions, start) == brute_minimum(positions)


def test_min_pair_distance_under_jit_and_vmap():
    rng = np.random.default_rng(5)
    batch = np.stack([platoon(rng, 90, LAYOUTS[b % len(LAYOUTS)], 1.0) for b in range(8)])
    batch[1] = rng.uniform(-1e5, 1e5, (90, 2))  # first pair far beyond the starting cutoff
    got = jax.jit(jax.vmap(min_pair_distance, in_axes=(0, None)))(batch, 1e-3)
    expected = jax.vmap(lambda positions: all_pairs_nearest(positions, jnp.inf)[0].min())(batch)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))
    small = jnp.asarray(batch[0, :BRUTE_FORCE_UNITS])
    assert jax.jit(min_pair_distance)(small, 1e-3) == all_pairs_nearest(small, jnp.inf)[0].min()
