"""The soak's random allocation problems (also drawn by the property tests): a ``ProblemSpec`` holds
the random numbers of one problem and ``build`` poses it.

Contract: problem ``i`` of seed ``s`` is the same in every run and process: its numbers come from
chunk ``i // CHUNK``, drawn with ``numpy.random.default_rng([s, chunk])`` (vectorised over the
chunk), so ``spec_at(s, i)`` rebuilds it alone. A fraction ``DEGENERATE_RATE`` of the problems is
of one of ``DEGENERATE_KINDS``. The family is described in docs/benchmarks.md.
"""

from __future__ import annotations

import hashlib
import inspect
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from platoon_opt import AllocationProblem, CircularObstacles, MeanVarianceTask, PlatoonState, VehicleLimits

LIMITS = VehicleLimits()
TASK = MeanVarianceTask()
MIN_UNITS, MAX_UNITS = 2, 12
# Units are scattered over [-SPREAD, SPREAD]^2 (m); obstacle centres over a margin of 1 m more.
SPREAD = 2.0
MAX_OBSTACLES = 3
RADIUS_RANGE = (0.1, 1.5)
# f_d - f: up to OFFSET_RANGE per component (m, m^2, m, m^2) times 10^e, e uniform in
# [-OFFSET_DECADES, 0] (so that u = K (f_d - f) + f_d' spans tracking errors of a closed loop,
# a few cm, to a far target); f_d' up to RATE_RANGE per component.
OFFSET_RANGE = np.array([1.5, 0.5, 1.5, 0.5])
OFFSET_DECADES = 3.0
RATE_RANGE = 1.0
# K = BASE_GAINS * 10^g with g in [-1, 1]; the "huge_gains" kind uses HUGE_GAIN.
BASE_GAINS = np.array([50.0, 10.0, 50.0, 10.0])
HUGE_GAIN = 1e6
DT = 0.01
KINDS = (
    "random",
    "coincident",  # every unit at one point: both variance rows of J vanish
    "two_coincident",  # units 0 and 1 at one point
    "line",  # every unit on one vertical (or horizontal) line: one variance row vanishes
    "zero_nominal",  # units 4 m apart, f_d = f, f_d' = 0, no obstacle: q'_d = 0
    "inside_obstacle",  # an obstacle centred on unit 0
    "huge_gains",  # K = 1e6 I
    "steering_at_limit",  # every |alpha| at its limit
)
DEGENERATE_KINDS = KINDS[1:]
# Fraction of soak problems drawn (uniformly) from DEGENERATE_KINDS.
DEGENERATE_RATE = 0.2
# Problems per chunk of random numbers.
CHUNK = 1000
# A unit this far outside the set its allocator promises (m/s) is a limit violation (the soak's
# count and the property tests' bound).
LIMIT_TOLERANCE = 1e-7


@dataclass(frozen=True)
class ProblemSpec:
    """The random numbers of one allocation problem; ``build`` applies the kind and poses it.

    Attributes:
        kind: one of ``KINDS``.
        x, y, theta, alpha, gear: the units (n,): m, rad, rad (|alpha| <= max steering), +-1.
        offset: f_d - f (4,), before the kind's changes; a desired variance is floored at 0.
        rate: f_d' (4,).
        gain_exponent: K = BASE_GAINS * 10^gain_exponent.
        centers, radii: obstacles (k, 2), (k,), m.
    """

    kind: str
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    gear: np.ndarray
    offset: np.ndarray
    rate: np.ndarray
    gain_exponent: float
    centers: np.ndarray
    radii: np.ndarray

    @property
    def n(self) -> int:
        return int(np.asarray(self.x).shape[0])

    def build(self) -> AllocationProblem:
        """The allocation problem (``AllocationProblem.build``, dt = ``DT``, default avoidance)."""
        x, y = np.array(self.x, dtype=float), np.array(self.y, dtype=float)
        alpha = np.array(self.alpha, dtype=float)
        offset, rate = np.array(self.offset, dtype=float), np.array(self.rate, dtype=float)
        centers = np.array(self.centers, dtype=float).reshape(-1, 2)
        radii = np.array(self.radii, dtype=float).reshape(-1)
        gains = BASE_GAINS * 10.0**self.gain_exponent
        n = x.shape[0]
        if self.kind == "coincident":
            x[:], y[:] = x[0], y[0]
        elif self.kind == "two_coincident":
            x[1], y[1] = x[0], y[0]
        elif self.kind == "line":
            if self.theta[0] >= 0:
                x[:] = x[0]
            else:
                y[:] = y[0]
        elif self.kind == "zero_nominal":
            x = x[0] + 4.0 * np.arange(n)
            offset, rate = np.zeros(4), np.zeros(4)
            centers, radii = np.zeros((0, 2)), np.zeros(0)
        elif self.kind == "inside_obstacle":
            if radii.size == 0:
                centers, radii = np.zeros((1, 2)), np.array([RADIUS_RANGE[1]])
            centers[0] = (x[0], y[0])
        elif self.kind == "huge_gains":
            gains = np.full(4, HUGE_GAIN)
        elif self.kind == "steering_at_limit":
            alpha = np.where(alpha < 0, -1.0, 1.0) * LIMITS.max_steering
        elif self.kind != "random":
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        state = PlatoonState(x, y, np.array(self.theta, dtype=float), alpha, np.array(self.gear, dtype=float))
        value = TASK.value(state.positions)
        desired = value + offset
        desired[[1, 3]] = np.maximum(desired[[1, 3]], 0.0)
        return AllocationProblem.build(
            state,
            TASK,
            desired,
            rate,
            gains,
            LIMITS,
            DT,
            obstacles=CircularObstacles(centers, radii),
        )


def draw_specs(
    rng: np.random.Generator, count: int, degenerate_rate: float = DEGENERATE_RATE
) -> list[ProblemSpec]:
    """``count`` problem specs, every random number drawn in one vectorised call per field."""
    size = (count, MAX_UNITS)
    n = rng.integers(MIN_UNITS, MAX_UNITS + 1, count)
    x, y = rng.uniform(-SPREAD, SPREAD, size), rng.uniform(-SPREAD, SPREAD, size)
    theta = rng.uniform(-np.pi, np.pi, size)
    alpha = rng.uniform(-LIMITS.max_steering, LIMITS.max_steering, size)
    gear = np.where(rng.random(size) < 0.5, -1.0, 1.0)
    offset = rng.uniform(-1.0, 1.0, (count, 4)) * OFFSET_RANGE
    offset *= 10.0 ** rng.uniform(-OFFSET_DECADES, 0.0, (count, 1))
    rate = rng.uniform(-RATE_RANGE, RATE_RANGE, (count, 4))
    gain_exponent = rng.uniform(-1.0, 1.0, count)
    obstacles = rng.integers(0, MAX_OBSTACLES + 1, count)
    centers = rng.uniform(-SPREAD - 1.0, SPREAD + 1.0, (count, MAX_OBSTACLES, 2))
    radii = rng.uniform(*RADIUS_RANGE, (count, MAX_OBSTACLES))
    degenerate = rng.random(count) < degenerate_rate
    kind = rng.integers(0, len(DEGENERATE_KINDS), count)
    return [
        ProblemSpec(
            kind=DEGENERATE_KINDS[kind[i]] if degenerate[i] else "random",
            x=x[i, : n[i]],
            y=y[i, : n[i]],
            theta=theta[i, : n[i]],
            alpha=alpha[i, : n[i]],
            gear=gear[i, : n[i]],
            offset=offset[i],
            rate=rate[i],
            gain_exponent=float(gain_exponent[i]),
            centers=centers[i, : obstacles[i]],
            radii=radii[i, : obstacles[i]],
        )
        for i in range(count)
    ]


def chunk_specs(seed: int, chunk: int, degenerate_rate: float = DEGENERATE_RATE) -> list[ProblemSpec]:
    """The ``CHUNK`` specs of chunk ``chunk`` of seed ``seed``."""
    return draw_specs(np.random.default_rng([seed, chunk]), CHUNK, degenerate_rate)


def spec_at(seed: int, index: int, degenerate_rate: float = DEGENERATE_RATE) -> ProblemSpec:
    """Problem ``index`` of seed ``seed``."""
    return chunk_specs(seed, index // CHUNK, degenerate_rate)[index % CHUNK]


def specs(seed: int, count: int, degenerate_rate: float = DEGENERATE_RATE) -> Iterator[ProblemSpec]:
    """Problems 0 .. count - 1 of seed ``seed`` (an iterator of specs)."""
    for chunk in range(math.ceil(count / CHUNK)):
        yield from chunk_specs(seed, chunk, degenerate_rate)[: count - chunk * CHUNK]


def family_version() -> str:
    """Hash of this module's source and of its constants as they are now (a test may change
    ``CHUNK``): what a stored soak chunk must match to be reused."""
    module = sys.modules[__name__]
    constants = (
        CHUNK,
        DEGENERATE_RATE,
        LIMIT_TOLERANCE,
        KINDS,
        LIMITS,
        TASK,
        OFFSET_RANGE.tolist(),
        BASE_GAINS.tolist(),
    )
    text = inspect.getsource(module) + repr(constants)
    return hashlib.sha256(text.encode()).hexdigest()[:20]
