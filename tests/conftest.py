"""Shared test helpers: random platoon states and problems, a model-only allocator, scenario texts."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from hypothesis import settings

from platoon_opt import Allocation, AllocationProblem, MeanVarianceTask, PlatoonState, VehicleLimits
from platoon_opt.limits import unit_rows
from platoon_opt.scenarios import SCENARIO_DIR
from platoon_opt.solvers.convex.allocator import FEASIBILITY_TOLERANCE

settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci")

LIMITS = VehicleLimits()
GAINS = np.array([50.0, 10, 50, 10])


def random_state(rng: np.random.Generator, n: int, spread: float = 2.0) -> PlatoonState:
    """n units scattered over a square of side ``spread``, random headings and steering."""
    limits = VehicleLimits()
    return PlatoonState(
        x=rng.uniform(-spread, spread, n),
        y=rng.uniform(-spread, spread, n),
        theta=rng.uniform(-np.pi, np.pi, n),
        alpha=rng.uniform(-limits.max_steering, limits.max_steering, n),
        gear=rng.choice([-1.0, 1.0], n),
    )


def random_problem(rng: np.random.Generator, n: int, **kwargs) -> AllocationProblem:
    """An allocation problem for a random state and a random task target."""
    state = random_state(rng, n)
    task = MeanVarianceTask()
    value = task.value(state.positions)
    desired = value + rng.normal(0, 0.5, 4) * np.array([1, 0.3, 1, 0.3])
    return AllocationProblem.build(
        state,
        task,
        desired,
        rng.normal(0, 0.5, 4),
        np.array([50.0, 10, 50, 10]),
        VehicleLimits(),
        0.01,
        **kwargs,
    )


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


class NominalAllocator:
    """Hands every unit its nominal velocity (Eq. 5 alone): the model's tests drive closed loops
    without an allocator of the solvers' floor."""

    name = "nominal"

    def allocate(self, problem: AllocationProblem) -> Allocation:
        start = time.perf_counter()
        return Allocation.of(
            problem,
            problem.nominal,
            allocator=self.name,
            status="nominal",
            iterations=0,
            solve_time=time.perf_counter() - start,
        )


def scenario_text(name: str) -> str:
    """The text of the shipped scenario file ``name``."""
    return (SCENARIO_DIR / f"{name}.toml").read_text()


def build_problem(
    x, y, theta, *, desired=None, rate=(0.0, 0.0, 0.0, 0.0), alpha=None, gear=None, exempt=None
):
    """A problem for units at (x, y) with headings theta; f_d defaults to the current f."""
    n = len(x)
    state = PlatoonState(
        np.asarray(x, float),
        np.asarray(y, float),
        np.asarray(theta, float) * np.ones(n),
        np.zeros(n) if alpha is None else np.asarray(alpha, float),
        None if gear is None else np.asarray(gear, float),
    )
    task = MeanVarianceTask()
    value = task.value(state.positions)
    problem = AllocationProblem.build(
        state, task, value if desired is None else np.asarray(desired), np.asarray(rate), GAINS, LIMITS, 0.01
    )
    return problem if exempt is None else dataclasses.replace(problem, exempt=np.asarray(exempt, bool))


def degenerate_problems() -> dict[str, AllocationProblem]:
    """All units on one vertical line (var_x = 0), coincident units (both variances 0), and a zero
    nominal velocity (f = f_d, no repulsion)."""
    n = 6
    y = 2.0 * np.arange(n)
    rng = np.random.default_rng(3)
    theta = rng.uniform(-np.pi, np.pi, n)
    line = build_problem(np.zeros(n), y, theta, desired=[1.0, 0.5, 4.0, 12.0], rate=[0.8, 0.0, 0.0, 0.0])
    coincident = build_problem(
        np.ones(n), np.ones(n), theta, desired=[2.0, 0.6, 1.0, 0.5], exempt=np.zeros(n, dtype=bool)
    )
    zero = build_problem(2.0 * np.arange(n), y % 4, theta)
    return {"line": line, "coincident": coincident, "zero": zero}


def free_problem(seed: int, n: int = 8) -> AllocationProblem:
    """A random problem with no unit under the precedence rule."""
    problem = random_problem(np.random.default_rng(seed), n)
    return dataclasses.replace(problem, exempt=np.zeros(n, dtype=bool))


def rows_of(allocator, problem):
    """A convex allocator's sets for ``problem`` and their linear rows (normals, offsets)."""
    sets = problem.achievable(rate_aware=allocator.rate_aware)
    return sets, *unit_rows(sets, allocator.speed, allocator.sides, problem.limits.max_speed)


def assert_inside(allocator, problem, allocation):
    """The achievable part of every unit lies in its polygon (and its exact sector) to 1e-7."""
    sets, normals, offsets = rows_of(allocator, problem)
    achievable = allocation.info["achievable"]
    excess = np.einsum("ikj,ij->ik", normals, achievable) - offsets
    assert np.max(excess) <= FEASIBILITY_TOLERANCE
    assert np.max(sets.distance(achievable)) <= FEASIBILITY_TOLERANCE


def without_dual(allocator):
    """A convex ``allocator`` without its exact fallback (the dual allocator on the same program),
    to reach the fallbacks after it."""
    object.__setattr__(allocator, "_exact", None)
    return allocator


def agree(values: list[float]) -> bool:
    """Relative agreement to 1e-6 (objectives in (m/s)^2, floored at 1e-3 (m/s)^2)."""
    values = np.asarray(values)
    return bool(np.ptp(values) <= 1e-6 * max(np.max(np.abs(values)), 1e-3))
