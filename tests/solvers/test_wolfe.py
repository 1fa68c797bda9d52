"""Wolfe's minimum-norm-point algorithm against Clarabel on point clouds (the polytope their
convex hull), including hulls that hold the origin and affinely dependent points."""

from __future__ import annotations

import numpy as np
import pytest
import qpsolvers
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.solvers.dual.wolfe import min_norm_point

seeds = st.integers(0, 2**32 - 1)


def nearest_by_clarabel(points: np.ndarray) -> np.ndarray:
    """argmin ||x|| over x = P^T w, w in the simplex, by Clarabel (x as variables: P P^T would
    be singular for more points than dimensions)."""
    k, m = points.shape
    cost = sp.block_diag((sp.identity(m), sp.csc_matrix((k, k))), format="csc")
    equalities = sp.vstack(
        (
            sp.hstack((sp.identity(m), -sp.csc_matrix(points.T))),
            sp.hstack((sp.csc_matrix((1, m)), np.ones((1, k)))),
        )
    ).tocsc()
    solution = qpsolvers.solve_qp(
        cost,
        np.zeros(m + k),
        A=equalities,
        b=np.concatenate((np.zeros(m), [1.0])),
        lb=np.concatenate((np.full(m, -np.inf), np.zeros(k))),
        solver="clarabel",
    )
    return solution[:m]


def oracle_of(points: np.ndarray):
    """The vertex minimizing x . p, with its index as payload."""

    def oracle(x):
        index = int(np.argmin(points @ x))
        return points[index], index

    return oracle


@settings(max_examples=40, deadline=None)
@given(seeds, st.integers(1, 60), st.sampled_from([2, 4]), st.floats(-3.0, 3.0))
def test_nearest_point_of_a_polytope_matches_clarabel(seed, k, m, offset):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(k, m)) * rng.uniform(0.01, 100.0, m) + offset
    if k > 3:  # repeated and collinear points
        points[1] = points[0]
        points[2] = 0.5 * (points[0] + points[3])
    result = min_norm_point(oracle_of(points), (points[-1], k - 1), tolerance=1e-16, max_iterations=500)
    assert result.status in ("optimal", "stalled")
    reference = nearest_by_clarabel(points)
    scale = float(np.max(np.linalg.norm(points, axis=1)))
    assert np.linalg.norm(result.x) <= np.linalg.norm(reference) + 1e-9 * scale
    np.testing.assert_allclose(result.x, reference, atol=1e-6 * scale)
    assert result.gap <= 1e-12 * scale**2
    # x is the convex combination of the corral that it reports.
    assert np.all(result.weights > 0) and result.weights.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(result.weights @ points[result.payloads], result.x, atol=1e-9 * scale)


def test_origin_inside_the_hull_is_found():
    points = np.vstack((np.eye(4), -np.ones((1, 4)))) * np.array([1.0, 10.0, 0.1, 1000.0])
    result = min_norm_point(oracle_of(points), (points[0], None), tolerance=1e-16, max_iterations=100)
    assert result.status == "optimal"
    assert np.linalg.norm(result.x) <= 1e-12 * 1000


def test_a_disk_converges_without_ending():
    """A curved set: the oracle's answers differ at every cycle; the gap still falls below the
    tolerance (the disk of radius 1 around (3, 4): nearest point 0.6 (3, 4) / ... at distance 4)."""
    centre = np.array([3.0, 4.0])

    def oracle(x):
        return centre - x / max(np.linalg.norm(x), 1e-300), None

    result = min_norm_point(
        oracle, (centre + np.array([1.0, 0.0]), None), tolerance=1e-16, max_iterations=500
    )
    np.testing.assert_allclose(result.x, centre * 4 / 5, atol=1e-7)
