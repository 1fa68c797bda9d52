"""The scaled convex programs (formulation.Program, docs/programs.md section 4): the backends
solve them on the soak's hard kinds (gains of 1e6, zero nominal velocity), and what they return
is the minimizer of the unscaled program (its KKT conditions, and the dual allocator's exact
answer)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import backends as qp_backends
from platoon_opt.solvers.convex import formulation as fm
from platoon_opt.solvers.convex.allocator import FEASIBILITY_TOLERANCE
from platoon_opt.solvers.dual.allocator import DualAllocator
from platoon_opt.study import problems as family
from tests.solvers.test_qp import kkt_residual

CONVEX = ("qp", "qp-projection", "cone", "cone-projection", "casadi-qp")


def problems_of(kind: str, count: int, seed: int = 7) -> list:
    """``count`` problems of the soak family's ``kind`` (its random numbers, seed ``seed``)."""
    specs = family.draw_specs(np.random.default_rng(seed), count, degenerate_rate=0.0)
    return [dataclasses.replace(spec, kind=kind).build() for spec in specs]


def dual_like(allocator) -> DualAllocator:
    """The dual allocator posing the same program as the convex ``allocator``."""
    return DualAllocator(
        reading=allocator.reading,
        speed=allocator.speed,
        rho=allocator.rho,
        eps=allocator.eps,
        sides=allocator.sides,
        priority=allocator.priority,
        precedence=allocator.precedence,
        anchor_weight=allocator.anchor_weight,
    )


def test_the_scaled_rows_have_unit_norm_and_the_map_is_invertible():
    problem = problems_of("huge_gains", 1)[0]
    for name in ("qp", "qp-projection"):
        program = get_allocator(name).program(problem)
        norms = np.sqrt(np.asarray(program.K.multiply(program.K).sum(axis=1))).ravel()
        np.testing.assert_allclose(norms[norms > 0], 1.0, rtol=1e-12)
        x = np.random.default_rng(1).normal(size=program.variables)
        np.testing.assert_allclose(program.original(program.scaled(x)), x, rtol=1e-12, atol=1e-9)
        # The right-hand sides of the equality rows are shifted to 0 (u reaches 1e6 m/s here).
        assert np.abs(program.upper[: program.n_eq]).max(initial=0.0) <= 1e-6


@pytest.mark.parametrize(
    "kind,backend",
    [
        ("huge_gains", "clarabel"),
        ("zero_nominal", "clarabel"),
        ("random", "clarabel"),
        ("zero_nominal", "osqp"),
        ("random", "osqp"),
    ],
)
@pytest.mark.parametrize("name", ["qp", "qp-projection"])
def test_scaled_solutions_meet_the_unscaled_kkt_conditions(kind, name, backend):
    # OSQP (a first-order method, stopping at 1e-9 of the data's size) ends "solved inaccurate"
    # on task-exact programs with gains of 1e6, whose linear term stays of order |u|^2 / v_max^2;
    # it is the default allocators' fallback, not their backend.
    allocator = get_allocator(name)
    for problem in problems_of(kind, 6):
        setup = allocator.setup(problem)
        scaled = fm.build(problem, setup)
        unscaled = fm.build(problem, setup, scaled=False)
        y = qp_backends.solve(scaled, backend, qp_backends.Workspaces(), {}).x
        x = scaled.original(y)
        equality, inside = unscaled.violation(x)
        assert inside <= FEASIBILITY_TOLERANCE
        assert equality <= 1e-6 * unscaled.equality_scale
        # Stationarity to 1e-5 relative to 1 + |gradient|: an interior-point answer stops at a
        # gap of 1e-9 v_max^2, which at a zero-nominal optimum (objective ~ 0, gradient ~ 1e-4)
        # leaves residuals of about 1e-6.
        assert kkt_residual(unscaled, x) <= 1e-5
        # Program.objective is the reading's objective whatever the scaling.
        assert scaled.objective(y) == pytest.approx(unscaled.objective(x), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("kind", ["huge_gains", "zero_nominal", "random"])
@pytest.mark.parametrize("name", CONVEX)
def test_convex_allocators_solve_the_hard_kinds_as_the_dual_does(kind, name):
    """No fallback, and the objective of the exact dual solve of the same program (relative to
    the objective's own scale: at the zero-nominal optimum the task-exact objective is 0)."""
    allocator = get_allocator(name)
    dual = dual_like(allocator)
    for problem in problems_of(kind, 8):
        allocation = allocator.allocate(problem)
        assert allocation.status == "optimal", allocation.status
        reference = dual.allocate(problem)
        assert reference.status == "optimal", reference.status
        scale = 1.0 + abs(reference.info["objective"])
        assert abs(allocation.info["objective"] - reference.info["objective"]) <= 1e-6 * scale


@pytest.mark.parametrize("index", [1608, 4520])
def test_task_exact_cone_programs_with_huge_gains_are_not_called_infeasible(index):
    """Soak seed 11, problems 1608 and 4520 (gains of 1e6): at Clarabel's infeasibility
    tolerance of 1e-8 the scaled cone-projection program ended "DualInfeasible" (its objective
    is bounded below); at 1e-12 it is solved, to the dual's objective."""
    spec = family.spec_at(11, index)
    assert spec.kind == "huge_gains"
    problem = spec.build()
    allocator = get_allocator("cone-projection")
    allocation = allocator.allocate(problem)
    assert allocation.status == "optimal"
    reference = dual_like(allocator).allocate(problem)
    scale = 1.0 + abs(reference.info["objective"])
    assert abs(allocation.info["objective"] - reference.info["objective"]) <= 1e-6 * scale
