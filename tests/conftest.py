"""Shared test helpers: random platoon states and problems."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import settings

from platoon_opt import AllocationProblem, MeanVarianceTask, PlatoonState, VehicleLimits

settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci")


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
