"""The host's problems made alike, so that one compiled dual solve serves many of them.

The host's ``DualAllocator.allocate`` compiles its kernel once per shape and static value (a few
seconds each); the problems it meets (the soak's 2 to 12 units, the tests' random sizes and
obstacle counts) would compile one program each. ``padded`` appends units that take no part in
any program: zero columns of J (they serve no task), nominal velocity 0 (which every set
contains, so their v and c are 0 and their deviation 0) and no precedence rule; the answer's
first n rows are the problem's. ``canonical`` also replaces what the kernel does not read (the
obstacles, the avoidance and safety parameters: the barrier rows come in the safe sets) by fixed
values. The compiled engine needs neither (its shapes are fixed per run).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from platoon_opt.arrays import unchecked
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.limits import AchievableSets
from platoon_opt.problem import AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.safety import SafetyParams
from platoon_opt.vehicle import PlatoonState

# Sizes up to this are rounded up to a power of 2 (at least SMALLEST); larger ones to a multiple of it.
BLOCK = 4096
SMALLEST = 8


def bucket(n: int) -> int:
    """The padded size of a platoon of n units."""
    if n <= BLOCK:
        return max(SMALLEST, 1 << math.ceil(math.log2(max(n, 1))))
    return -(-n // BLOCK) * BLOCK


def _pad(array: np.ndarray, extra: int, axis: int, value: float = 0.0) -> np.ndarray:
    width = [(0, 0)] * np.ndim(array)
    width[axis] = (0, extra)
    return np.pad(np.asarray(array), width, constant_values=value)


def padded(problem: AllocationProblem, safe: SafeSets | None) -> tuple[AllocationProblem, SafeSets | None]:
    """``canonical(problem)`` and its safe sets with units appended up to ``bucket(n)`` (module
    docstring)."""
    problem = canonical(problem)
    extra = bucket(problem.n) - problem.n
    if extra == 0:
        return problem, safe
    state = problem.state
    grown = PlatoonState.trusted(
        _pad(state.x, extra, 0),
        _pad(state.y, extra, 0),
        _pad(state.theta, extra, 0),
        _pad(state.alpha, extra, 0),
        _pad(state.gear, extra, 0, 1.0),
    )
    jacobian = dataclasses.replace(problem.jacobian, rows=_pad(problem.jacobian.rows, extra, 1))
    problem = dataclasses.replace(
        problem,
        state=grown,
        jacobian=jacobian,
        secondary=_pad(problem.secondary, extra, 0),
        nominal=_pad(problem.nominal, extra, 0),
        exempt=_pad(problem.exempt, extra, 0, False),
        gear=_pad(problem.gear, extra, 0, 1.0),
        obstacle_distance=_pad(problem.obstacle_distance, extra, 0, np.inf),
        unit_distance=_pad(problem.unit_distance, extra, 0, np.inf),
    )
    if safe is not None:
        own = safe.sets
        sets = AchievableSets(
            _pad(own.axis, extra, 0), _pad(own.lower, extra, 0), _pad(own.upper, extra, 0), own.max_speed
        )
        safe = unchecked(
            SafeSets,
            sets=sets,
            normals=_pad(safe.normals, extra, 0),
            offsets=_pad(safe.offsets, extra, 0),
            fixed=safe.fixed,
            radius=safe.radius,
            slack=_pad(safe.slack, extra, 0),
            worst=_pad(safe.worst, extra, 0, np.inf),
            overflow=_pad(safe.overflow, extra, 0, False),
        )
    return problem, safe


def canonical(problem: AllocationProblem) -> AllocationProblem:
    """``problem`` with what the dual's kernel does not read (obstacles, avoidance and safety
    parameters) replaced by fixed values."""
    return dataclasses.replace(
        problem, obstacles=CircularObstacles.none(), avoidance=AvoidanceParams(), safety=SafetyParams()
    )
