"""What the benchmark measures: the allocator configurations (``entries``), the repetitions per
size, the random problems of the scale part (``scale_problem``) and the problems of the paper
scenario's closed loop (``closed_loop_problems``).

Contract: ``scale_problem(n, seed)`` is the same problem in every run; an ``Entry`` builds a fresh
allocator through the registry. The other parts look ``entries`` and ``repetitions`` up on this
module when they run (a test may narrow them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from platoon_opt import (
    AllocationProblem,
    MeanVarianceTask,
    PlatoonState,
    VehicleLimits,
    load_scenario,
    simulate,
)
from platoon_opt.allocation import Allocation, Allocator
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex import ConvexAllocator
from platoon_opt.solvers.registry import PromisingAllocator

SIZES = (8, 64, 512, 4096, 32768)
DUAL_ONLY_SIZES = (100_000,)
# Mean spacing of the units in scale problems (m): neighbours within d_minr = 1 m are common.
SPACING = 1.5
# The scenario of the n = 8 comparison and of the closed loops.
SCENARIO = "paper_no_obstacles"


@dataclass(frozen=True)
class Entry:
    """One allocator configuration of the benchmark.

    Attributes:
        label: name in the tables.
        name, options: ``get_allocator(name, **options)``.
        reading, speed: the program it solves (its dual counterpart solves the same one;
            reading "strict": the achievable-first reading under strict priority).
        backend: "dual", "clarabel" or "osqp".
        sizes: problem sizes it is run at (None: every size of the run but dual-only ones).
    """

    label: str
    name: str
    options: dict[str, Any]
    reading: str
    speed: str
    backend: str
    sizes: tuple[int, ...] | None = None

    def build(self) -> PromisingAllocator:
        return get_allocator(self.name, **self.options)


def convex(allocator: Allocator) -> ConvexAllocator:
    """``allocator`` as the ``ConvexAllocator`` every QP name builds, for the parts that pose its
    program (``ConvexAllocator.program``); TypeError for any other allocator."""
    if not isinstance(allocator, ConvexAllocator):
        raise TypeError(f"{allocator.name} is a {type(allocator).__name__}, not a ConvexAllocator")
    return allocator


def entries() -> list[Entry]:
    """The allocators measured: the dual in its four programs and under strict priority, and the
    QP allocators that pose the same programs (OSQP at its exact settings, eps 1e-9, for the
    polygon)."""
    af, te = "achievable-first", "task-exact"
    return [
        Entry("dual", "dual", {}, af, "polygon", "dual"),
        Entry("dual cone", "dual", {"speed": "cone"}, af, "cone", "dual"),
        Entry("dual task-exact", "dual", {"reading": te}, te, "polygon", "dual"),
        Entry("dual task-exact cone", "dual", {"reading": te, "speed": "cone"}, te, "cone", "dual"),
        Entry("qp clarabel", "qp", {"backend": "clarabel"}, af, "polygon", "clarabel"),
        Entry("qp osqp", "qp", {"backend": "osqp"}, af, "polygon", "osqp"),
        Entry("cone clarabel", "cone", {}, af, "cone", "clarabel"),
        Entry("qp-projection clarabel", "qp-projection", {"backend": "clarabel"}, te, "polygon", "clarabel"),
        # OSQP needs minutes for the task-exact program beyond a few hundred units.
        Entry(
            "qp-projection osqp", "qp-projection", {"backend": "osqp"}, te, "polygon", "osqp", (8, 64, 512)
        ),
        Entry("cone-projection clarabel", "cone-projection", {}, te, "cone", "clarabel"),
        # Strict priority: Wolfe's stage 1, then the penalized second stage; QP: two programs.
        Entry("dual strict", "dual", {"priority": "strict"}, "strict", "polygon", "dual"),
        Entry(
            "qp strict clarabel",
            "qp",
            {"backend": "clarabel", "priority": "strict"},
            "strict",
            "polygon",
            "clarabel",
        ),
    ]


def repetitions(n: int, backend: str) -> int:
    """Repetitions per size: fewer where one call takes seconds."""
    if backend == "dual":
        return 21 if n <= 4096 else 7
    return 15 if n <= 512 else (5 if n <= 4096 else 2)


def scale_problem(n: int, seed: int) -> AllocationProblem:
    """A platoon of n units spread uniformly at mean spacing ``SPACING`` with random headings,
    tracking a target that moves at 0.8 m/s, 5 mm off the mean and 0.5 % off the variances:
    a mix of achievable, steering-limited and speed-limited nominal velocities."""
    rng = np.random.default_rng(seed)
    side = SPACING * math.sqrt(n)
    limits = VehicleLimits()
    state = PlatoonState(
        x=rng.uniform(0, side, n),
        y=rng.uniform(0, side, n),
        theta=rng.uniform(-np.pi, np.pi, n),
        alpha=rng.uniform(-limits.max_steering, limits.max_steering, n),
        gear=np.ones(n),
    )
    task = MeanVarianceTask()
    value = task.value(state.positions)
    offset = np.array([0.005, 0.005 * value[1], -0.005, -0.005 * value[3]])
    return AllocationProblem.build(
        state,
        task,
        value + offset,
        np.array([0.8, 0.0, 0.0, 0.0]),
        np.array([50.0, 10, 50, 10]),
        limits,
        0.01,
    )


def closed_loop_problems(duration: float) -> list[AllocationProblem]:
    """The problems of every step of the paper scenario (no obstacles) under the dual."""
    problems: list[AllocationProblem] = []
    dual = get_allocator("dual")

    class Recorder:
        name = "recorder"

        def allocate(self, problem: AllocationProblem) -> Allocation:
            problems.append(problem)
            return dual.allocate(problem)

    simulate(load_scenario(SCENARIO), Recorder(), duration=duration)
    return problems
