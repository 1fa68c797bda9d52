"""The safety options every allocator shares, and the safety filter (docs/safety.md).

``SafetyOptions`` declares ``safety``, ``barrier_rate``, ``safety_distance``, ``obstacle_margin``,
``neighbour_cutoff`` and ``turning_room``; each left at None takes the scenario's ``[safety]`` value
(``AllocationProblem.safety``), so that one scenario file can switch barriers on for every
allocator and one option can switch them on for one allocator. The convex programs and the dual
put the barrier rows into each unit's set; the paper's iteration and ``nmpc`` hand their answer
through ``safety_filter``: each velocity projected onto its unit's safe set.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from platoon_opt.errors import ConfigurationError, OptionError
from platoon_opt.limits import LOOSE, AchievableSets
from platoon_opt.problem import Allocation, AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.safety import MODES, SafetyParams
from platoon_opt.solvers.options import Choice, Flag, Number, Option
from platoon_opt.vehicle import choose_gear

SAFETY = Option(
    "safety", None, "barrier constraints, none or barrier; None: the scenario's [safety] mode", Choice(MODES)
)
BARRIER_RATE = Option(
    "barrier_rate",
    None,
    "gamma: share of the barrier h one step may use up; None: the scenario's (0.5)",
    Number(above=0, at_most=1),
)
SAFETY_DISTANCE = Option(
    "safety_distance",
    None,
    "least distance between unit tips (m); None: the scenario's (0.3)",
    Number(above=0),
)
OBSTACLE_MARGIN = Option(
    "obstacle_margin",
    None,
    "added to every obstacle radius (m); None: the scenario's (0.05)",
    Number(at_least=0),
)
NEIGHBOUR_CUTOFF = Option(
    "neighbour_cutoff",
    None,
    "pairs of units closer than this are constrained (m); None: the scenario's (d_safe + 4 v_max dt)",
    Number(above=0),
)

TURNING_ROOM = Option(
    "turning_room",
    None,
    "keep units heading at an obstacle or a neighbour far enough to turn away; None: the scenario's (True)",
    Flag(),
)


@dataclass(frozen=True)
class SafetyOptions:
    """The safety options, as dataclass fields an allocator inherits (see the module docstring)."""

    safety: str | None = SAFETY.field()
    barrier_rate: float | None = BARRIER_RATE.field()
    safety_distance: float | None = SAFETY_DISTANCE.field()
    obstacle_margin: float | None = OBSTACLE_MARGIN.field()
    neighbour_cutoff: float | None = NEIGHBOUR_CUTOFF.field()
    turning_room: bool | None = TURNING_ROOM.field()

    def safety_for(self, problem: AllocationProblem) -> SafetyParams:
        """The scenario's safety parameters with this allocator's options over them.

        Raises:
            OptionError: the cutoff leaves pairs unguarded, or the vehicle's gear rule cannot keep
                an allocated gear (``SafetyParams.check``).
        """
        params = self.safety_over(problem.safety)
        if params.enabled:
            try:
                params.check(problem.limits, problem.dt, where="option safety")
            except ConfigurationError as error:
                raise OptionError(str(error)) from None
        return params

    def safety_over(self, scenario: SafetyParams) -> SafetyParams:
        """The scenario's safety parameters ``scenario`` with this allocator's options over them,
        unchecked."""
        given: dict[str, Any] = {
            "mode": self.safety,
            "barrier_rate": self.barrier_rate,
            "safety_distance": self.safety_distance,
            "obstacle_margin": self.obstacle_margin,
            "neighbour_cutoff": self.neighbour_cutoff,
            "turning_room": self.turning_room,
        }
        return dataclasses.replace(scenario, **{k: v for k, v in given.items() if v is not None})

    def safety_name(self) -> list[str]:
        """The name parts of the safety options: "barrier" when switched on by the option, and
        "no-turning-room" when that is switched off."""
        return ["barrier"] * (self.safety == "barrier") + ["no-turning-room"] * (self.turning_room is False)


def safety_filter(problem: AllocationProblem, allocation: Allocation, params: SafetyParams) -> Allocation:
    """``allocation`` with each velocity projected onto its unit's safe set (``SafeSets``): the
    rate-aware sector of the gear the unit controller will choose for it, cut by the barrier rows.
    ``info["filtered"]`` says how far (m/s, all units) the filter moved the velocities and
    ``info["slack_units"]`` how many units needed a slack. Unchanged if ``params`` is off."""
    if not params.enabled:
        return allocation
    start = time.perf_counter()
    velocity = allocation.velocities
    state = problem.state
    gear = choose_gear(velocity, state.theta, state.gear, problem.limits)
    safe = problem.safe_sets(params, gear=gear)
    safe_velocity = safe.project(velocity)
    return Allocation.of(
        problem,
        safe_velocity,
        allocator=allocation.allocator,
        status=allocation.status,
        iterations=allocation.iterations,
        solve_time=allocation.solve_time + time.perf_counter() - start,
        fell_back=allocation.fell_back,
        solved=allocation.solved,
        program_changed=allocation.program_changed,
        **{
            **allocation.info,
            "filtered": float(np.linalg.norm(safe_velocity - velocity)),
            **slack_info(safe),
        },
    )


def slack_info(safe: SafeSets) -> dict[str, float | int]:
    """What an allocation with barriers reports: ``slack_units`` (units whose barrier rows were
    relaxed, starting unsafe) and ``slack`` (the largest relaxation, m/s)."""
    return {"slack_units": int(np.count_nonzero(safe.slack)), "slack": float(np.max(safe.slack, initial=0.0))}


def loose_padding(sets: AchievableSets, safe: SafeSets, max_speed: float) -> tuple[np.ndarray, np.ndarray]:
    """The rows (n, k, 2), (n, k) of ``safe`` for a sparse program: a unit's padding rows (zero
    normals) become ``axis . v <= LOOSE max_speed``, never active, as the polygon's
    (``limits.unit_rows``), so that the pattern stays fixed and every row has a strict slack."""
    padded = ~np.any(safe.normals != 0.0, axis=2)
    axis = sets.unit_vectors((sets.lower + sets.upper) / 2)
    normals = np.where(padded[..., None], axis[:, None, :], safe.normals)
    return normals, np.where(padded, LOOSE * max_speed, safe.offsets)
