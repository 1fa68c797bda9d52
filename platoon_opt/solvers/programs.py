"""What the convex allocators and the dual share: the names of the allocation programs and the
options that choose among them (docs/programs.md has the mathematics).

Two readings of "the closest achievable velocity consistent with f(q)":

* ``achievable-first`` (``qp``, ``cone``): ``min ||v - q'_d||^2 + rho ||J v - u||^2`` over
  achievable v, or lexicographically (``priority="strict"``): the best achievable task velocity
  first, then the least deviation that keeps it;
* ``task-exact`` (``qp-projection``, ``cone-projection``): ``min ||a - c||^2 + eps ||a - q'_d||^2``
  subject to ``J a = u`` and c achievable; the units get a.

Each with the speed disk as an inscribed polygon (``polygon``, linear rows) or exact (``cone``).
"""

from __future__ import annotations

import numpy as np

from platoon_opt.allocation import Allocation
from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.options import Choice, Flag, Integer, Number, Option

READINGS = ("achievable-first", "task-exact")
SPEED_MODELS = ("polygon", "cone")
# Half-width of the stage-2 band around the stage-1 task velocity (strict priority), relative to
# 1 + its largest component.
STRICT_BAND = 1e-7

READING = Option(
    "reading",
    "achievable-first",
    "the program: achievable-first (v handed out) or task-exact (a)",
    Choice(READINGS),
)
SPEED = Option(
    "speed", "polygon", "the speed disk as the inscribed polygon or exact (cone)", Choice(SPEED_MODELS)
)
RHO = Option(
    "rho",
    1e3,
    "weight of ||J v - u||^2 in the achievable-first program ((m/s)^2 per squared task velocity)",
    Number(above=0),
)
EPS = Option(
    "eps",
    1e-4,
    "weight of ||a - q'_d||^2 in the task-exact program: picks the nearest of the equally good",
    Number(above=0),
)
PRIORITY = Option(
    "priority",
    "weighted",
    "achievable-first: the rho-weighted program, or strict (best task velocity, then least deviation)",
    Choice(("weighted", "strict")),
)
SIDES = Option("sides", 16, "sides of the polygon inscribed in the speed disk", Integer(at_least=3))
RATE_AWARE = Option(
    "rate_aware",
    False,
    "narrow each steering sector to what the steering reaches within dt (with barriers always so) and "
    "measure deviation from each nominal velocity as the unit drives it within dt",
    Flag(),
)
GEARS = Option(
    "gears",
    "model",
    "each unit's sector: its gear rule's gear (model), the gear whose sector lies nearer its "
    "nominal velocity (either: the gear rule without hysteresis, the sector the paper's iteration "
    "projects onto), or the nearer gear while the platoon catches up and the gear rule's otherwise "
    "(catching-up: while the task's feedback asks its centroid for more than the top speed); the "
    "achievable-first programs hand velocities in the posed gear, so for them the nearer gear has no "
    "hysteresis and the units switch gears far more often",
    Choice(("model", "either", "catching-up")),
)
PRECEDENCE = Option(
    "precedence",
    None,
    "units under the precedence rule: pin (fixed at p_i) or anchor (drawn to p_i); "
    "None: pin for achievable-first, anchor for task-exact",
    Choice(("pin", "anchor")),
)
ANCHOR_WEIGHT = Option("anchor_weight", 1.0, "weight of an anchored unit's ||. - p_i||^2", Number(above=0))


def default_precedence(reading: str) -> str:
    """The precedence rule of a reading when none is given: "pin" (achievable-first), "anchor"
    (task-exact: pinned units leave the exact task to the others, whose velocities then ran to
    1000 m/s in closed loop)."""
    return "pin" if reading == "achievable-first" else "anchor"


def name_parts(
    reading: str, rate_aware: bool, gears: str, precedence: str | None, anchor_weight: float
) -> list[str]:
    """The parts of an allocator's name that say how its sets and exempt units differ from the
    defaults: "rate-aware", "either gear" or "either gear while catching up", and "pin" or
    "anchor=<weight>" when not the reading's own (None)."""
    parts = ["rate-aware"] if rate_aware else []
    if gears != GEARS.default:
        parts.append("either gear" if gears == "either" else "either gear while catching up")
    precedence = precedence or default_precedence(reading)
    if precedence != default_precedence(reading) or anchor_weight != ANCHOR_WEIGHT.default:
        parts.append(f"anchor={anchor_weight:g}" if precedence == "anchor" else "pin")
    return parts


def posed(problem: AllocationProblem, rate_aware: bool, gears: str) -> AllocationProblem:
    """The problem a program solves: with ``gears="either"``, each unit in the gear whose sector
    lies nearer its nominal velocity (``AllocationProblem.in_nearer_gears``), with
    ``gears="catching-up"`` so only while the platoon catches up
    (``AllocationProblem.catching_up``); with ``rate_aware``, each nominal velocity as the unit
    drives it within the step in that gear (``AllocationProblem.steered``; the sectors are
    narrowed where the program asks for them). Posing is idempotent (a steered velocity steers to
    itself, to rounding, its nearer gear is its own, and neither the gears nor the nominal
    velocities change whether the platoon catches up), so an allocator that hands its posed
    problem to another (the convex one to the dual) poses the same program."""
    if gears == "either":
        problem = problem.in_nearer_gears()
    elif gears == "catching-up":
        problem = problem.in_nearer_gears(where=problem.catching_up())
    return problem.steered() if rate_aware else problem


def program_promise(reading: str, rate_aware: bool, gears: str) -> str:
    """What an allocator solving these programs keeps achievable, in words."""
    sets = "rate-aware sector" if rate_aware else "sector"
    gear = {
        "model": "its gear's",
        "either": "its nearer gear's",
        "catching-up": "its nearer gear's (catching up) or its gear's",
    }[gears]
    if reading == "achievable-first":
        return f"every unit (exempt ones too) in {gear} {sets}"
    return (
        f"the achievable part c of every unit in {gear} {sets} (the handed velocity a meets "
        "the task instead; after the last-resort fallback a = c, the projected nominal velocity)"
    )


def achievable_part_excess(
    problem: AllocationProblem, allocation: Allocation, rate_aware: bool, gears: str
) -> float:
    """How far (m/s) the farthest achievable part lies outside the sector of the gear the program
    posed (``posed``): the handed velocity itself in the achievable-first reading and after the
    last-resort fallback (the projected nominal velocity), c (``info["achievable"]``) in the
    task-exact one."""
    sets = posed(problem, False, gears).achievable(rate_aware=rate_aware)
    return float(np.max(sets.distance(np.asarray(allocation.info.get("achievable", allocation.velocities)))))
