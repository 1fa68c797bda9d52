"""The safety options every allocator shares, and the safety filter (docs/safety.md).

``SafetyOptions`` declares ``safety``, ``barrier_rate``, ``safety_distance``, ``obstacle_margin``,
``neighbour_cutoff`` and ``turning_room``; each left at None takes the scenario's ``[safety]`` value
(``AllocationProblem.safety``), so that one scenario file can switch barriers on for every
allocator and one option can switch them on for one allocator. The convex programs and the dual
put the barrier rows into each unit's set; the paper's iteration and ``nmpc`` hand their answer
through ``safety_filter``: each velocity projected onto its unit's safe set. The handout
(``safe_handout``: the filter's, and the task-exact reading's) is written once for numpy and JAX,
so that the compiled engine runs it too (with the safe sets built in a ``Capacity``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import numpy as np

from platoon_opt.allocation import Allocation
from platoon_opt.arrays import any_platoon, namespace
from platoon_opt.barrier_constraints import Capacity
from platoon_opt.controller import drive
from platoon_opt.errors import ConfigurationError, OptionError
from platoon_opt.limits import LOOSE, AchievableSets
from platoon_opt.problem import AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.safety import MODES, SafetyParams, turning_radius
from platoon_opt.scenarios import Scenario
from platoon_opt.solvers.options import Choice, Flag, Number, Option
from platoon_opt.vehicle import STANDING_SPEED, choose_gear

# A unit handed at most this share of the speed it wants is blocked (``escape``): its safe set
# keeps nothing of its wanted velocity but a direction within 0.06 degrees of square to it, or a
# speed that its distance to a barrier's boundary shrinks geometrically.
BLOCKED_SHARE = 1e-3

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

    def compiled_safety(self, scenario: Scenario) -> SafetyParams | None:
        """The safety parameters a compiled kernel keeps for ``scenario`` (off, or on in the
        default ``Capacity``), or None where the host must run the allocator: barriers on with
        options that fail their check (the host reports it)."""
        params = self.safety_over(scenario.safety)
        if not params.enabled:
            return params
        try:
            params.check(scenario.limits, scenario.dt)
        except ConfigurationError:
            return None
        return params

    def safety_name(self) -> list[str]:
        """The name parts of the safety options: "barrier" when switched on by the option, and
        "no-turning-room" when that is switched off."""
        return ["barrier"] * (self.safety == "barrier") + ["no-turning-room"] * (self.turning_room is False)


def safety_filter(problem: AllocationProblem, allocation: Allocation, params: SafetyParams) -> Allocation:
    """``allocation`` with each velocity whose executed step would break its unit's barrier rows
    projected onto its unit's safe set (``filtered``).
    ``info["filtered"]`` says how far (m/s, all units) the filter moved the velocities,
    ``info["held_units"]`` how many it moved, ``info["escaping_units"]`` how many of those were
    blocked units given a way out (``escape``) and ``info["slack_units"]`` how many units needed a
    slack. Unchanged if ``params`` is off."""
    if not params.enabled:
        return allocation
    start = time.perf_counter()
    velocity = allocation.velocities
    handout, safe = filtered(problem, params, velocity)
    return Allocation.of(
        problem,
        handout.velocities,
        allocator=allocation.allocator,
        status=allocation.status,
        iterations=allocation.iterations,
        solve_time=allocation.solve_time + time.perf_counter() - start,
        fell_back=allocation.fell_back,
        solved=allocation.solved,
        program_changed=allocation.program_changed,
        **{
            **allocation.info,
            "filtered": float(np.linalg.norm(handout.velocities - velocity)),
            "held_units": handout.held,
            "escaping_units": handout.escaping,
            **slack_info(safe),
        },
    )


def filtered(
    problem: AllocationProblem, params: SafetyParams, velocity: Any, *, capacity: Capacity | None = None
) -> tuple[Handout, SafeSets]:
    """The safety filter's handout of ``velocity`` (n, 2), m/s (``safe_handout``, the safe
    velocity being its projection onto the safe set), and the safe sets: the rate-aware sector of
    the gear the unit controller will choose for it, cut by the barrier rows. Numpy, or traced
    with a ``capacity`` (``SafeSets.build``)."""
    state = problem.state
    gear = choose_gear(velocity, state.theta, state.gear, problem.limits)
    safe = problem.safe_sets(params, gear=gear, capacity=capacity)
    handout = safe_handout(problem, params, safe, velocity, safe.project(velocity), capacity=capacity)
    return handout, safe


def keeps_barriers(problem: AllocationProblem, safe: SafeSets, velocity: Any) -> Any:
    """Whether the step each unit executes toward ``velocity`` (n, 2), m/s (its unit controller,
    then its exact arc: ``controller.drive``) keeps the unit's barrier rows in ``safe`` (n,).

    The rows bound the executed displacement D through ``D / dt``: a robust row implies its plain
    half-plane, which keeps the barrier over the step whatever the steering does
    (docs/safety.md, section 5). A unit that stands keeps them all."""
    xp = namespace(velocity, safe.normals)
    state = problem.state
    _, after = drive(state, velocity, problem.limits, problem.dt)
    executed = (after.positions - state.positions) / problem.dt
    rows = xp.einsum("ikj,ij->ik", safe.barrier_normals, executed) - safe.barrier_offsets
    return xp.all(rows <= 0.0, axis=1)


def clear_of_obstacles(problem: AllocationProblem, params: SafetyParams) -> Any:
    """Whether each unit is beyond the reach of every obstacle's rows (n,): farther from its
    inflated surface than ``params.reach`` and, with turning room, one turning radius more
    (``CircularObstacles.nearest``: memory O(n) beyond a few thousand unit-obstacle pairs)."""
    reach = params.reach(problem.limits, problem.dt)
    if params.turning_room:
        reach += turning_radius(problem.limits)
    distance, _ = problem.obstacles.nearest(problem.state.positions)
    return distance >= params.obstacle_margin + reach


class Handout(NamedTuple):
    """What ``safe_handout`` hands the units (numpy on the host; traced, JAX scalars).

    Attributes:
        velocities: (n, 2) m/s.
        held: units handed their safe velocity instead of the wanted one.
        escaping: blocked units handed a velocity that slides along their rows (``escape``).
        overflow: whether the other gear's safe sets of a blocked unit overflowed the capacity
            (traced only; ``SafeSets.overflow``).
    """

    velocities: Any
    held: Any
    escaping: Any
    overflow: Any = False


def safe_handout(
    problem: AllocationProblem,
    params: SafetyParams,
    safe: SafeSets,
    wanted: Any,
    safe_velocity: Any,
    *,
    capacity: Capacity | None = None,
) -> Handout:
    """What a unit with barriers is handed: its ``wanted`` velocity (n, 2), m/s (the task-exact
    reading's a, a filtered allocator's answer) where no obstacle's rows reach it
    (``clear_of_obstacles``) and the step it executes toward ``wanted`` keeps its barrier rows
    (``keeps_barriers``); else ``safe_velocity`` (in its safe set), or, for a blocked unit, its
    ``escape`` velocity. Units away from obstacles drive as without barriers, at full speed while
    they turn, where the nearest velocity of the one-step sector would slow them down; near an
    obstacle the turning rows, which hold for velocities in that sector, keep a unit the room to
    turn away (docs/safety.md, sections 5 and 6). Numpy, or traced with the ``capacity`` that
    built ``safe`` (the other gear's sets of ``escape`` are built in it too)."""
    xp = namespace(wanted, safe.normals)
    kept = clear_of_obstacles(problem, params) & keeps_barriers(problem, safe, wanted)
    handed = xp.where(kept[:, None], wanted, safe_velocity)
    handed, escaping, overflow = escape(problem, params, safe, wanted, handed, capacity=capacity)
    held = int(np.count_nonzero(~kept)) if xp is np else xp.sum(~kept)
    return Handout(handed, held, escaping, overflow)


def escape(
    problem: AllocationProblem,
    params: SafetyParams,
    safe: SafeSets,
    wanted: Any,
    handed: Any,
    *,
    capacity: Capacity | None = None,
) -> tuple[Any, Any, Any]:
    """``handed`` (n, 2), m/s, with every blocked unit given a way out where it has one, how
    many were, and whether the other gear's sets of a blocked unit overflowed ``capacity``.

    A unit is blocked when it wants to move but is handed almost nothing of it: a speed at most
    ``BLOCKED_SHARE`` of the wanted one. Its wanted velocity points into an obstacle or a
    neighbour so squarely that the nearest velocity of its safe set is zero, or shrinks with its
    distance to the boundary step after step, though the set may hold others: nearest is no
    answer, the unit would stand (or crawl) for good, heading in. It aims instead at the velocity
    its barrier rows allow nearest its wanted one whatever its steering (``SafeSets.sliding``:
    the wanted velocity without the part that pushes into the rows), and is handed the velocity
    of either gear's safe set (``safe``'s, or the other gear's built alike: backing out) that
    goes furthest along that aim (``SafeSets.support``), at most at the wanted speed, when the
    step it executes keeps that set's rows (``keeps_barriers``). A blocked unit without one
    stands (zero velocity), so that it turns its wheel toward its standing target
    (``controller.standing_targets``) instead of holding it while it crawls. The guarantee is
    untouched: every velocity is in a safe set. On numpy only the blocked units' sets are
    searched; traced, every unit's (the same numbers per unit)."""
    xp = namespace(wanted, handed, safe.normals)
    wanted_speed = xp.hypot(wanted[:, 0], wanted[:, 1])
    least = xp.maximum(STANDING_SPEED, BLOCKED_SHARE * wanted_speed)
    blocked = (xp.hypot(handed[:, 0], handed[:, 1]) <= least) & (wanted_speed > STANDING_SPEED)
    if xp is np:
        if not np.any(blocked):
            return handed, 0, False
        result, escaping, _ = _ways_out(
            problem, params, safe, wanted, handed, blocked, wanted_speed, least, capacity
        )
        return result, int(escaping), False
    # Traced, the search runs only on steps where some unit of some platoon is blocked; the
    # others keep ``handed`` (``arrays.any_platoon``).
    return jax.lax.cond(
        any_platoon(xp.any(blocked)),
        lambda: _ways_out(problem, params, safe, wanted, handed, blocked, wanted_speed, least, capacity),
        lambda: (handed, xp.sum(blocked), xp.asarray(False)),
    )


def _ways_out(
    problem: AllocationProblem,
    params: SafetyParams,
    safe: SafeSets,
    wanted: Any,
    handed: Any,
    blocked: Any,
    wanted_speed: Any,
    least: Any,
    capacity: Capacity | None,
) -> tuple[Any, Any, Any]:
    """``escape``'s search for the ``blocked`` units (n,) bool: ``wanted_speed`` (n,) is the
    speed of ``wanted`` and ``least`` (n,) the speed a way out must exceed, m/s."""
    xp = namespace(wanted, handed, safe.normals)
    units = np.flatnonzero(blocked) if xp is np else slice(None)
    wanted_speed, least = wanted_speed[units], least[units]
    gear = xp.where(xp.cos(safe.sets.axis - problem.state.theta) >= 0, 1.0, -1.0)
    other = problem.safe_sets(params, gear=-gear, capacity=capacity)
    mine_wanted = wanted[units]
    # Blocked units stand unless a way out is found; traced, the others keep ``handed``.
    result, best = xp.zeros_like(mine_wanted), xp.zeros(mine_wanted.shape[0])
    for sets in (safe, other):
        mine = sets.take(units)
        aim = mine.sliding(mine_wanted)
        # The set's velocity furthest along the aim, at most at the wanted speed (the set is
        # convex and holds 0, so shortening stays inside). The nearest velocity to the aim would
        # crawl: the aim itself is short when the rows leave little of the wanted velocity.
        corner = mine.support(aim)
        length = xp.hypot(corner[:, 0], corner[:, 1])
        way_out = corner * xp.minimum(1.0, wanted_speed / xp.maximum(length, 1e-300))[:, None]
        speed = xp.hypot(way_out[:, 0], way_out[:, 1])
        trial = _put(handed, units, way_out, blocked)
        # How far along the aim it goes (m^2/s^2; 0 for a unit that stands).
        along = xp.einsum("ij,ij->i", way_out, aim)
        better = (speed > least) & (along > best) & keeps_barriers(problem, sets, trial)[units]
        if xp is not np:
            better = better & blocked
        result, best = xp.where(better[:, None], way_out, result), xp.where(better, along, best)
    return _put(handed, units, result, blocked), xp.sum(best > 0), xp.any(blocked & other.overflow)


def _put(velocities: Any, units: Any, values: Any, chosen: Any) -> Any:
    """``velocities`` (n, 2) with ``values`` for the ``units`` chosen: on numpy the indices
    ``units`` (``values`` theirs alone), traced the mask ``chosen`` (``values`` of every unit)."""
    if namespace(velocities, values) is not np:
        return namespace(values).where(chosen[:, None], values, velocities)
    result = velocities.copy()
    result[units] = values
    return result


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
