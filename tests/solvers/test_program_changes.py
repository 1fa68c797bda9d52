"""The program solved is the program asked for (issue 19, section 4): after a backend failure the
convex allocators try the other backends of the same program, then the dual allocator on the same
program, and only then another program, which ``Allocation.program_changed`` and
``info["program"]`` report."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from platoon_opt import AllocationProblem
from platoon_opt.metrics import integrated_errors
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import backends as qp_backends
from platoon_opt.solvers.convex.backends import BackendFailure
from platoon_opt.solvers.dual.allocator import DualAllocator
from platoon_opt.tasks import MeanVarianceTask
from platoon_opt.vehicle import PlatoonState, VehicleLimits
from tests.conftest import random_problem, without_dual
from tests.solvers.test_scaling import dual_like


def issue_problem() -> AllocationProblem:
    """The reproduction of issue 19, section 4: Clarabel left a row violated by 2.4e-7 and
    cone-projection was answered by OSQP on the 16-gon."""
    state = PlatoonState(
        x=np.array([-0.2947892639433781, 0.521885625777265]),
        y=np.array([0.30846612613561675, 0.2837928795211515]),
        theta=np.array([-1.7693579622132214, -2.604191152802843]),
        alpha=np.array([0.7146114523081213, -0.12173508535393573]),
        gear=np.array([-1.0, -1.0]),
    )
    return AllocationProblem.build(
        state,
        MeanVarianceTask(),
        desired=np.array([0.3468192176743969, 0.5106922871847158, 0.35352815790278697, 0.3227609792521817]),
        desired_rate=np.array(
            [-0.2665386360749642, -0.040097988178963956, -0.34617640924211845, 0.5480048520681368]
        ),
        gains=np.array([279.1415293555599, 55.82830587111197, 279.1415293555599, 55.82830587111197]),
        limits=VehicleLimits(),
        dt=0.01,
    )


def test_issue_reproduction_is_answered_by_the_cone_program():
    problem = issue_problem()
    allocation = get_allocator("cone-projection").allocate(problem)
    assert allocation.status == "optimal" and not allocation.program_changed
    assert allocation.info["program"] == "as asked"
    exact = get_allocator("dual", reading="task-exact", speed="cone").allocate(problem)
    assert exact.status == "optimal"
    np.testing.assert_allclose(allocation.velocities, exact.velocities, atol=1e-7)


def fail_clarabel(monkeypatch) -> None:
    def broken(program, workspaces, options, fresh):
        raise BackendFailure("AlmostSolved")

    monkeypatch.setattr(qp_backends, "_clarabel", broken)


@pytest.mark.parametrize(
    "name,options",
    [
        ("cone-projection", {}),
        ("cone", {}),
        ("cone", {"priority": "strict"}),
        ("qp", {"fallbacks": ()}),
        ("qp-projection", {"fallbacks": ()}),
    ],
)
def test_after_clarabel_fails_the_dual_solves_the_same_program(name, options, monkeypatch):
    fail_clarabel(monkeypatch)
    problem = issue_problem()
    allocator = get_allocator(name, **options)
    allocation = allocator.allocate(problem)
    stage = "[task]" if options.get("priority") == "strict" else ""
    assert allocation.status == f"fallback:clarabel{stage}:AlmostSolved->dual"
    assert allocation.fell_back and not allocation.program_changed
    assert allocation.info["program"] == "as asked"
    exact = dual_like(allocator).allocate(problem)
    np.testing.assert_array_equal(allocation.velocities, exact.velocities)


def failed_dual(problem: AllocationProblem):
    """A dual allocation that fell back (no Newton step allowed), standing in for a failing dual."""
    allocation = dataclasses.replace(get_allocator("dual"), max_iterations=0).allocate(problem)
    assert allocation.fell_back
    return allocation


def test_the_cone_program_is_changed_only_after_the_dual_failed(monkeypatch):
    problem = issue_problem()
    allocator = get_allocator("cone-projection")
    # Two units, four task rows: a is fixed by J a = u; the achievable parts c tell the programs apart.
    achievable = dual_like(allocator).allocate(problem).info["achievable"]
    failed = failed_dual(problem)
    fail_clarabel(monkeypatch)
    monkeypatch.setattr(DualAllocator, "allocate", lambda self, p: failed)
    allocation = allocator.allocate(problem)
    assert allocation.status.startswith("fallback:clarabel:AlmostSolved; dual:")
    assert allocation.status.endswith("->osqp(polygon)")
    assert allocation.program_changed and allocation.info["program"] == "polygon"
    assert not np.allclose(allocation.info["achievable"], achievable, atol=1e-6)


def test_the_last_resort_projection_is_a_change_of_program(monkeypatch):
    problem = random_problem(np.random.default_rng(4), 5)
    failed = failed_dual(problem)
    fail_clarabel(monkeypatch)
    monkeypatch.setattr(qp_backends, "_osqp", lambda *args: (_ for _ in ()).throw(BackendFailure("x")))
    monkeypatch.setattr(DualAllocator, "allocate", lambda self, p: failed)
    allocation = get_allocator("qp").allocate(problem)
    assert allocation.status.endswith("->projection")
    assert allocation.program_changed and allocation.info["program"] == "projection"


def test_a_run_counts_its_program_changes(monkeypatch):
    fail_clarabel(monkeypatch)
    allocator = get_allocator("cone", fallbacks=("osqp",))
    without_dual(allocator)  # OSQP on the polygon answers
    trajectory = simulate(load_scenario("paper_obstacles"), allocator, duration=0.05)
    metrics = integrated_errors(trajectory)
    assert metrics["fallback_steps"] == metrics["program_changes"] == trajectory.status.shape[0] > 0
    assert np.all(trajectory.program_changed)
