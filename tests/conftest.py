"""Shared test helpers: random platoon states and problems, a model-only allocator, scenario texts."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from hypothesis import settings

from platoon_opt import Allocation, AllocationProblem, MeanVarianceTask, PlatoonState, VehicleLimits
from platoon_opt.scenarios import SCENARIO_DIR

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
