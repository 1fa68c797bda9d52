"""The cross-check of a compiled convex program against Clarabel, on the problems of its own runs.

A study runs the convex programs (``qp``, ``qp-projection``, ``cone``, ``cone-projection``) through
the dual in the compiled engine (``backend="dual"``). Closed loops of two exact solvers of one
program part at the level of their rounding and then drift apart (the paper scenarios amplify a
difference of 1e-15 a billion times over 45 s), so their integrated errors cannot be compared run
by run. What can be compared is the allocation: ``cross_check`` takes a configuration's runs on
some seeds (as the study kept them, or run again in the engine), poses again the problem of every
``every``-th step from the recorded state, and solves it with the dual and with Clarabel. Both
answers are feasible points of one program, and the dual's duality gap certifies that its point is
within 1e-10 (relative) of the optimum: the check passes when no answer of Clarabel's is better
than the dual's by more than ``AGREE``. Clarabel's own answers to the task-exact programs lie up
to about 2e-5 (relative) above the dual's at its default settings (the term weighted by
eps = 1e-4 makes them ill-conditioned): the section reports that too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from platoon_opt.problem import AllocationProblem
from platoon_opt.scenarios import Scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers.convex.allocator import ConvexAllocator
from platoon_opt.study.config import AllocatorConfig, AllocatorFactory
from platoon_opt.trajectory import Trajectory
from platoon_opt.vehicle import PlatoonState

# An objective of Clarabel's below the dual's by more than this (relative) would contradict the
# dual's certificate (its relative gap stops at 1e-10; Clarabel meets its constraints to 1e-8).
AGREE = 1e-6
# Steps between two problems checked.
EVERY = 50


class CrossCheck(NamedTuple):
    """The dual against Clarabel on one configuration's problems of one scenario.

    Attributes:
        scenario, config: what was checked; reference: the Clarabel configuration's label.
        seeds: the seeds whose runs were replayed; problems: problems solved by both.
        excess: the largest (dual's objective - Clarabel's) over the scale (``_relative``): how
            much better than the dual Clarabel did, at most (<= 0: never better).
        behind: the largest (Clarabel's objective - the dual's) over the scale: how far above the
            dual's optimum Clarabel's answers lay.
        velocity: the largest difference of a handed velocity (m/s).
        worst: (seed, t) of the largest ``excess``.
    """

    scenario: str
    config: str
    reference: str
    seeds: tuple[int, ...]
    problems: int
    excess: float
    behind: float
    velocity: float
    worst: tuple[int, float]

    @property
    def agree(self) -> bool:
        """No answer of Clarabel's better than the dual's by more than ``AGREE``."""
        return self.excess <= AGREE


def clarabel_of(config: AllocatorConfig) -> AllocatorConfig:
    """``config`` with Clarabel as its backend, its other options kept (label "<name>:clarabel",
    then those options: "qp-projection:clarabel,rate_aware=True")."""
    options = {**dict(config.options), "backend": "clarabel"}
    others = ",".join(f"{key}={value}" for key, value in config.options if key != "backend")
    return AllocatorConfig(
        config.name, tuple(options.items()), f"{config.name}:clarabel" + (f",{others}" if others else "")
    )


def cross_check(
    scenario: Scenario,
    config: AllocatorConfig,
    factory: AllocatorFactory,
    seeds: Sequence[int],
    *,
    every: int = EVERY,
    duration: float | None = None,
    tracks: Sequence[Trajectory | None] | None = None,
) -> CrossCheck:
    """Replay the problems of ``config``'s compiled runs on ``seeds`` through Clarabel.

    ``tracks``: per seed, the run's trajectory as the study kept it (thinned by a stride that
    divides ``every``: the same problems), or None to run it again in the engine."""
    reference = clarabel_of(config)
    names = tuple(scenario.task().names)
    count, excess, behind, velocity, worst = 0, -math.inf, -math.inf, 0.0, (seeds[0], 0.0)
    for seed, kept in zip(seeds, tracks if tracks is not None else [None] * len(seeds)):
        trajectory = (
            kept
            if kept is not None
            else simulate(scenario, config.build(factory), seed=seed, duration=duration, compiled=True)
        )
        stride = round(trajectory.dt / scenario.dt)
        if every % stride:
            raise ValueError(f"cross_check: a track thinned by {stride} has no problem every {every} steps")
        dual, clarabel = config.build(factory), reference.build(factory)
        if not isinstance(dual, ConvexAllocator) or dual.exact is None:
            raise ValueError(f"cross_check: {config.label} is no convex program solved by the dual")
        for k in range(0, trajectory.steps, every // stride):
            problem = _problem_at(scenario, names, trajectory, k)
            ours, theirs = dual.allocate(problem), clarabel.allocate(problem)
            unit = dual.exact.objective_unit(problem)
            difference = _relative(ours.info["objective"], theirs.info["objective"], unit)
            count += 1
            if difference > excess:
                excess, worst = difference, (seed, float(trajectory.t[k]))
            behind = max(behind, -difference)
            gap = np.asarray(ours.velocities) - np.asarray(theirs.velocities)
            velocity = max(velocity, float(np.max(np.hypot(gap[:, 0], gap[:, 1]))))
    return CrossCheck(
        scenario.name, config.label, reference.label, tuple(seeds), count, excess, behind, velocity, worst
    )


def _problem_at(scenario: Scenario, names: tuple[str, ...], trajectory: Any, k: int) -> AllocationProblem:
    """The problem the engine posed at step ``k`` of ``trajectory``, posed again from its state."""
    state = PlatoonState(
        trajectory.x[k], trajectory.y[k], trajectory.theta[k], trajectory.alpha[k], trajectory.gear[k]
    )
    t = float(trajectory.t[k])
    desired, rate, _ = scenario.desired_at(names, t)
    return AllocationProblem.build(
        state,
        scenario.task(),
        desired,
        rate,
        scenario.gains,
        scenario.limits,
        scenario.dt,
        avoidance=scenario.avoidance,
        obstacles=trajectory.obstacles,
        t=t,
        safety=scenario.safety,
    )


def _relative(ours: float, theirs: float, unit: float) -> float:
    """(ours - theirs) relative to the larger, or to ``unit`` (m^2/s^2) if that is larger: the
    objective of one unit off by v_max in the term weighted least, the scale of the dual's relative
    gap (docs/dual.md, section 8), below which an optimum near 0 is met by both to rounding."""
    if not (math.isfinite(ours) and math.isfinite(theirs)):
        return math.inf
    return (ours - theirs) / max(abs(ours), abs(theirs), unit)


def cross_check_section(checks: Sequence[CrossCheck]) -> str:
    """The report's section: a row per scenario and configuration."""
    if not checks:
        return ""
    lines = [
        "## Cross-check: the compiled dual against Clarabel\n",
        "The convex programs ran through the dual in the compiled engine. On the seeds below the "
        f"problem of every {EVERY}th step of those runs was posed again from the recorded state and "
        "solved by both the dual and Clarabel (the same program). Both answers are feasible, and "
        "the dual's duality gap certifies its own within 1e-10 of the optimum, so the check passes "
        f"when no answer of Clarabel's is better than the dual's by more than {AGREE:g} (relative to "
        "the larger objective, or to the cost of one unit off by v_max, the scale of the dual's "
        "relative gap). Clarabel above the dual: how far Clarabel's answers lay above the dual's "
        "optimum. (Runs of the two solvers themselves part at the level of their rounding and "
        "drift apart over a run, so their integrated errors are not compared.)\n",
        "| scenario | configuration | against | seeds | problems | Clarabel better by, at most "
        "(relative) | Clarabel above the dual, at most | largest velocity difference (m/s) | agree |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for check in checks:
        lines.append(
            f"| {check.scenario} | `{check.config}` | `{check.reference}` | "
            f"{', '.join(map(str, check.seeds))} | {check.problems} | {max(check.excess, 0.0):.2g} | "
            f"{max(check.behind, 0.0):.2g} | {check.velocity:.2g} | {'yes' if check.agree else '**no**'} |"
        )
    return "\n".join(lines) + "\n"
