"""The fixed-capacity constraint search beyond 32 units (``barrier_constraints.nearest_constraints``
with its cell list): where its capacity holds, the host's table (``constraints_within``, a k-d
tree), slot for slot; it marks exactly the units it cannot hold; traced, the same."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.avoidance import CircularObstacles
from platoon_opt.barrier_constraints import Capacity, constraints_within, nearest_constraints
from platoon_opt.neighbours import BRUTE_FORCE_UNITS

MARGIN, DISTANCE, SEARCH = 0.05, 0.3, 0.39
CUTOFF = DISTANCE + SEARCH
# Units and cells never overflow in the states below.
ROOMY = Capacity(obstacles=8, neighbours=40, rows=12, cell_units=64)


def _state(seed, n, spread):
    rng = np.random.default_rng(seed)
    positions = rng.uniform(-spread, spread, (n, 2))
    k = int(rng.integers(0, 5))
    obstacles = CircularObstacles(rng.uniform(-spread, spread, (k, 2)), rng.uniform(0.1, 0.5, k))
    return positions, obstacles


def _same_table(table, host, units):
    """``table`` holds, for each of ``units``, ``host``'s constraints in ``host``'s order (its
    obstacle slots, then its other-unit slots)."""
    for unit in units:
        mine, theirs = table.present[unit], host.present[unit]
        for field in ("centre", "radius", "share"):
            np.testing.assert_array_equal(
                getattr(table, field)[unit][mine], getattr(host, field)[unit][theirs]
            )


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(BRUTE_FORCE_UNITS + 1, 300),
    spread=st.sampled_from([2.0, 5.0]),
)
def test_the_cell_list_finds_the_hosts_constraints(seed, n, spread):
    positions, obstacles = _state(seed, n, spread)
    table, overflow = nearest_constraints(positions, obstacles, MARGIN, DISTANCE, SEARCH, ROOMY)
    host = constraints_within(positions, obstacles, MARGIN, DISTANCE, SEARCH)
    assert not np.any(overflow)
    _same_table(table, host, np.arange(n))


@pytest.mark.parametrize("seed", range(20))
def test_a_small_capacity_marks_exactly_the_units_it_cannot_hold(seed):
    """Two neighbour slots and cells of 3 units: a unit overflows when the host gives it more
    than 2 other units, or when a cell among the 9 around its own holds more than 3 units; the
    others have the host's constraints."""
    capacity = Capacity(obstacles=8, neighbours=2, rows=12, cell_units=3)
    positions, obstacles = _state(seed, 120, 3.0)
    table, overflow = nearest_constraints(positions, obstacles, MARGIN, DISTANCE, SEARCH, capacity)
    host = constraints_within(positions, obstacles, MARGIN, DISTANCE, SEARCH)
    neighbours = np.count_nonzero(host.present & (host.share == 2), axis=1)
    # The cells as the search cuts them: side the cutoff, from the least coordinates.
    cell = np.floor((positions - positions.min(axis=0)) / (CUTOFF * (1 + 2.0**-20))).astype(int)
    keys, counts = np.unique(cell, axis=0, return_counts=True)
    full = {tuple(key) for key, count in zip(keys, counts) if count > 3}
    crowded = np.array(
        [any((x + dx, y + dy) in full for dx in (-1, 0, 1) for dy in (-1, 0, 1)) for x, y in cell]
    )
    expected = (neighbours > 2) | crowded
    assert np.array_equal(overflow, expected)
    assert 0 < np.count_nonzero(expected) < 120
    _same_table(table, host, np.flatnonzero(~expected))


def test_the_traced_search_is_the_numpy_search():
    search = jax.jit(nearest_constraints, static_argnames=("capacity",))
    for seed in range(5):
        positions, obstacles = _state(seed, 100, 3.0)
        table, overflow = nearest_constraints(positions, obstacles, MARGIN, DISTANCE, SEARCH, ROOMY)
        traced, traced_overflow = search(positions, obstacles, MARGIN, DISTANCE, SEARCH, capacity=ROOMY)
        assert np.array_equal(np.asarray(traced_overflow), overflow)
        for field in ("centre", "radius", "share", "present"):
            np.testing.assert_array_equal(np.asarray(getattr(traced, field)), getattr(table, field))
