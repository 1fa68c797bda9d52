"""The convex allocators' and the dual's answers do not depend on the unrelated problems they
answered before (issue 19, section 5); iterative and nmpc: test_history_iterative_nmpc.py.

Each problem is answered fresh (a new allocator) and by one allocator object that answers every
problem in turn, forward and then backward, so that each answer comes after two different
histories. The problems are the soak's family (half of them of its degenerate kinds: gains of
1e6, zero nominal velocity, ...) and tests/conftest.py::random_problem, of 2 to 12 units. What is
compared: the status and the program's objective (``info["objective"]``, m^2/s^2), to 1e-7
relative (floored at OBJECTIVE_FLOOR: at a zero optimum the last digits of a zero are noise).
Clarabel updates its solver of a structure in place (strongly convex programs only), OSQP and
qpOASES start from their previous solve (warm start, hot start) and the dual from its previous
multipliers: that may speed a solve up, never change its answer beyond that tolerance (a kept
solver that fails, or whose answer is rejected, is replaced by a new one: the tests at the end).
"""

from __future__ import annotations

import numpy as np
import pytest

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import backends as qp_backends
from platoon_opt.solvers.registry import available_allocators
from platoon_opt.study import problems as family
from tests.conftest import random_problem
from tests.solvers.test_history_iterative_nmpc import problems

RELATIVE = 1e-7
OBJECTIVE_FLOOR = 1e-9  # m^2/s^2
# iterative and nmpc have their own test.
NAMES = [name for name in available_allocators() if name not in ("iterative", "nmpc")]


def test_every_registered_allocator_but_two_is_covered_here():
    assert set(available_allocators()) - set(NAMES) == {"iterative", "nmpc"}
    assert {"qp", "qp-projection", "cone", "cone-projection", "casadi-qp", "dual"} <= set(NAMES)


@pytest.mark.parametrize("options", [{}, {"priority": "strict"}], ids=["weighted", "strict"])
@pytest.mark.parametrize("name", NAMES)
def test_answers_do_not_depend_on_earlier_problems(name, options):
    if options and name.endswith("projection"):
        pytest.skip("strict priority is the achievable-first reading's")
    posed = problems(10, 12, seed=3)
    # Two problems of the soak family with gains of 1e6 and a small one between them.
    huge = [spec.build() for spec in family.specs(5, 400, degenerate_rate=1.0) if spec.kind == "huge_gains"]
    posed += [huge[0], posed[-2], huge[1]]
    fresh = [get_allocator(name, **options).allocate(problem) for problem in posed]
    allocator = get_allocator(name, **options)
    for turn, index in enumerate([*range(len(posed)), *reversed(range(len(posed)))]):
        after = allocator.allocate(posed[index])
        what = f"{allocator.name}, problem {index} (turn {turn})"
        assert after.status == fresh[index].status, what
        expected = fresh[index].info["objective"]
        difference = abs(after.info["objective"] - expected)
        assert difference <= RELATIVE * max(abs(expected), OBJECTIVE_FLOOR), what


def test_casadi_qp_retries_cold_when_a_hot_start_fails(monkeypatch):
    """A failure of a Function that solved before is retried once with a new Function: the
    answer is the fresh one, and a first solve that fails is not retried."""
    calls: list[bool] = []
    real = qp_backends._casadi_solve

    def hot_fails(entry, program):
        calls.append(entry.used)
        if entry.used:
            return None, "Premature homotopy termination because QP is infeasible."
        return real(entry, program)

    monkeypatch.setattr(qp_backends, "_casadi_solve", hot_fails)
    first, second = problems(4, 6, seed=9)[-2:]
    fresh = get_allocator("casadi-qp").allocate(second)
    allocator = get_allocator("casadi-qp")
    allocator.allocate(first)
    allocator.allocate(first)  # same structure: the hot start fails, the cold retry succeeds
    after = allocator.allocate(second)
    assert after.status == fresh.status == "optimal"
    assert after.info["objective"] == pytest.approx(fresh.info["objective"], rel=RELATIVE)
    assert calls[:4] == [False, False, True, False]  # fresh; first; hot start fails, cold retry


def test_casadi_qp_prints_nothing(capfd):
    """qpOASES prints its licence banner when a solver object is made, at any printLevel: the
    backend drops what the native code writes to stdout while it builds and solves."""
    problem = problems(3, 5, seed=2)[-1]
    allocation = get_allocator("casadi-qp").allocate(problem)
    assert allocation.status == "optimal"
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""


@pytest.mark.parametrize("name", ["casadi-qp", "qp"])
def test_soak_problem_26_after_its_chunk_is_answered_as_fresh(name):
    """Soak seed 11, problem 26 (gains of 1e6), after problems 0-25 of its chunk on the same
    object: qpOASES hot-started from problem 25 ended in "premature homotopy termination", and a
    Clarabel solver updated in place reported DualInfeasible; fresh, both solve it."""
    specs = family.chunk_specs(11, 0)
    allocator = get_allocator(name)
    for spec in specs[:26]:
        allocator.allocate(spec.build())
    problem = specs[26].build()
    assert specs[26].kind == "huge_gains"
    after, fresh = allocator.allocate(problem), get_allocator(name).allocate(problem)
    assert after.status == fresh.status == "optimal"
    assert after.info["objective"] == pytest.approx(fresh.info["objective"], rel=RELATIVE)


class _StaleSolver:
    """A kept Clarabel solver whose next solve answers as ``result`` does (updates pass on)."""

    def __init__(self, solver, result) -> None:
        self._solver, self._result = solver, result

    def solve(self):
        return self._result(self._solver.solve())

    def __getattr__(self, name):
        return getattr(self._solver, name)


class _Result:
    def __init__(self, x, status, iterations=0) -> None:
        self.x, self.status, self.iterations = x, status, iterations


def test_a_kept_clarabel_solver_that_fails_is_replaced_by_a_new_one(monkeypatch):
    rng = np.random.default_rng(5)
    allocator = get_allocator("qp")
    first, second = (allocator.program(random_problem(rng, 6)) for _ in range(2))
    assert first.key == second.key
    fresh = qp_backends.clarabel_solver(second).solve()
    workspaces = qp_backends.Workspaces()
    qp_backends.solve(first, "clarabel", workspaces, {})
    kept = workspaces.get(("clarabel", first.key))
    kept.solver = _StaleSolver(kept.solver, lambda real: _Result(real.x, "AlmostSolved"))
    solved = qp_backends.solve(second, "clarabel", workspaces, {})
    assert not solved.reused and workspaces.get(("clarabel", second.key)) is not kept
    np.testing.assert_array_equal(solved.x, np.array(fresh.x))


def test_a_rejected_answer_of_a_kept_clarabel_solver_is_solved_again_by_a_new_one(monkeypatch):
    """A kept solver that reports "Solved" with rows violated: the allocator's check rejects it
    and the same backend solves the program afresh, before any fallback."""
    rng = np.random.default_rng(6)
    first, second = random_problem(rng, 5), random_problem(rng, 5)
    fresh = get_allocator("qp", fallbacks=()).allocate(second)
    allocator = get_allocator("qp", fallbacks=())
    key = allocator.program(first).key
    assert allocator.program(second).key == key
    allocator.allocate(first)
    kept = allocator._workspaces.get(("clarabel", key))
    solved = qp_backends.clarabel.SolverStatus.Solved
    kept.solver = _StaleSolver(kept.solver, lambda real: _Result(np.array(real.x) + 1e-3, solved))
    after = allocator.allocate(second)
    assert after.status == fresh.status == "optimal" and not after.fell_back
    assert after.info["objective"] == pytest.approx(fresh.info["objective"], rel=RELATIVE)
