"""Box-constrained QPs (platoon_opt.solvers.nmpc.box_qp): the structured Hessian against its
dense form, the active-set Newton method and projected Newton against the KKT conditions and
Clarabel."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
import qpsolvers
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt.solvers.nmpc import box_qp
from platoon_opt.solvers.nmpc.box_qp import BlockLowRank, active_set_newton, projected_newton
from platoon_opt.solvers.nmpc.interior import interior_point, lifted_clarabel

# ``BlockLowRank`` works on its dense form up to ``DENSE_UP_TO`` variables, on the split above:
# each test runs both.
PATHS = {"split": 0, "dense": 10**9}
both_paths = pytest.mark.parametrize("path", PATHS)

seeds = st.integers(0, 2**32 - 1)


def structured(rng: np.random.Generator, n: int, b: int, c: int, weak: float = 1.0) -> BlockLowRank:
    """Blocks from ``2 b`` random rows each scaled by ``weak``, coupling of ``c`` random rows: with
    weak << 1 the blocks are as much weaker than the coupling as the SQP's smoothness rows are
    than its task rows."""
    rows = weak * rng.normal(size=(n, 2 * b, b))
    blocks = rows.transpose(0, 2, 1) @ rows + 1e-8 * np.identity(b)
    return BlockLowRank(blocks, rng.normal(size=(c, n * b)) * rng.uniform(0, 3, n * b))


def box(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds around 0, some of them 0 (an input at its bound)."""
    lower, upper = -rng.uniform(0, 1, size), rng.uniform(0, 1, size)
    lower[rng.random(size) < 0.2] = 0.0
    upper[rng.random(size) < 0.2] = 0.0
    return lower, upper


def assert_kkt(hessian: np.ndarray, gradient, lower, upper, x, tolerance: float = 1e-7) -> None:
    """Feasible, zero gradient on the free variables, gradient pushing outward at the bounds."""
    grad = hessian @ x + gradient
    scale = tolerance * (1 + np.abs(gradient).max())
    assert np.all(x >= lower - 1e-12) and np.all(x <= upper + 1e-12)
    at_lower, at_upper = x <= lower + 1e-9, x >= upper - 1e-9
    free = ~(at_lower | at_upper)
    assert np.all(np.abs(grad[free]) <= scale)
    assert np.all(grad[at_lower & ~at_upper] >= -scale) and np.all(grad[at_upper & ~at_lower] <= scale)


@both_paths
def test_structured_hessian_matches_its_dense_form(path, monkeypatch):
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", PATHS[path])
    rng = np.random.default_rng(0)
    hessian = structured(rng, 4, 6, 5)
    dense = hessian.dense()
    x = rng.normal(size=24)
    np.testing.assert_allclose(hessian.matvec(x), dense @ x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(hessian.diagonal(), np.diag(dense), rtol=1e-12)
    expected = hessian.coupling.T @ hessian.coupling
    for i in range(4):
        expected[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += hessian.blocks[i]
    np.testing.assert_allclose(dense, expected, rtol=1e-12)


@both_paths
@pytest.mark.parametrize("weak", [1.0, 1e-3])
def test_free_set_solve_matches_a_dense_solve(weak, path, monkeypatch):
    """Woodbury with refinement (and the dense path's Cholesky) is backward stable on the free
    variables' system (its residual at the rounding of the product) and agrees with a dense
    solve, also when the blocks are 1e6 times weaker than the coupling (where the dense solve
    itself is good to about 1e-8)."""
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", PATHS[path])
    rng = np.random.default_rng(1)
    hessian = structured(rng, 5, 8, 12, weak)
    free = rng.random(40) < 0.7
    free[8:16] = False  # a block with nothing free
    rhs = rng.normal(size=40)
    y = hessian.solve_free(free, rhs)
    system = hessian.dense()[np.ix_(free, free)]
    assert np.all(y[~free] == 0)
    residual = np.linalg.norm(system @ y[free] - rhs[free])
    assert residual <= 1e-14 * (np.linalg.norm(system, 2) * np.linalg.norm(y) + np.linalg.norm(rhs[free]))
    expected = np.linalg.solve(system, rhs[free])
    np.testing.assert_allclose(y[free], expected, rtol=1e-6, atol=1e-9 * np.abs(expected).max())


# A random box QP of the SQP's kind: n blocks of b, c coupling rows, blocks ``weak`` times the
# coupling's scale, on the dense or the split path.
qp_family = given(
    seed=seeds,
    n=st.integers(1, 6),
    b=st.integers(1, 10),
    c=st.integers(0, 12),
    weak=st.sampled_from([1.0, 1e-2, 1e-3]),
    path=st.sampled_from(sorted(PATHS)),
)


def random_qp(seed: int, n: int, b: int, c: int, weak: float):
    """(H, g, lower, upper) of ``qp_family``."""
    rng = np.random.default_rng(seed)
    hessian = structured(rng, n, b, c, weak)
    gradient = rng.normal(size=n * b) * 10 ** rng.uniform(-2, 2)
    return hessian, gradient, *box(rng, n * b)


def assert_solves(hessian: BlockLowRank, gradient, lower, upper, x, tolerance: float) -> None:
    """x meets the KKT conditions and its objective is Clarabel's or lower."""
    dense = hessian.dense()
    assert_kkt(dense, gradient, lower, upper, x, tolerance)
    reference = qpsolvers.solve_qp(sp.csc_matrix(dense), gradient, lb=lower, ub=upper, solver="clarabel")

    def value(point):
        return 0.5 * point @ dense @ point + gradient @ point

    assert value(x) <= value(reference) + 1e-7 * (1 + abs(value(reference)))


@settings(max_examples=60)
@qp_family
def test_active_set_newton_meets_the_kkt_conditions_and_matches_clarabel(seed, n, b, c, weak, path):
    with mock.patch.object(box_qp, "DENSE_UP_TO", PATHS[path]):
        hessian, gradient, lower, upper = random_qp(seed, n, b, c, weak)
        solution = active_set_newton(hessian, gradient, lower, upper)
        if solution.x is None:  # cycled: allowed, the caller falls back from its best iterate
            assert solution.start is not None
            assert np.all(solution.start >= lower) and np.all(solution.start <= upper)
            return
        assert_solves(hessian, gradient, lower, upper, solution.x, tolerance=1e-7)
        # A guess changes the path, not the answer.
        again = active_set_newton(hessian, gradient, lower, upper, guess=solution)
    np.testing.assert_allclose(again.x, solution.x, rtol=1e-9, atol=1e-12)
    assert again.iterations <= 2


@both_paths
def test_active_set_newton_rarely_cycles(path, monkeypatch):
    """On 200 random problems of the SQP's shape (8 blocks of 20, 40 coupling rows, weak
    blocks) the sets cycle in at most a few."""
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", PATHS[path])
    rng = np.random.default_rng(2)
    cycled = 0
    for _ in range(200):
        hessian = structured(rng, 8, 20, 40, 1e-2)
        lower, upper = box(rng, 160)
        cycled += active_set_newton(hessian, rng.normal(size=160) * 100, lower, upper).x is None
    assert cycled <= 5, cycled  # measured: 1


@settings(max_examples=40)
@qp_family
def test_projected_newton_meets_the_kkt_conditions_and_matches_clarabel(seed, n, b, c, weak, path):
    """On the dense form and on the split (Woodbury for the free set), from any box around 0."""
    with mock.patch.object(box_qp, "DENSE_UP_TO", PATHS[path]):
        hessian, gradient, lower, upper = random_qp(seed, n, b, c, weak)
        x = projected_newton(hessian, gradient, lower, upper)
    assert x is not None
    assert_solves(hessian, gradient, lower, upper, x, tolerance=1e-6)


# Problems of ``structured(rng, 20, 4, 10, 1e-3)`` on which the exchange of sets alone cycles
# (found by search: 7 of 3,000 seeds).
CYCLING_SEEDS = [440, 812, 1593]
INTERIOR_POINTS = {"mehrotra": interior_point, "clarabel": lifted_clarabel}


@settings(max_examples=40)
@qp_family
def test_the_interior_points_meet_the_kkt_conditions_and_match_clarabel(seed, n, b, c, weak, path):
    """Mehrotra's steps on the split, and Clarabel on the lifted QP, then the exchange from
    their sets: the exact minimizer, in at most three exchanges; bounds that meet included."""
    for name, solver in INTERIOR_POINTS.items():
        with mock.patch.object(box_qp, "DENSE_UP_TO", PATHS[path]):
            hessian, gradient, lower, upper = random_qp(seed, n, b, c, weak)
            solution = solver(hessian, gradient, lower, upper)
        assert solution is not None and solution.x is not None, name
        assert solution.iterations <= 3, name
        assert_solves(hessian, gradient, lower, upper, solution.x, tolerance=1e-7)


@pytest.mark.parametrize("seed", CYCLING_SEEDS)
def test_mehrotra_solves_where_the_exchange_cycles(seed, monkeypatch):
    """On the problems whose exchange of sets cycles, and on one shaped like the SQP's at n = 200
    (blocks 1e4 times weaker than 40 coupling rows of 30 units' 20 inputs), the interior point
    ends at the minimizer without restarts."""
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", 0)
    rng = np.random.default_rng(seed)
    for n, b, c, weak in ((20, 4, 10, 1e-3), (30, 20, 40, 1e-2)):
        hessian = structured(rng, n, b, c, weak)
        lower, upper = box(rng, n * b)
        gradient = rng.normal(size=n * b) * 100
        solution = interior_point(hessian, gradient, lower, upper)
        assert solution is not None and solution.x is not None
        assert_solves(hessian, gradient, lower, upper, solution.x, tolerance=1e-7)


def test_free_part_on_the_split_matches_the_dense_form(monkeypatch):
    """Few free variables on the split (most inputs at their bounds): H_FF is formed from the
    blocks and the coupling's free columns, and the solve is the dense one's."""
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", 12)
    rng = np.random.default_rng(3)
    hessian = structured(rng, 5, 8, 6)
    assert hessian.is_split
    dense = hessian.dense()
    for count in (1, 5, 12):
        kept = np.sort(rng.choice(40, count, replace=False))
        np.testing.assert_allclose(hessian._free_part(kept), dense[np.ix_(kept, kept)], rtol=1e-12)
        free = np.isin(np.arange(40), kept)
        rhs = rng.normal(size=40)
        y = hessian.solve_free(free, rhs)
        assert np.all(y[~free] == 0)
        np.testing.assert_allclose(y[kept], np.linalg.solve(dense[np.ix_(kept, kept)], rhs[kept]), rtol=1e-9)


@both_paths
@pytest.mark.parametrize("seed", CYCLING_SEEDS)
def test_a_cycling_exchange_restarts_from_projected_newton_steps(seed, path, monkeypatch):
    """Without restarts the sets cycle and the method says so, with a start in the box no worse
    than 0; with them it ends at the minimizer."""
    monkeypatch.setattr(box_qp, "DENSE_UP_TO", PATHS[path])
    rng = np.random.default_rng(seed)
    hessian = structured(rng, 20, 4, 10, 1e-3)
    lower, upper = box(rng, 80)
    gradient = rng.normal(size=80) * 100
    alone = active_set_newton(hessian, gradient, lower, upper, restarts=0)
    assert alone.x is None and alone.start is not None
    assert np.all(alone.start >= lower) and np.all(alone.start <= upper)
    dense = hessian.dense()
    assert 0.5 * alone.start @ dense @ alone.start + gradient @ alone.start <= 0
    restarted = active_set_newton(hessian, gradient, lower, upper)
    assert restarted.x is not None
    assert_solves(hessian, gradient, lower, upper, restarted.x, tolerance=1e-7)
