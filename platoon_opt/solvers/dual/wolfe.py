"""Wolfe's minimum-norm-point algorithm: the point of a compact convex set K in R^m nearest the
origin, given only a linear minimization oracle ``q(x) = argmin_{p in K} x . p``.

The dual allocator's strict priority needs the projection of the task velocity u onto the set of
achievable task velocities ``J(C) = sum_i J_i C_i``; with ``K = J(C) - u`` the oracle is one pass
over the units (each unit's support point, ``J_i`` applied), and m = 4. The method keeps a
"corral" of at most m + 1 affinely independent atoms (oracle answers) and the point x of their
convex hull nearest the origin; each major cycle adds the oracle's atom for x, each minor cycle
moves to the nearest point of the corral's affine hull and drops atoms until that point lies in
the hull's convex part. It ends when the Frank-Wolfe gap ``x . (x - q(x))`` is within the
tolerance; since ``||x - x*||^2 <= 2 x . (x - q(x))``, the gap bounds the distance to the
answer. On a polytope it ends after finitely many cycles (Wolfe 1976); on a set with curved
faces (the exact speed disk) it converges but need not end, and ``max_iterations`` caps it.

Reference: P. Wolfe, "Finding the nearest point in a polytope", Math. Programming 11 (1976);
the cycle structure follows Chakrabarty, Jain and Kothari, "Provable submodular minimization
using Wolfe's algorithm" (NeurIPS 2014).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

# Weights of the corral at or below this (relative to 1) are dropped as zero.
_ZERO_WEIGHT = 1e-14


@dataclass(frozen=True)
class NearestPoint:
    """Result of ``min_norm_point``.

    Attributes:
        x: the point of K found (m,); ``||x - x*|| <= sqrt(2 gap)``.
        gap: the Frank-Wolfe gap ``x . (x - q(x))`` at x (>= 0 up to rounding).
        iterations: major cycles (oracle calls after the first).
        status: "optimal" (gap within tolerance), "stalled" (a cycle no longer brings x nearer the
            origin: the gap is at rounding level) or "max_iterations".
        weights, payloads: x as a convex combination of the corral's atoms: their weights (k,) and
            what the oracle returned with each (e.g. the primal point behind an atom).
    """

    x: np.ndarray
    gap: float
    iterations: int
    status: str
    weights: np.ndarray
    payloads: list[Any]


def _affine_minimizer(atoms: np.ndarray) -> np.ndarray:
    """Weights a (k,), sum 1, of the point ``atoms.T @ a`` of the atoms' affine hull nearest the
    origin, for atoms (k, m): the least-squares solution of ``a_0 + (a_j - a_0) b_j = 0``, which
    keeps the atoms' own scale (a KKT system mixes their squared size with 1) and gives the
    shortest b when atoms are affinely dependent to rounding."""
    base, spans = atoms[0], atoms[1:] - atoms[0]
    beta = np.linalg.lstsq(spans.T, -base, rcond=None)[0]
    return np.concatenate(([1.0 - beta.sum()], beta))


def min_norm_point(
    oracle: Callable[[np.ndarray], tuple[np.ndarray, Any]],
    start: tuple[np.ndarray, Any],
    *,
    tolerance: float,
    max_iterations: int,
) -> NearestPoint:
    """The point of K nearest the origin (module docstring).

    Args:
        oracle: x (m,) -> (a point p of K minimizing ``x . p`` (m,), a payload kept with it).
        start: (a point of K (m,), its payload): the first atom.
        tolerance: stop when the gap is within ``tolerance`` times the largest squared norm of an
            atom met (the scale of K's points): the answer is then within
            ``sqrt(2 tolerance)`` of that size.
        max_iterations: major cycles at most.
    """
    atoms = np.asarray(start[0], dtype=float)[None, :]
    payloads = [start[1]]
    weights = np.ones(1)
    x = atoms[0].copy()
    scale = float(x @ x)
    m = x.size
    for iteration in range(max_iterations + 1):
        atom, payload = oracle(x)
        atom = np.asarray(atom, dtype=float)
        gap = float(x @ x - x @ atom)
        scale = max(scale, float(atom @ atom))
        if gap <= tolerance * scale:
            return NearestPoint(x, max(gap, 0.0), iteration, "optimal", weights, payloads)
        if iteration == max_iterations:
            break
        corral = weights, list(payloads)  # x's combination, kept in case the cycle stalls
        if atoms.shape[0] > m:
            # A full corral (m + 1 atoms) holds x in its interior only if x = 0, where the gap
            # vanishes; with rounding, keep the m atoms of the largest weight.
            keep = np.argsort(weights)[1:]
            atoms, weights = atoms[keep], weights[keep] / weights[keep].sum()
            payloads = [payloads[i] for i in keep]
        atoms = np.vstack((atoms, atom))
        weights = np.append(weights, 0.0)
        payloads.append(payload)
        while True:  # minor cycles
            affine = _affine_minimizer(atoms)
            if np.all(affine > _ZERO_WEIGHT):
                weights = affine
                break
            # Move from the current weights toward the affine minimizer until a weight reaches 0
            # (at once, theta = 0, when an atom at weight 0 does not help: rounding).
            falling = affine <= _ZERO_WEIGHT
            drop = weights[falling] - affine[falling]
            theta = float(np.min(np.where(drop > 0, weights[falling] / np.where(drop > 0, drop, 1.0), 0.0)))
            weights = theta * affine + (1.0 - theta) * weights
            kept = weights > _ZERO_WEIGHT
            if kept.all():  # rounding: drop the smallest
                kept[np.argmin(weights)] = False
            kept[np.argmax(weights)] = True
            atoms, weights = atoms[kept], weights[kept] / weights[kept].sum()
            payloads = [p for p, k in zip(payloads, kept) if k]
        nearer = weights @ atoms
        if not float(nearer @ nearer) < float(x @ x):
            return NearestPoint(x, max(gap, 0.0), iteration, "stalled", *corral)
        x = nearer
    return NearestPoint(x, max(gap, 0.0), max_iterations, "max_iterations", weights, payloads)
