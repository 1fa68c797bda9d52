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

from platoon_opt.controller import drive
from platoon_opt.errors import ConfigurationError, OptionError
from platoon_opt.limits import LOOSE, AchievableSets
from platoon_opt.problem import Allocation, AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.safety import MODES, SafetyParams, turning_radius
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
    """``allocation`` with each velocity whose executed step would break its unit's barrier rows
    (``safe_handout``) projected onto its unit's safe set (``SafeSets``): the rate-aware sector of
    the gear the unit controller will choose for it, cut by the barrier rows.
    ``info["filtered"]`` says how far (m/s, all units) the filter moved the velocities,
    ``info["held_units"]`` how many it moved and ``info["slack_units"]`` how many units needed a
    slack. Unchanged if ``params`` is off."""
    if not params.enabled:
        return allocation
    start = time.perf_counter()
    velocity = allocation.velocities
    state = problem.state
    gear = choose_gear(velocity, state.theta, state.gear, problem.limits)
    safe = problem.safe_sets(params, gear=gear)
    safe_velocity, held = safe_handout(problem, params, safe, velocity, safe.project(velocity))
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
            "held_units": held,
            **slack_info(safe),
        },
    )


def keeps_barriers(problem: AllocationProblem, safe: SafeSets, velocity: np.ndarray) -> np.ndarray:
    """Whether the step each unit executes toward ``velocity`` (n, 2), m/s (its unit controller,
    then its exact arc: ``controller.drive``) keeps the unit's barrier rows in ``safe`` (n,).

    The rows bound the executed displacement D through ``D / dt``: a robust row implies its plain
    half-plane, which keeps the barrier over the step whatever the steering does
    (docs/safety.md, section 5). A unit that stands keeps them all."""
    state = problem.state
    _, after = drive(state, velocity, problem.limits, problem.dt)
    executed = (after.positions - state.positions) / problem.dt
    rows = np.einsum("ikj,ij->ik", safe.barrier_normals, executed) - safe.barrier_offsets
    return np.all(rows <= 0.0, axis=1)


def clear_of_obstacles(problem: AllocationProblem, params: SafetyParams) -> np.ndarray:
    """Whether each unit is beyond the reach of every obstacle's rows (n,): farther from its
    inflated surface than ``params.reach`` and, with turning room, one turning radius more.
    Memory O(n) per obstacle."""
    reach = params.reach(problem.limits, problem.dt)
    if params.turning_room:
        reach += turning_radius(problem.limits)
    positions, obstacles = problem.state.positions, problem.obstacles
    clear = np.ones(problem.n, dtype=bool)
    for centre, radius in zip(obstacles.centers, obstacles.radii):
        distance = np.hypot(positions[:, 0] - centre[0], positions[:, 1] - centre[1])
        clear &= distance >= radius + params.obstacle_margin + reach
    return clear


def safe_handout(
    problem: AllocationProblem,
    params: SafetyParams,
    safe: SafeSets,
    wanted: np.ndarray,
    safe_velocity: np.ndarray,
) -> tuple[np.ndarray, int]:
    """What a unit with barriers is handed: its ``wanted`` velocity (n, 2), m/s (the task-exact
    reading's a, a filtered allocator's answer) where no obstacle's rows reach it
    (``clear_of_obstacles``) and the step it executes toward ``wanted`` keeps its barrier rows
    (``keeps_barriers``); else ``safe_velocity`` (in its safe set). Also how many units got
    ``safe_velocity``. Units away from obstacles drive as without barriers, at full speed while
    they turn, where the nearest velocity of the one-step sector would slow them down; near an
    obstacle the turning rows, which hold for velocities in that sector, keep a unit the room to
    turn away (docs/safety.md, sections 5 and 6)."""
    kept = clear_of_obstacles(problem, params) & keeps_barriers(problem, safe, wanted)
    return np.where(kept[:, None], wanted, safe_velocity), int(np.count_nonzero(~kept))


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
