"""What an allocator answers and the contracts it may keep.

``Allocation`` is one step's result (velocities (n, 2) in m/s, with the allocator's status);
``Allocator`` turns an ``AllocationProblem`` (``platoon_opt.problem``) into one. The optional
protocols say what else the closed loop may ask of an allocator: to check the task before a run
(``TaskChecked``), to be handed the reference over its horizon (``Previewing``), to apply barrier
parameters of its own (``SafetyAware``). ``safe_fallback`` is what a step whose allocator failed
hands out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from platoon_opt.problem import AllocationProblem
from platoon_opt.safety import SafetyParams


@dataclass(frozen=True)
class Allocation:
    """What an allocator returns for one step.

    Attributes:
        velocities: desired tip velocities handed to the units (n, 2), m/s, always finite.
        allocator: the allocator's name (with its main option, e.g. "iterative(m=4)").
        status: "optimal", "converged", "max_iterations", ... ; a fallback is prefixed
            "fallback:" and names what failed.
        iterations: iterations the allocator ran.
        task_residual: ||J q' - u||.
        deviation: ||q' - q'_d|| (all units, m/s).
        solve_time: wall time of the allocation (s).
        fell_back: whether the primary method failed and a fallback produced the result.
        degenerate_task: directions of J J^T that were damped (a variance near 0).
        info: allocator-specific extras (backend, duality gap, ...).
        solved: whether the allocation ran a solve of its own at this step (a fallback's
            counts); False when it reused an earlier one, as ``nmpc`` handing its stored plan
            between solves. Compute time per solve counts the steps with ``solved``.
        program_changed: whether the velocities answer another program than the one the
            allocator poses (a ``cone`` variant answered on the inscribed polygon, strict
            priority's first stage alone, or no program: the nominal velocity projected onto
            each unit's set). A fallback to another exact solver of the same program leaves it
            False; ``info["program"]`` names what was solved.
    """

    velocities: np.ndarray
    allocator: str
    status: str
    iterations: int
    task_residual: float
    deviation: float
    solve_time: float
    fell_back: bool = False
    degenerate_task: int = 0
    info: Mapping[str, Any] = field(default_factory=dict)
    solved: bool = True
    program_changed: bool = False

    @classmethod
    def of(
        cls,
        problem: AllocationProblem,
        velocities: np.ndarray,
        *,
        allocator: str,
        status: str,
        iterations: int,
        solve_time: float,
        fell_back: bool = False,
        solved: bool = True,
        program_changed: bool = False,
        **info: Any,
    ) -> Allocation:
        """Build the result for ``problem``, computing the residual and the deviation;
        ``info`` holds the allocator's extras."""
        if not np.isfinite(velocities).all():
            raise FloatingPointError(f"{allocator}: non-finite velocities for status {status!r}")
        difference = velocities - problem.nominal
        return cls(
            velocities=velocities,
            allocator=allocator,
            status=status,
            iterations=iterations,
            task_residual=problem.task_residual(velocities),
            # Not np.linalg.norm: its BLAS dot product stalls on a busy machine (15 ms at n = 32,768).
            deviation=math.sqrt(float(np.einsum("ij,ij->", difference, difference))),
            solve_time=solve_time,
            fell_back=fell_back,
            degenerate_task=int(problem.jacobian.degenerate),
            info=dict(info),
            solved=solved,
            program_changed=program_changed,
        )


@runtime_checkable
class Allocator(Protocol):
    """Turns an ``AllocationProblem`` into an ``Allocation``. ``name`` labels its results."""

    name: str

    def allocate(self, problem: AllocationProblem) -> Allocation:
        """Velocities for one step."""
        ...


@runtime_checkable
class TaskChecked(Protocol):
    """An allocator with options that must fit the task (one weight per task component): it
    says so once, before the first step, instead of failing at every step."""

    def check_task(self, names: tuple[str, ...]) -> None:
        """Raise ``OptionError`` (naming the option, what it must be and the value) unless the
        options fit a task with components ``names``."""
        ...


@runtime_checkable
class Previewing(Protocol):
    """An allocator that plans ahead: the closed loop hands it f_d over its horizon
    (``AllocationProblem.desired_ahead``), as a receding-horizon controller is given its
    reference, instead of leaving it to extrapolate."""

    def preview_times(self, problem: AllocationProblem) -> np.ndarray:
        """The times after ``problem.t`` (K,), s, at which it wants f_d for ``problem``; none
        when it will not plan at this step."""
        ...


@runtime_checkable
class SafetyAware(Protocol):
    """An allocator whose options may switch barrier constraints on or change their numbers."""

    def safety_for(self, problem: AllocationProblem) -> SafetyParams:
        """The safety parameters this allocator applies to ``problem``."""
        ...


def safety_of(problem: AllocationProblem, allocator: Allocator) -> SafetyParams:
    """The barrier parameters ``allocator`` applies to ``problem``: its options over the scenario's."""
    return allocator.safety_for(problem) if isinstance(allocator, SafetyAware) else problem.safety


def safe_fallback(problem: AllocationProblem, allocator: Allocator) -> np.ndarray:
    """The velocities (n, 2) of a step whose allocator failed: the nominal velocity projected onto
    each unit's achievable set, or onto its safe set (rate-aware sector, barrier rows) when the
    allocator or the scenario keeps barriers on."""
    params = safety_of(problem, allocator)
    if params.enabled:
        return problem.safe_sets(params).project(problem.nominal)
    return problem.achievable().project(problem.nominal)


def check_allocator(allocator: Allocator, names: tuple[str, ...]) -> None:
    """Let ``allocator`` refuse a task with components ``names`` (``TaskChecked``), before a run."""
    if isinstance(allocator, TaskChecked):
        allocator.check_task(tuple(names))
