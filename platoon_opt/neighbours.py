"""Each unit's nearest other unit within a cutoff, exactly, in O(n) memory.

Written once for numpy and ``jax.numpy`` (``platoon_opt.arrays.namespace``): eager on the host,
traced under ``jax.jit``, ``jax.vmap`` and ``jax.lax.scan``. Positions are (n, 2) in m, cutoffs
in m. Up to ``BRUTE_FORCE_UNITS`` units all pairs are compared (an n x n block); beyond, a cell
list (``cell_list_nearest``):

* the plane is cut into square cells of side at least the cutoff, so that the units closer than
  the cutoff to a unit lie in its own cell or in one of the 8 around it;
* the columns of cells are grouped in blocks 2 wide, in two ways: columns (0, 1), (2, 3), ... and
  (-1, 0), (1, 2), ...; any 2 adjacent columns share a block in one of them;
* for each grouping the units are sorted by block, then row. The units in the same block and at
  most 1 row apart are then a contiguous run of the sorted units, so comparing each unit with
  the units s places before and after it, for s = 1, 2, ... until no unit has a neighbouring
  cell's unit s places away, meets every pair of units in neighbouring cells: slices of the
  sorted arrays, without gathers or searches, in a ``lax.while_loop`` under JAX.

Memory O(n); time O(n log n + n w), with w the most units in 3 rows of a block (O(n^2) if all
crowd into one cell). Distances are computed as in ``all_pairs_nearest`` (``hypot`` of
p_i - p_j) and ties go to the lower index, so both answer the same, bit for bit.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from platoon_opt.arrays import namespace, while_loop

# Up to this many units the nearest neighbour comes from all pairs.
BRUTE_FORCE_UNITS = 32

# The cell side is the cutoff times (1 + CELL_MARGIN). The cell coordinates (p - origin) / side
# are rounded by a few 2^-53 of the extent, at most 2^-21 of a cell while the extent spans at most
# 2^30 cells: the margin keeps every pair closer than the cutoff in neighbouring cells.
CELL_MARGIN = 2.0**-20
# Shifts compared per pass of the loop: fewer passes over the best-so-far arrays (XLA fuses the
# comparisons of one pass), at most SHIFTS - 1 shifts past the last needed.
SHIFTS = 4


def nearest_unit(positions: Any, cutoff: Any) -> tuple[Any, Any]:
    """Distance (n,) in m to each unit's nearest other unit closer than ``cutoff`` (m, > 0) and
    its index (n,); inf and n when none is closer. Ties go to the lower index. Coincident units
    are neighbours at distance 0. An infinite cutoff puts all units in one cell: O(n^2) time (for
    the smallest distance of all, ``min_pair_distance``)."""
    if positions.shape[0] <= BRUTE_FORCE_UNITS:
        return all_pairs_nearest(positions, cutoff)
    return cell_list_nearest(positions, cutoff)


def all_pairs_nearest(positions: Any, cutoff: Any) -> tuple[Any, Any]:
    """``nearest_unit`` by comparing all pairs: O(n^2) memory, for a few units."""
    xp = namespace(positions)
    n = positions.shape[0]
    offset = positions[:, None, :] - positions[None, :, :]
    length = xp.where(xp.eye(n, dtype=bool), xp.inf, xp.hypot(offset[..., 0], offset[..., 1]))
    index = xp.argmin(length, axis=1)
    distance = xp.take_along_axis(length, index[:, None], axis=1)[:, 0]
    beyond = distance >= cutoff
    return xp.where(beyond, xp.inf, distance), xp.where(beyond, n, index)


def cell_list_nearest(positions: Any, cutoff: Any) -> tuple[Any, Any]:
    """``nearest_unit`` by a cell list (see the module docstring): O(n) memory, n >= 1."""
    xp = namespace(positions, cutoff)
    n = positions.shape[0]
    bits = max(1, (n - 1).bit_length())
    # Cells per axis at most: beyond (a spread over 2^(61 - bits) / 2 cutoffs, 4 * 10^6 for
    # 10^5 units) the cells grow, which stays exact, only slower, and keeps key << bits in int64.
    max_cells = 2.0 ** min(30, (61 - bits) // 2)
    origin = xp.min(positions, axis=0)
    extent = xp.max(xp.max(positions, axis=0) - origin)
    side = xp.maximum(cutoff * (1 + CELL_MARGIN), extent / max_cells)
    cell = xp.floor((positions - origin) / side).astype(xp.int64)
    # Keys (2, n) of the cells, row after row within a block, one line per grouping; a block's
    # last row is 2 keys before the next block's first, so keys at most 1 apart are neighbours.
    rows = xp.max(cell[:, 1]) + 2
    key = xp.stack((cell[:, 0] // 2, (cell[:, 0] + 1) // 2)) * rows + cell[:, 1]
    # Sorted with each unit's index in the low bits: one plain sort of int64, ties by index.
    packed = xp.sort((key << bits) | xp.arange(n), axis=1)
    index, key = packed & ((1 << bits) - 1), packed >> bits
    x, y = positions[index, 0], positions[index, 1]
    # Padded beyond the largest shift (a pass runs after one with a shift below n) with units
    # that are no one's neighbours (key -2).
    reach = n + 2 * SHIFTS
    others = [
        xp.concatenate(
            (xp.full((2, reach), fill, dtype=a.dtype), a, xp.full((2, reach), fill, dtype=a.dtype)), 1
        )
        for a, fill in ((x, 0.0), (y, 0.0), (key, -2), (index, n))
    ]

    def compare(state: tuple[Any, Any, Any, Any]) -> tuple[Any, Any, Any, Any]:
        shift, distance, nearest, _ = state
        found = False
        for s in [sign * (shift + k) for k in range(SHIFTS) for sign in (1, -1)]:
            other_x, other_y, other_key, other = (_window(xp, a, reach + s, n) for a in others)
            near = xp.abs(other_key - key) <= 1
            length = xp.where(near, xp.hypot(x - other_x, y - other_y), xp.inf)
            distance, nearest = _nearer(xp, (distance, nearest), (length, other))
            found = found | xp.any(near)
        return shift + SHIFTS, distance, nearest, found

    # Each shift beyond the first without neighbours has none either (the keys are sorted).
    state = (1, xp.full((2, n), xp.inf), xp.full((2, n), n, dtype=xp.int64), True)
    state = while_loop(lambda state: state[3], compare, state)
    distance, nearest = _unsort(xp, index, state[1]), _unsort(xp, index, state[2])
    distance, nearest = _nearer(xp, (distance[0], nearest[0]), (distance[1], nearest[1]))
    beyond = distance >= cutoff
    return xp.where(beyond, xp.inf, distance), xp.where(beyond, n, nearest)


def _nearer(xp: Any, best: tuple[Any, Any], candidate: tuple[Any, Any]) -> tuple[Any, Any]:
    """The lesser of (distance, index) pairs, element by element: ties to the lower index."""
    closer = (candidate[0] < best[0]) | ((candidate[0] == best[0]) & (candidate[1] < best[1]))
    return xp.where(closer, candidate[0], best[0]), xp.where(closer, candidate[1], best[1])


def _window(xp: Any, array: Any, start: Any, size: int) -> Any:
    """``array[:, start : start + size]`` for a ``start`` that may be traced."""
    if xp is jnp:
        return jax.lax.dynamic_slice_in_dim(array, start, size, axis=1)
    return array[:, start : start + size]


def _unsort(xp: Any, index: Any, values: Any) -> Any:
    """``values`` (2, n) of sorted units back in the units' order: ``out[g, index[g, t]] = values[g, t]``."""
    groupings = xp.arange(2)[:, None]
    if xp is jnp:
        return jnp.zeros_like(values).at[groupings, index].set(values)
    out = np.empty_like(values)
    out[groupings, index] = values
    return out


def min_pair_distance(positions: Any, start: Any, *, known: Any = None) -> Any:
    """The smallest distance between two of the units (n >= 2), m, exactly, in O(n) memory.

    Beyond ``BRUTE_FORCE_UNITS`` units: ``cell_list_nearest`` with the cutoff ``start`` (m, > 0),
    doubled until some pair is closer. Cheapest with ``start`` at most about the answer (such as
    a safety distance): then the cells hold a few units each, whereas a cutoff far above the
    spacing crowds many units into each cell. ``known``: the least of ``nearest_unit``'s distances
    within some cutoff, already at hand (inf if no pair was within it): where finite it is the
    answer, and no search runs.
    """
    xp = namespace(positions, start)
    if positions.shape[0] <= BRUTE_FORCE_UNITS:
        return xp.min(all_pairs_nearest(positions, xp.inf)[0])

    def widen(state: tuple[Any, Any]) -> tuple[Any, Any]:
        cutoff = 2 * state[0]
        return cutoff, xp.min(cell_list_nearest(positions, cutoff)[0])

    # Halved so that the first widening searches within ``start``: the search is traced once.
    found = xp.inf if known is None else known
    state = (xp.asarray(start, dtype=xp.float64) / 2, xp.asarray(found, dtype=xp.float64))
    return while_loop(lambda state: xp.isinf(state[1]), widen, state)[1]
