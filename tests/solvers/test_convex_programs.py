"""The convex family's public view of its programs: ``ConvexAllocator.program`` is the program the
allocator's backend is given, and ``backends.clarabel_form`` / ``clarabel_solver`` /
``osqp_solver`` are the data and solvers the Clarabel and OSQP backends set up."""

from __future__ import annotations

import numpy as np
import pytest

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import allocator as convex_allocator
from platoon_opt.solvers.convex import backends
from tests.conftest import random_problem


def assert_same_program(mine, theirs) -> None:
    assert mine.key == theirs.key
    for attribute in ("P_upper", "K"):
        a, b = getattr(mine, attribute), getattr(theirs, attribute)
        np.testing.assert_array_equal(a.indptr, b.indptr)
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_array_equal(a.data, b.data)
    for attribute in ("q", "lower", "upper", "free", "fixed"):
        np.testing.assert_array_equal(getattr(mine, attribute), getattr(theirs, attribute))
    assert (mine.cone_columns is None) == (theirs.cone_columns is None)
    if mine.cone_columns is not None:
        np.testing.assert_array_equal(mine.cone_columns, theirs.cone_columns)


@pytest.mark.parametrize(
    "name, options",
    [
        ("qp", {}),
        ("qp", {"backend": "osqp"}),
        ("qp-projection", {}),
        ("cone", {}),
        ("cone-projection", {}),
        ("casadi-qp", {}),
        ("qp", {"priority": "strict"}),
    ],
)
def test_program_is_what_the_allocator_solves(name, options, monkeypatch):
    given = []

    def recording_solve(program, backend, workspaces, solver_options):
        given.append(program)
        return backends.solve(program, backend, workspaces, solver_options)

    monkeypatch.setattr(convex_allocator, "solve", recording_solve)
    allocator = get_allocator(name, **options)
    rng = np.random.default_rng(7)
    for _ in range(5):
        problem = random_problem(rng, 6)
        given.clear()
        allocation = allocator.allocate(problem)
        assert allocation.status == "optimal"
        if allocator.priority == "strict":
            target = allocation.info["stage1_task_velocity"]
            expected = [allocator.program(problem, "task"), allocator.program(problem, "deviation", target)]
        else:
            expected = [allocator.program(problem)]
        assert len(given) == len(expected)
        for mine, theirs in zip(expected, given):
            assert_same_program(mine, theirs)


def test_program_refuses_a_stage_of_another_reading():
    problem = random_problem(np.random.default_rng(0), 4)
    with pytest.raises(ValueError, match="stage"):
        get_allocator("qp-projection").program(problem, "task")


class RecordingSolver:
    """Forwards to a real Clarabel solver, recording what it was set up with."""

    def __init__(self, created: list, *args) -> None:
        self.args = args
        self._solver = REAL_SOLVER(*args)
        created.append(self)

    def __getattr__(self, name):
        return getattr(self._solver, name)


REAL_SOLVER = backends.clarabel.DefaultSolver


@pytest.mark.parametrize("name", ["qp", "cone", "cone-projection"])
def test_clarabel_form_is_what_clarabel_is_given(name, monkeypatch):
    created: list[RecordingSolver] = []
    monkeypatch.setattr(backends.clarabel, "DefaultSolver", lambda *args: RecordingSolver(created, *args))
    allocator = get_allocator(name)
    rng = np.random.default_rng(3)
    programs = [allocator.program(random_problem(rng, 5)) for _ in range(4)]
    workspaces = backends.Workspaces()
    for program in programs:
        backends.solve(program, "clarabel", workspaces, {})
    # A new solver for every program, even of one structure (its update would keep the first
    # program's equilibration), each set up with that program's form.
    assert len(created) == len(programs)
    for program, solver in zip(programs, created):
        P, q, A, b, cones, settings = solver.args
        form = backends.clarabel_form(program)
        assert (A != form.matrix).nnz == 0
        np.testing.assert_array_equal(A.indices, form.matrix.indices)
        np.testing.assert_array_equal(b, form.offsets)
        np.testing.assert_array_equal(form.matrix.data[form.k_entries], program.K_values)
        assert [repr(cone) for cone in cones] == [repr(cone) for cone in form.cones]
        assert (P != program.P_upper).nnz == 0 and np.array_equal(q, program.q)
        for key, value in backends.CLARABEL_SETTINGS.items():
            assert getattr(settings, key) == value


def test_bare_solvers_solve_the_backends_program():
    """A bare solve of ``clarabel_solver``/``osqp_solver`` gives the backend's answer."""
    allocator = get_allocator("qp")
    program = allocator.program(random_problem(np.random.default_rng(11), 6))
    x = backends.solve(program, "clarabel", backends.Workspaces(), {}).x
    np.testing.assert_array_equal(np.array(backends.clarabel_solver(program).solve().x), x)
    x = backends.solve(program, "osqp", backends.Workspaces(), {}).x
    np.testing.assert_array_equal(np.array(backends.osqp_solver(program).solve(raise_error=False).x), x)
