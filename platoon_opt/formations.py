"""The platoon's initial formation and headings (``[platoon]``, docs/scenarios.md), on the host.

Every formation but "explicit" is a pattern of offsets that is centred and scaled per axis so that
the units' sample variances (ddof = 1) equal ``platoon.variance`` exactly, around the platoon's
centre, as the paper's ring is:

* "ring": phases phi_0 + 2 pi i / n on a circle (phi_0 drawn from the seed if ``seed.ring_phase``);
* "disk": drawn uniformly in the unit disk by the seed, each unit at least ``0.7 / sqrt(n)`` disk
  radii from the others before the scaling (rejection, at most ``TRIES`` draws per unit), so that
  no two units start on top of each other;
* "grid": rows of ceil(sqrt(n)) columns, filled row by row from the lower left;
* "line": evenly spaced on the line through the centre along (sqrt(var_x), sqrt(var_y)), the one
  line whose variances are both those asked (a line along an axis would have a variance of 0,
  which makes the task's Jacobian singular);
* "explicit": the positions the file gives, as they are.

Headings: "fixed" (``platoon.heading``), "random" (uniform in (-pi, pi], drawn by the seed: the
paper's Fig. 5) or "toward_target" (each unit faces the target's start).
"""

from __future__ import annotations

import math

import numpy as np

FORMATIONS = ("ring", "disk", "grid", "line", "explicit")
HEADINGS = ("fixed", "random", "toward_target")
# Draws per unit of a disk formation before the seed is refused.
TRIES = 1000
# A disk's least spacing, times 1 / sqrt(n) disk radii: the discs of that radius around n units
# cover at most 0.49 of the disk, so a draw is kept with probability above 1/2 to the last unit.
_SPACING = 0.7
# A pattern whose spread along an axis is below this (in its own units) has no variance to scale.
_FLAT = 1e-12


def scaled(offsets: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """``offsets`` (n, 2) centred and scaled per axis so that their sample variances are
    ``variance`` (2,) m^2 (the caller checks that both spreads are > 0: ``spread``)."""
    offsets = offsets - offsets.mean(axis=0)
    return offsets * np.sqrt(variance / offsets.var(axis=0, ddof=1))


def spread(offsets: np.ndarray) -> np.ndarray:
    """The sample variances (2,) of ``offsets`` (n, 2) about their mean."""
    return (offsets - offsets.mean(axis=0)).var(axis=0, ddof=1)


def ring(n: int, phase: float) -> np.ndarray:
    """n points on the unit circle at phases ``phase + 2 pi i / n`` (n, 2)."""
    angles = phase + 2 * np.pi * np.arange(n) / n
    return np.column_stack((np.cos(angles), np.sin(angles)))


def grid(n: int) -> np.ndarray:
    """n points on a grid of ceil(sqrt(n)) columns, row by row (n, 2)."""
    columns = math.ceil(math.sqrt(n))
    index = np.arange(n)
    return np.column_stack((index % columns, index // columns)).astype(float)


def line(n: int) -> np.ndarray:
    """n evenly spaced points on the diagonal (n, 2): scaling turns it to the asked variances."""
    steps = np.arange(n, dtype=float)
    return np.column_stack((steps, steps))


def disk(n: int, rng: np.random.Generator) -> np.ndarray | None:
    """n points drawn uniformly in the unit disk, each at least 0.7 / sqrt(n) from the ones before
    it (n, 2); None if a point found no place in ``TRIES`` draws. Near points are looked up in
    square cells of that side (a point's rivals lie in its own and the 8 cells around it), so the
    draw is O(n)."""
    least = _SPACING / math.sqrt(n)
    points = np.empty((n, 2))
    cells: dict[tuple[int, int], list[int]] = {}
    for i in range(n):
        for _ in range(TRIES):
            radius, angle = math.sqrt(rng.uniform()), rng.uniform(0.0, 2 * np.pi)
            x, y = radius * math.cos(angle), radius * math.sin(angle)
            cx, cy = math.floor(x / least), math.floor(y / least)
            near = [j for dx in (-1, 0, 1) for dy in (-1, 0, 1) for j in cells.get((cx + dx, cy + dy), ())]
            if all(math.hypot(points[j, 0] - x, points[j, 1] - y) >= least for j in near):
                points[i] = x, y
                cells.setdefault((cx, cy), []).append(i)
                break
        else:
            return None
    return points


def toward(positions: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Each unit's heading (n,) rad facing ``target`` (2,) m from ``positions`` (n, 2) m (0 for a
    unit standing on it)."""
    offset = target - positions
    return np.arctan2(offset[:, 1], offset[:, 0])
