"""The time series of one closed-loop run (``Trajectory``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from platoon_opt.avoidance import CircularObstacles


@dataclass(frozen=True)
class Trajectory:
    """Time series of one run. T steps; states are sampled at the T + 1 instants ``t``.

    Attributes:
        t: (T + 1,) s.
        x, y, theta, alpha, gear: (T + 1, n) unit states (m, rad, +-1).
        task_value, desired: f(q(t)) and f_d(t), (T + 1, m).
        target: target position (T + 1, 2), m.
        task_names: the m component names.
        status: allocation status per step (T,).
        iterations, task_residual, deviation, solve_time: per step (T,).
        fell_back: per step (T,) bool.
        exempt: number of units under the precedence rule per step (T,).
        obstacles: the obstacles of this run (after the seed's jitter).
        scenario, allocator, seed: what was run.
        dt: the time step (s).
        solved: per step (T,) bool, whether the allocation ran a solve (``Allocation.solved``;
            False where ``nmpc`` handed its stored plan). None, as a trajectory built without it
            passes, is replaced by every step solving.
        program_changed: per step (T,) bool, whether the allocation answered another program
            than its allocator poses (``Allocation.program_changed``). None (a trajectory
            built without it) is replaced by no step changing it.
        slack: per step (T,) int, units whose barrier rows were relaxed (``info["slack_units"]``);
            None (a trajectory built without it) is replaced by zeros.
        compiled: whether the compiled engine ran it (``platoon_opt.engine``; its ``solve_time``
            is nan: the allocation is not timed apart from the compiled step) or the host loop.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    gear: np.ndarray
    task_value: np.ndarray
    desired: np.ndarray
    target: np.ndarray
    task_names: tuple[str, ...]
    status: np.ndarray
    iterations: np.ndarray
    task_residual: np.ndarray
    deviation: np.ndarray
    solve_time: np.ndarray
    fell_back: np.ndarray
    exempt: np.ndarray
    obstacles: CircularObstacles
    scenario: str
    allocator: str
    seed: int
    dt: float
    solved: np.ndarray | None = None
    program_changed: np.ndarray | None = None
    slack: np.ndarray | None = None
    compiled: bool = False

    def __post_init__(self) -> None:
        if self.solved is None:
            object.__setattr__(self, "solved", np.ones(self.steps, dtype=bool))
        if self.program_changed is None:
            object.__setattr__(self, "program_changed", np.zeros(self.steps, dtype=bool))
        if self.slack is None:
            object.__setattr__(self, "slack", np.zeros(self.steps, dtype=int))

    @property
    def steps(self) -> int:
        """Number of steps T."""
        return self.t.shape[0] - 1

    def component(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """f and f_d of the task component ``name``, each (T + 1,)."""
        k = self.task_names.index(name)
        return self.task_value[:, k], self.desired[:, k]
