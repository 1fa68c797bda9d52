"""Platoon tasks written symbolically with CasADi: the Jacobian and df/dt by automatic
differentiation.

A user writes f as a Python function of CasADi symbols, ``f(x, y)`` or ``f(x, y, t)``,
with ``x`` and ``y`` column vectors (n x 1, the tip coordinates in m) and ``t`` a scalar
(s), returning m components; or hands a ready ``casadi.Function`` of a fixed n. The task
compiles, once per platoon size n, one ``casadi.Function`` per quantity (value, Jacobian,
partial time derivative) and caches it, so a simulation pays the symbolic work once.

    import casadi as ca
    from platoon_opt.solvers.symbolic import SymbolicTask

    def spread(x, y):
        n = x.numel()
        mx, my = ca.sum1(x) / n, ca.sum1(y) / n
        return ca.vertcat(mx, my, (ca.sumsqr(x - mx) + ca.sumsqr(y - my)) / (n - 1))

    task = SymbolicTask(("mean_x", "mean_y", "spread"), spread)

The Jacobian is returned as rows (m, n, 2), O(m n) memory like every ``Task``; the graph of
a task built from sums and elementwise operations is O(n) (CasADi differentiates it in
reverse mode), so building the Function for n = 20,000 takes a few seconds, not 12 GB.

Scenario files name these tasks by kind (``platoon_opt.scenarios.TASKS``):
``[task] kind = "symbolic_covariance"`` names ``covariance_task()`` (kind "covariance" is the same
task written by hand, ``platoon_opt.tasks.CovarianceTask``, which the compiled engine can trace).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from platoon_opt.tasks import TaskJacobian


@dataclass(frozen=True)
class _Compiled:
    """The Functions of one platoon size: value (m,), Jacobian blocks (m, n) in x and y, df/dt (m,)."""

    value: ca.Function
    jacobian: ca.Function
    time_derivative: ca.Function


@dataclass(frozen=True)
class SymbolicTask:
    """A platoon task f(q, t) defined by a CasADi expression; implements ``platoon_opt.Task``.

    Attributes:
        names: the m component names (used by scenarios: "mean_x"/"mean_y" follow the
            target, every other component is a constant of ``[task.desired]``).
        expression: ``f(x, y)`` or ``f(x, y, t)`` building the m components from CasADi SX
            symbols ``x``, ``y`` (n x 1, m) and ``t`` (scalar, s); or a ``casadi.Function``
            with inputs ``(x, y)`` or ``(x, y, t)`` of one fixed n and one output (m x 1).
        rcond: passed to ``TaskJacobian`` (damping of vanishing rows).
    """

    names: tuple[str, ...]
    expression: Callable[..., Any] | ca.Function
    rcond: float = 1e-6
    _cache: dict[int, _Compiled] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        names = tuple(self.names)
        if not names or not all(isinstance(name, str) and name for name in names):
            raise ValueError(f"SymbolicTask.names must be non-empty strings, got {self.names!r}")
        if len(set(names)) != len(names):
            raise ValueError(f"SymbolicTask.names must be distinct, got {self.names!r}")
        object.__setattr__(self, "names", names)
        if isinstance(self.expression, ca.Function):
            if self.expression.n_in() not in (2, 3) or self.expression.n_out() != 1:
                raise ValueError(
                    "SymbolicTask.expression as a casadi.Function must take (x, y) or (x, y, t) and "
                    f"return one output, got {self.expression.n_in()} inputs, "
                    f"{self.expression.n_out()} outputs"
                )
        elif not callable(self.expression):
            raise TypeError(f"SymbolicTask.expression must be callable, got {self.expression!r}")

    def compiled(self, n: int) -> _Compiled:
        """The Functions for a platoon of ``n`` units, built on first use and cached."""
        if n not in self._cache:
            self._cache[n] = self._compile(n)
        return self._cache[n]

    def _compile(self, n: int) -> _Compiled:
        x, y, t = ca.SX.sym("x", n), ca.SX.sym("y", n), ca.SX.sym("t")
        f = self._evaluate_symbolic(x, y, t, n)
        # Reverse mode: m adjoint sweeps over an O(n) graph give the m x n blocks in O(m n).
        return _Compiled(
            value=ca.Function("task_value", [x, y, t], [f]),
            jacobian=ca.Function("task_jacobian", [x, y, t], [ca.jacobian(f, x), ca.jacobian(f, y)]),
            time_derivative=ca.Function("task_time_derivative", [x, y, t], [ca.jacobian(f, t)]),
        )

    def _evaluate_symbolic(self, x: ca.SX, y: ca.SX, t: ca.SX, n: int) -> ca.SX:
        expression = self.expression
        if isinstance(expression, ca.Function):
            if expression.numel_in(0) != n:
                raise ValueError(
                    f"SymbolicTask: the casadi.Function takes n = {expression.numel_in(0)} units, got n = {n}"
                )
            args = [x, y, t][: expression.n_in()]
            f = expression(*args)
        else:
            takes_time = len(inspect.signature(expression).parameters) >= 3
            f = expression(x, y, t) if takes_time else expression(x, y)
        f = ca.vec(ca.vertcat(*f) if isinstance(f, (list, tuple)) else ca.SX(f))
        if f.numel() != len(self.names):
            raise ValueError(
                f"SymbolicTask: the expression returns {f.numel()} components for "
                f"{len(self.names)} names {self.names!r}"
            )
        return f

    @staticmethod
    def _split(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        positions = np.asarray(positions, dtype=float)
        if positions.ndim != 2 or positions.shape[1] != 2:
            raise ValueError(f"positions must have shape (n, 2), got shape {positions.shape}")
        return positions[:, 0], positions[:, 1]

    def value(self, positions: np.ndarray, t: float = 0.0) -> np.ndarray:
        """f(q, t), shape (m,), for tip positions (n, 2) in m at time ``t`` (s)."""
        x, y = self._split(positions)
        return self.compiled(x.shape[0]).value(x, y, t).full().reshape(-1)

    def jacobian(self, positions: np.ndarray, t: float = 0.0) -> TaskJacobian:
        """df/dq at (q, t) as ``TaskJacobian`` rows (m, n, 2)."""
        x, y = self._split(positions)
        jx, jy = self.compiled(x.shape[0]).jacobian(x, y, t)
        return TaskJacobian.of(np.stack((jx.full(), jy.full()), axis=-1), self.rcond)

    def time_derivative(self, positions: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Partial df/dt at (q, t), shape (m,), 1/s times the components' units."""
        x, y = self._split(positions)
        return self.compiled(x.shape[0]).time_derivative(x, y, t).full().reshape(-1)


# --- tasks written this way -----------------------------------------------------------------


def mean_variance_expression(x: ca.SX, y: ca.SX) -> ca.SX:
    """Eq. 4 written symbolically: [mu_x, var_x, mu_y, var_y] (m, m^2, m, m^2), unbiased variance."""
    n = x.numel()
    mx, my = ca.sum1(x) / n, ca.sum1(y) / n
    return ca.vertcat(mx, ca.sumsqr(x - mx) / (n - 1), my, ca.sumsqr(y - my) / (n - 1))


def covariance_expression(x: ca.SX, y: ca.SX) -> ca.SX:
    """Eq. 4 plus the sample covariance: [mu_x, var_x, mu_y, var_y, cov_xy] (cov_xy in m^2).

    The covariance matrix [[var_x, cov_xy], [cov_xy, var_y]] is the formation's spread
    ellipse: its eigenvectors are the formation's axes, so commanding cov_xy (with var_x
    and var_y) commands the formation's orientation, angle 0.5 atan2(2 cov_xy, var_x - var_y).
    """
    n = x.numel()
    mx, my = ca.sum1(x) / n, ca.sum1(y) / n
    dx, dy = x - mx, y - my
    return ca.vertcat(mx, ca.sumsqr(dx) / (n - 1), my, ca.sumsqr(dy) / (n - 1), ca.dot(dx, dy) / (n - 1))


def symbolic_mean_variance_task() -> SymbolicTask:
    """The paper's task (Eq. 4) built by automatic differentiation; equals ``MeanVarianceTask``."""
    return SymbolicTask(("mean_x", "var_x", "mean_y", "var_y"), mean_variance_expression)


def covariance_task() -> SymbolicTask:
    """[mean_x, var_x, mean_y, var_y, cov_xy]: position, spread and orientation of the formation."""
    return SymbolicTask(("mean_x", "var_x", "mean_y", "var_y", "cov_xy"), covariance_expression)
