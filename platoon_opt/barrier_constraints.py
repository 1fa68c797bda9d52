"""Which barrier constraints each unit carries: the obstacles and the other units near it.

A unit is constrained by every obstacle whose inflated surface lies within ``search`` of its tip
and by every other unit within ``safety_distance + search`` (``safety.barriers`` sets ``search``:
the step's reach, and one turning radius more with turning rows). ``Constraints`` holds them per
unit in slots, in one order on every path: the obstacles by index, then the other units j of
unit i by ``(j - i) mod n`` (the order in which all pairs i < j list them).

Two searches fill the slots:

* ``constraints_within``, on the host: every constraint, as many slots as the most any unit has
  (a k-d tree beyond ``BRUTE_FORCE_UNITS`` units: memory O(n) for a bounded density);
* ``nearest_constraints``, for compiled code (written once for numpy and JAX): a fixed
  ``Capacity`` of slots, and per unit whether its constraints overflowed them, as jax-md's
  neighbour lists do. It compares all pairs up to ``BRUTE_FORCE_UNITS`` units, and beyond, the
  units of the 9 cells around each unit's cell of a cell list with a fixed capacity per cell.

Shapes: n units, C slots per unit; positions in m.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from platoon_opt.arrays import namespace, pytree, searchsorted
from platoon_opt.avoidance import CircularObstacles
from platoon_opt.neighbours import BRUTE_FORCE_UNITS, CELL_MARGIN


@pytree(data=("centre", "radius", "share", "present"))
@dataclass(frozen=True)
class Constraints:
    """Each unit's barrier constraints ``||p_i - centre|| >= radius``, in slots.

    Attributes:
        centre: (n, C, 2) m: an obstacle's centre or another unit's tip.
        radius: (n, C) m: the obstacle's inflated radius, or the safety distance.
        share: (n, C): 1 for an obstacle, 2 for a pair of units (each unit takes half).
        present: (n, C) bool: which slots hold a constraint (the others are zeros).
    """

    centre: Any
    radius: Any
    share: Any
    present: Any


class Capacity(NamedTuple):
    """Fixed sizes of a compiled safe-set build (``nearest_constraints``, ``safety.barrier_rows``).

    The defaults held every run of 32 seeds of the shipped scenarios of at most 32 units over 20 s
    but one of ``curved_field_16`` (experiments/barrier_capacity.md); a unit beyond them overflows.

    Attributes:
        obstacles: obstacle slots per unit.
        neighbours: other-unit slots per unit.
        rows: barrier rows per unit (up to three robust rows and a turning row per constraint).
        cell_units: beyond ``BRUTE_FORCE_UNITS`` units, the units kept of each cell of the cell
            list (``nearest_constraints``); a unit next to a fuller cell overflows.
    """

    obstacles: int = 3
    neighbours: int = 7
    rows: int = 12
    cell_units: int = 8


def constraints_within(
    positions: np.ndarray, obstacles: CircularObstacles, margin: float, safety_distance: float, search: float
) -> Constraints:
    """Every constraint of every unit (numpy): the obstacles (radius + ``margin``) whose inflated
    surface is within ``search`` (m) of a tip, and the units closer than ``safety_distance +
    search``; as many slots as the most any unit has."""
    n = positions.shape[0]
    owner, centre, radius, share, rank = [], [], [], [], []
    for index, (point, size) in enumerate(zip(obstacles.centers, obstacles.radii)):
        inflated = size + margin
        distance = np.hypot(positions[:, 0] - point[0], positions[:, 1] - point[1])
        units = np.flatnonzero(distance < inflated + search)
        owner.append(units)
        centre.append(np.broadcast_to(point, (units.size, 2)))
        radius.append(np.full(units.size, inflated))
        share.append(np.ones(units.size))
        rank.append(np.full(units.size, index))
    i, j = _pairs_within(positions, safety_distance + search).T
    for unit, other in ((i, j), (j, i)):
        owner.append(unit)
        centre.append(positions[other])
        radius.append(np.full(unit.size, safety_distance))
        share.append(np.full(unit.size, 2.0))
        rank.append(len(obstacles) + (other - unit) % n)
    who, where, size, half, order = (np.concatenate(parts) for parts in (owner, centre, radius, share, rank))
    sort = np.lexsort((order, who))
    who = who[sort]
    counts = np.bincount(who, minlength=n)
    slot = np.arange(who.size) - np.repeat(np.cumsum(counts) - counts, counts)
    slots = int(counts.max(initial=0))
    table = Constraints(
        np.zeros((n, slots, 2)), np.zeros((n, slots)), np.zeros((n, slots)), np.zeros((n, slots), dtype=bool)
    )
    table.centre[who, slot] = where[sort]
    table.radius[who, slot] = size[sort]
    table.share[who, slot] = half[sort]
    table.present[who, slot] = True
    return table


def nearest_constraints(
    positions: Any,
    obstacles: CircularObstacles,
    margin: Any,
    safety_distance: Any,
    search: Any,
    capacity: Capacity,
) -> tuple[Constraints, Any]:
    """The constraints of ``constraints_within`` in ``capacity``'s slots (numpy or JAX), and
    which units (n,) have more than their slots hold (the slots keep the first in order). Up to
    ``BRUTE_FORCE_UNITS`` units all pairs are compared; beyond, the units of a cell list
    (``_cell_candidates``), and a unit next to a cell of more than ``capacity.cell_units`` units
    overflows too. The obstacles are compared with every unit (memory O(n k) for k obstacles)."""
    xp = namespace(positions, obstacles.centers)
    n = positions.shape[0]
    inflated = obstacles.radii + margin
    gap = positions[:, None, :] - obstacles.centers[None, :, :]
    near_obstacle = xp.hypot(gap[..., 0], gap[..., 1]) < inflated + search
    obstacle_slots, obstacle_over = _first(
        xp, near_obstacle, xp.arange(len(obstacles))[None, :], len(obstacles), capacity.obstacles
    )
    if n <= BRUTE_FORCE_UNITS:
        candidates, crowded = xp.broadcast_to(xp.arange(n)[None, :], (n, n)), False
    else:
        candidates, crowded = _cell_candidates(xp, positions, safety_distance + search, capacity.cell_units)
    # A cell list's unused slots (n) are read as the last unit and are never near.
    others = xp.minimum(candidates, n - 1)
    offset = positions[:, None, :] - positions[others]
    # The squared distance, as the host's search compares it.
    squared = xp.einsum("ijk,ijk->ij", offset, offset)
    index = xp.arange(n)[:, None]
    near = (squared < (safety_distance + search) ** 2) & (candidates != index) & (candidates < n)
    columns, unit_over = _first(xp, near, (candidates - index) % n, n, capacity.neighbours)
    unit_slots = xp.take_along_axis(others, columns, axis=1)
    near_unit = xp.take_along_axis(near, columns, axis=1)
    size = xp.broadcast_to(inflated[None, :], near_obstacle.shape)
    table = Constraints(
        xp.concatenate((obstacles.centers[obstacle_slots], positions[unit_slots]), axis=1),
        xp.concatenate(
            (
                xp.take_along_axis(size, obstacle_slots, axis=1),
                xp.full(unit_slots.shape, safety_distance, dtype=float),
            ),
            axis=1,
        ),
        xp.concatenate((xp.ones(obstacle_slots.shape), xp.full(unit_slots.shape, 2.0)), axis=1),
        xp.concatenate(
            (
                xp.take_along_axis(near_obstacle, obstacle_slots, axis=1),
                near_unit,
            ),
            axis=1,
        ),
    )
    zero = ~table.present
    table = Constraints(
        xp.where(zero[..., None], 0.0, table.centre),
        xp.where(zero, 0.0, table.radius),
        xp.where(zero, 0.0, table.share),
        table.present,
    )
    return table, obstacle_over | unit_over | crowded


def _first(xp: Any, near: Any, rank: Any, bound: int, slots: int) -> tuple[Any, Any]:
    """The columns (n, s) of the first ``slots`` true entries of ``near`` (n, c) by ``rank``
    (integers in [0, ``bound``); s = min(slots, c); false entries fill the rest), and which rows
    have more."""
    columns = near.shape[1]
    score = xp.where(near, rank, rank + bound)
    order = xp.argsort(score, axis=1)[:, : min(slots, columns)]
    return order, xp.sum(near, axis=1) > slots


# The 9 cells around a cell (its own included): steps in columns and in rows.
_COLUMN_STEPS = np.repeat([-1, 0, 1], 3)
_ROW_STEPS = np.tile([-1, 0, 1], 3)


def _cell_candidates(xp: Any, positions: Any, cutoff: Any, per_cell: int) -> tuple[Any, Any]:
    """The units (n, 9 ``per_cell``) that may lie within ``cutoff`` (m) of each unit: those of its
    cell and of the 8 around it, the plane cut into square cells of side at least ``cutoff``, at
    most ``per_cell`` of each cell (n, a unit of no one, fills the rest); and whether some of
    those cells held more (n,). Memory O(n): the units sorted by cell, each cell's run found by
    a binary search."""
    n = positions.shape[0]
    origin = xp.min(positions, axis=0)
    extent = xp.max(xp.max(positions, axis=0) - origin)
    # At most 2^30 cells per axis, so that the keys fit in int64 (the cells grow beyond).
    side = xp.maximum(cutoff * (1 + CELL_MARGIN), extent / 2.0**30)
    cell = xp.floor((positions - origin) / side).astype(xp.int64)
    # Keys column after column; rows 0 .. max + 2, so that the rows just below and above a
    # column's units are empty cells and the 9 keys around a cell are distinct.
    rows = xp.max(cell[:, 1]) + 3
    key = cell[:, 0] * rows + cell[:, 1]
    order = xp.argsort(key, stable=True)
    sorted_key = key[order]
    around = key[:, None] + _COLUMN_STEPS * rows + _ROW_STEPS
    start = searchsorted(sorted_key, around.reshape(-1), "left").reshape(n, 9)
    end = searchsorted(sorted_key, around.reshape(-1), "right").reshape(n, 9)
    slot = start[..., None] + xp.arange(per_cell)
    held = slot < end[..., None]
    units = xp.where(held, order[xp.minimum(slot, n - 1)], n).reshape(n, 9 * per_cell)
    return units, xp.any(end - start > per_cell, axis=1)


def _pairs_within(positions: np.ndarray, cutoff: float) -> np.ndarray:
    """Pairs (p, 2) of units closer than ``cutoff`` (m), i < j."""
    n = positions.shape[0]
    if n <= BRUTE_FORCE_UNITS:
        i, j = np.triu_indices(n, 1)
        gap = positions[i] - positions[j]
        close = np.einsum("ij,ij->i", gap, gap) < cutoff**2
        return np.column_stack((i[close], j[close]))
    return cKDTree(positions).query_pairs(cutoff, output_type="ndarray").reshape(-1, 2)
