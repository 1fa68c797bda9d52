"""Shared test helpers: random platoon states and problems, a model-only allocator, scenario texts."""

from __future__ import annotations

import dataclasses
import gc
import os
import shutil
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import settings

from platoon_opt import Allocation, AllocationProblem, MeanVarianceTask, PlatoonState, VehicleLimits, engine
from platoon_opt.avoidance import CircularObstacles
from platoon_opt.limits import unit_rows
from platoon_opt.scenarios import SCENARIO_DIR
from platoon_opt.solvers.convex.allocator import FEASIBILITY_TOLERANCE
from platoon_opt.study.compile_cache import enable_compilation_cache

# The tests leave the user's compilation cache alone: one folder per test session, made by its
# first process and inherited by the pytest-xdist workers and the study's worker processes, so that
# a test loads what another compiled (the fixture below drops programs from memory after each
# module; a file half written by one process is compiled again by another, with a warning).
# test_compile_cache sets folders of its own.
_PROGRAMS_PREFIX = "platoon-opt-test-programs-"
_OWN_PROGRAMS: str | None = None
if _PROGRAMS_PREFIX not in os.environ.get("PLATOON_OPT_JAX_CACHE", ""):
    _OWN_PROGRAMS = os.environ["PLATOON_OPT_JAX_CACHE"] = tempfile.mkdtemp(prefix=_PROGRAMS_PREFIX)
enable_compilation_cache()


def pytest_unconfigure(config):
    """The session's first process removes the folder of compiled programs it made."""
    if _OWN_PROGRAMS is not None:
        shutil.rmtree(_OWN_PROGRAMS, ignore_errors=True)


settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop every compiled program after each test module: each keeps hundreds of memory mappings,
    and one process may have 65,530 (``platoon_opt.engine.PROGRAMS_KEPT``)."""
    yield
    engine._compiled.cache_clear()
    jax.clear_caches()
    gc.collect()


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


def padded_safe_state(state, problem, gear):
    """``state`` (of a ``safe_problem``), its obstacles and ``gear`` as JAX arrays, with far units
    (up to 8) and far obstacles (up to 3) added that constrain no one: one compiled program for
    every ``safe_problem``."""
    n, far = problem.n, 1e6
    extra = 8 - n
    x = np.concatenate((state.x, far + 10.0 * np.arange(extra)))
    y = np.concatenate((state.y, np.full(extra, far)))
    padded = PlatoonState(x, y, *(np.concatenate((a, np.zeros(extra))) for a in (state.theta, state.alpha)))
    padded = dataclasses.replace(padded, gear=np.concatenate((state.gear, np.ones(extra))))
    obstacles = problem.obstacles
    missing = 3 - len(obstacles)
    centers = np.concatenate(
        (obstacles.centers, np.full((missing, 2), -far) - 10.0 * np.arange(missing)[:, None])
    )
    radii = np.concatenate((obstacles.radii, np.full(missing, 0.1)))
    traced = (padded, CircularObstacles(centers, radii), np.concatenate((gear, np.ones(extra))))
    return jax.tree_util.tree_map(jnp.asarray, traced)


def safe_problem(seed: int, *, safety=None, crowded: bool = False) -> AllocationProblem:
    """A problem from a random safe state near obstacles and neighbours (``safety``: a
    ``SafetyParams`` with barriers on; default one with a random rate): units pressed against
    inflated obstacles and neighbours at the safety distance, some steering at the limit, some
    backing, a random task target. Drawn again until the state is safe."""
    from platoon_opt.safety import SafetyParams

    rng = np.random.default_rng(seed)
    params = safety or SafetyParams(mode="barrier", barrier_rate=float(rng.choice([0.1, 0.5, 1.0])))
    while True:
        n = int(rng.integers(2, 9))
        k = int(rng.integers(0, 4))
        centers, radii = rng.uniform(-1, 1, (k, 2)), rng.uniform(0.05, 0.4, k)
        spread = 0.5 if crowded else 1.2
        positions = rng.uniform(-spread, spread, (n, 2))
        if k:  # some units right at an inflated surface
            pressed = rng.random(n) < 0.5
            which = rng.integers(0, k, n)
            angle = rng.uniform(-np.pi, np.pi, n)
            inflated = radii[which] + params.obstacle_margin + rng.uniform(0, 0.02, n)
            at = centers[which] + inflated[:, None] * np.column_stack((np.cos(angle), np.sin(angle)))
            positions = np.where(pressed[:, None], at, positions)
        gap = positions[:, None] - positions[None]
        distance = np.hypot(gap[..., 0], gap[..., 1]) + np.eye(n) * 1e9
        clearance = (
            np.hypot(*(positions[:, None] - centers[None]).transpose(2, 0, 1))
            - radii
            - params.obstacle_margin
        )
        if distance.min() >= params.safety_distance and (k == 0 or clearance.min() >= 0):
            break
    steering = rng.uniform(-LIMITS.max_steering, LIMITS.max_steering, n)
    steering = np.where(rng.random(n) < 0.3, np.sign(steering) * LIMITS.max_steering, steering)
    state = PlatoonState(
        positions[:, 0], positions[:, 1], rng.uniform(-np.pi, np.pi, n), steering, rng.choice([-1.0, 1.0], n)
    )
    task = MeanVarianceTask()
    desired = task.value(state.positions) + rng.normal(0, 0.5, 4) * np.array([1, 0.3, 1, 0.3])
    return AllocationProblem.build(
        state,
        task,
        desired,
        rng.normal(0, 0.5, 4),
        GAINS,
        LIMITS,
        0.01,
        obstacles=CircularObstacles(centers, radii),
        safety=params,
    )


def barrier_margin(problem: AllocationProblem, velocities: np.ndarray, params) -> float:
    """How well ``velocities`` (n, 2) keep the barriers once driven through the real vehicle model
    for one step (the unit controller, the steering rate, the exact arcs): the least of h(after)
    over every unit-obstacle pair and unit pair, and of h(after) - (1 - gamma) h(before) over the
    constrained ones (within ``params.reach`` of the obstacle's inflated surface or of the safety
    distance), m^2. >= 0 (to round-off) is the guarantee."""
    from platoon_opt.vehicle import step_vehicles, unit_controller

    state, dt = problem.state, problem.dt
    after = step_vehicles(state, unit_controller(state, velocities, problem.limits, dt), problem.limits, dt)
    keep, reach = 1 - params.barrier_rate, params.reach(problem.limits, dt)

    def values(positions):
        """h of every pair and whether it is constrained."""
        obstacles = problem.obstacles
        inflated = obstacles.radii + params.obstacle_margin
        distance = np.hypot(*(positions[:, None] - obstacles.centers[None]).transpose(2, 0, 1))
        upper = np.triu_indices(positions.shape[0], 1)
        gap = np.hypot(*(positions[:, None] - positions[None]).transpose(2, 0, 1))[upper]
        h = np.concatenate(((distance**2 - inflated**2).ravel(), gap**2 - params.safety_distance**2))
        near = np.concatenate(((distance < inflated + reach).ravel(), gap < params.safety_distance + reach))
        return h, near

    (before, near), (now, _) = values(state.positions), values(after.positions)
    return float(min(np.min(now, initial=np.inf), np.min((now - keep * before)[near], initial=np.inf)))
