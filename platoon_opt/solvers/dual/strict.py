"""Strict priority for the dual allocator (docs/dual.md, section 7): the best achievable task
velocity first, then the least deviation that keeps it. On the host: Wolfe's algorithm in numpy,
the penalized second stage by the compiled Newton method (``newton.newton``).

``solve_strict`` takes the achievable-first program (``reduction.Reduced`` as numpy arrays, units
under the precedence rule pinned: masked out of the core) and returns the answer as a
``newton.Solution`` (velocities (n,) x 2, m/s; only the core units' count) with what the
allocator reports of both stages (``StrictSolution``). Stage 1 is Wolfe's minimum-norm-point
algorithm (``platoon_opt.solvers.dual.wolfe``) over the achievable task velocities; stage 2 is
the dual Newton method with a penalty raised until J v lies within the band of
``platoon_opt.solvers.programs.STRICT_BAND`` around the stage-1 task velocity.

The answer is a point of the band, not its minimum: on the benchmark's problems (n = 64),
Clarabel's minimum over the band lies up to 0.2 % below the dual's point of it, with both
stage-1 task velocities within 1.2e-7 of each other (measured).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np

from platoon_opt.arrays import host
from platoon_opt.solvers.dual.coupling import task_basis
from platoon_opt.solvers.dual.newton import STATUSES, Solution, newton
from platoon_opt.solvers.dual.reduction import Reduced
from platoon_opt.solvers.dual.sets import TINY
from platoon_opt.solvers.dual.wolfe import min_norm_point
from platoon_opt.solvers.programs import STRICT_BAND

# Wolfe's gap tolerance (relative to the atoms' squared size; the stage-1 task velocity is then
# within sqrt(2e-16) of that size, below the band), its cycles at most, the penalty rounds at
# most and the largest factor of one round.
STAGE1_TOLERANCE = 1e-16
STAGE1_ITERATIONS = 500
PENALTY_ROUNDS = 40
PENALTY_STEP = 1e1

_newton = host(newton)
_task_basis = host(task_basis, static=("rcond",))


class StrictSolution(NamedTuple):
    """Result of ``solve_strict``.

    Attributes:
        solution: the answer (the core units' entries); its iterations and evaluations count the
            Newton steps and passes over the units of every penalty round and Wolfe's oracle
            calls.
        basis: E (m, m), the regular directions of J J^T (the others' columns 0):
            ``basis @ solution.lam`` are the multipliers in task coordinates.
        stage1_task_velocity: t* (m,), in the free units' task coordinates (u less the pinned
            units' share).
        stage1_gap: Wolfe's gap at t* (bounds ||t* - exact||^2 / 2).
        stage1_iterations: Wolfe's major cycles.
        band: the allowed ``max |E^T (J v - t*)|``.
        band_residual: the one met by the answer.
        penalty: the last penalty rho (the next step starts from it).
        stage2_bound: for Wolfe's stage-1 point, the certified bound on its deviation's excess
            over the exact second stage, relative to the deviation; None for a penalized iterate.
        status: "optimal", "stage1" (in the band, but Wolfe stopped at its cycle cap), "stage2"
            (Wolfe's point, its bound above ``STRICT_BAND``), or what stopped the last round's
            Newton method ("max_iterations", "singular", "stalled").
    """

    solution: Solution
    status: str
    basis: np.ndarray
    stage1_task_velocity: np.ndarray
    stage1_gap: float
    stage1_iterations: int
    band: float
    band_residual: float
    penalty: float
    stage2_bound: float | None = None

    @property
    def accuracy(self) -> float:
        """The answer's certified accuracy, relative as the band: ``stage2_bound``, or the band
        residual in units of ``STRICT_BAND``."""
        if self.stage2_bound is not None:
            return self.stage2_bound
        return self.band_residual * STRICT_BAND / self.band

    def info(self) -> dict[str, Any]:
        """The entries of ``Allocation.info`` that strict priority adds."""
        info = {
            "stage1_task_velocity": self.stage1_task_velocity,
            "stage1_gap": self.stage1_gap,
            "stage1_iterations": self.stage1_iterations,
            "band": self.band,
            "band_residual": self.band_residual,
            "penalty": self.penalty,
        }
        if self.stage2_bound is not None:
            info["stage2_bound"] = self.stage2_bound
        return info


def solve_strict(
    reduced: Reduced,
    warm: np.ndarray | None,
    rcond: float,
    *,
    rho: float,
    previous_penalty: float,
    tolerance: float,
    max_iterations: int,
) -> StrictSolution:
    """Both stages of strict priority on the core units of ``reduced`` (docs/dual.md, section 7).

    Args:
        reduced: the achievable-first program, units under the precedence rule pinned.
        warm: the last step's multipliers in task coordinates (m,), or None.
        rcond: the degenerate-direction threshold of J J^T (``TaskJacobian.rcond``).
        rho: the first penalty of the second stage, > 0.
        previous_penalty: the last step's last penalty, 0 for none: the rounds start from it,
            lowered by ``PENALTY_STEP`` (the band needs less when the task is in reach).
        tolerance, max_iterations: of each round's ``newton.newton``.

    The answer is the first penalized iterate within the band. When no round reaches it (the
    task out of reach, t* at a corner of J(C): the multipliers grow without bound and Newton
    stalls on a dual that is flat between kinks), it is Wolfe's stage-1 point v1 (``J v1 = t*``
    to rounding; the multipliers stay the last round's) if its deviation is certified: each
    converged penalized round's optimum is at most the exact second stage's (any v with
    J v = t* costs no penalty), so ``deviation(v1) - (primal - gap)`` of the best round bounds
    v1's excess (status "optimal" when it is within ``STRICT_BAND`` of the deviation, the
    relative accuracy the band itself allows; else "stage2", with the bound as stage2_bound).
    """
    program = reduced.program
    sets, rows, u, core = program.sets, program.rows, program.u, program.core > 0

    def apply(vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
        """J v (m,) of the core units (the others' columns of J are 0)."""
        return np.einsum("kij,ij->k", rows, np.stack((vx, vy), axis=1))

    def oracle(x: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        pulled = np.einsum("k,kij->ij", -x, rows)
        vx, vy = sets.support(pulled[:, 0], pulled[:, 1])
        return apply(vx, vy) - u, (vx, vy)

    inside = sets.project(program.dx, program.dy)
    nearest = min_norm_point(
        oracle,
        (apply(inside.vx, inside.vy) - u, (inside.vx, inside.vy)),
        tolerance=STAGE1_TOLERANCE,
        max_iterations=STAGE1_ITERATIONS,
    )
    target = u + nearest.x
    reachable = float(nearest.x @ nearest.x) == 0.0
    vectors, regular = _task_basis(rows, rcond=rcond)
    basis = vectors * regular[None, :]
    stage2 = replace(program, rows=np.einsum("kr,kij->rij", basis, rows), u=basis.T @ target)
    band = STRICT_BAND * (1.0 + float(np.max(np.abs(stage2.u), initial=0.0)))

    def off_band(vx: np.ndarray, vy: np.ndarray) -> float:
        """max |E^T (J v - t*)|, against the band."""
        return float(
            np.max(np.abs(np.einsum("rij,ij->r", stage2.rows, np.stack((vx, vy), axis=1)) - stage2.u))
        )

    cold = np.zeros(basis.shape[1])
    lam = cold if warm is None else basis.T @ warm
    # From the last step's penalty, lowered: the band needs less when the task is in reach.
    first = rho
    rho = max(first, previous_penalty / PENALTY_STEP)
    restart = warm is not None or rho > first
    iterations, evaluations, lower = 0, nearest.iterations + 1, -math.inf
    for _ in range(PENALTY_ROUNDS):
        solution = _newton(replace(stage2, rho=rho), lam, tolerance, max_iterations, band)
        status = STATUSES[int(solution.status)]
        iterations, evaluations = (
            iterations + int(solution.iterations),
            evaluations + int(solution.evaluations),
        )
        residual = off_band(solution.vx, solution.vy)
        if status != "optimal" and restart:
            # A warm start from a different problem can leave Newton stalled: once, cold.
            rho, lam, restart = first, cold, False
            continue
        if residual <= band or status != "optimal":
            break
        restart = False
        lower = max(lower, float(solution.primal - solution.gap))
        # Inside J(C) (u in reach) the multipliers converge and the residual |lambda| / (2 rho)
        # falls like 1 / rho; on its boundary it can fall like 1 / sqrt(rho) while they grow,
        # and a large step leaves Newton far from the next solution.
        if reachable:
            rho *= max(2.0 * residual / band, 10.0)
        else:
            rho *= min(max(2.0 * (residual / band) ** 2, 10.0), PENALTY_STEP)
        lam = solution.lam
    stage2_bound = None
    if residual <= band:
        status = "stage1" if nearest.status == "max_iterations" else "optimal"
    else:
        vx = sum(weight * payload[0] for weight, payload in zip(nearest.weights, nearest.payloads))
        vy = sum(weight * payload[1] for weight, payload in zip(nearest.weights, nearest.payloads))
        ex, ey = (vx - program.dx) * core, (vy - program.dy) * core
        deviation = float(ex @ ex + ey @ ey)
        stage2_bound = max(deviation - lower, 0.0) / max(deviation, TINY)
        status = "optimal" if stage2_bound <= STRICT_BAND else "stage2"
        residual = off_band(vx, vy)
        solution = solution._replace(vx=vx, vy=vy, primal=deviation)
    solution = solution._replace(iterations=iterations, evaluations=evaluations)
    return StrictSolution(
        solution, status, basis, target, nearest.gap, nearest.iterations, band, residual, rho, stage2_bound
    )
