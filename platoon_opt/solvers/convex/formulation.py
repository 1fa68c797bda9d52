"""The convex allocation programs of one step as sparse matrices, shared by every backend.

``build(problem, setup, stage, target)`` poses the achievable-first program (``qp``, ``cone``;
variables ``[v_1, ..., v_nf, s]`` with ``s = J v - u``, so that the Hessian stays diagonal; stages
"joint", "task" and "deviation" of strict priority) or the task-exact one (``qp-projection``,
``cone-projection``; variables ``[a_1, c_1, a_2, c_2, ...]``, objective divided by eps) in the
canonical form ``min 1/2 x^T P x + q^T x + constant`` subject to ``lower <= K x <= upper`` (the
first ``n_eq`` rows equalities; in cone mode each free unit's achievable part also in the speed
disk). Pinned units leave the program, anchored ones stay drawn to their precedence velocity;
equalities are imposed on the regular directions of the free units' ``J J^T`` only. The sparsity
pattern depends only on ``Program.key``, so backends keep a factorization across steps; nonzeros
are O(n m). The mathematics and the reasons: docs/programs.md, sections 2-4.

Shapes: n units, nf free units, m task components; velocities (n, 2) in m/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
import scipy.sparse as sp

from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.programs import READINGS, SPEED_MODELS, STRICT_BAND
from platoon_opt.tasks import TaskJacobian

# Stages of the achievable-first reading: "joint" (rho-weighted), "task" and "deviation"
# (the strict lexicographic solve); the task-exact reading has the single stage "joint".
STAGES = ("joint", "task", "deviation")


@dataclass(frozen=True)
class _Pattern:
    """A fixed CSC pattern from COO coordinates ``rows``, ``cols``; data come in COO order."""

    shape: tuple[int, int]
    rows: np.ndarray
    cols: np.ndarray
    order: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray

    @classmethod
    def of(cls, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> _Pattern:
        order = np.lexsort((rows, cols))
        indptr = np.zeros(shape[1] + 1, dtype=np.int64)
        np.cumsum(np.bincount(cols, minlength=shape[1]), out=indptr[1:])
        return cls(shape, rows, cols, order, rows[order].astype(np.int64), indptr)

    def values(self, data: np.ndarray) -> np.ndarray:
        """The CSC data array (what a backend's in-place update takes)."""
        return data[self.order]

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((self.values(data), self.indices, self.indptr), shape=self.shape)

    def apply(self, data: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The matrix times x (shape[1],), without building the matrix."""
        return np.bincount(self.rows, weights=data * x[self.cols], minlength=self.shape[0])


@dataclass(frozen=True)
class _Structure:
    """Patterns of one program shape (see ``_structure``)."""

    variables: int
    velocity_columns: np.ndarray  # (nf, 2): the velocity handed to each free unit
    achievable_columns: np.ndarray  # (nf, 2): its achievable part (the same for achievable-first)
    hessian: _Pattern  # full symmetric
    hessian_upper: _Pattern
    hessian_upper_entries: np.ndarray  # which COO entries of ``hessian`` are in the upper triangle
    constraints: _Pattern


@lru_cache(maxsize=32)
def _structure(reading: str, stage: str, free: int, per_unit: int, m: int, task_rows: int) -> _Structure:
    """The sparsity patterns for ``free`` units with ``per_unit`` linear rows each, an m-row task
    and ``task_rows`` rows on the task (equalities, or the two sides of the stage-2 band). COO
    order (the order of the data built in ``build``):

    * Hessian: achievable-first, the diagonal; task-exact, per unit and coordinate
      (a, a), (c, c), (a, c), (c, a).
    * Constraints: the task rows (row-major over the block, then the -I of ``s``), then the
      linear rows of each unit (x entry, y entry of each row).
    """
    units = np.arange(free)
    if reading == "achievable-first":
        task_variables = m if stage != "deviation" else 0
        variables = 2 * free + task_variables
        velocity = np.column_stack((2 * units, 2 * units + 1))
        achievable = velocity
        h_rows = h_cols = np.arange(variables)
        eq_rows = np.repeat(np.arange(task_rows), 2 * free)
        eq_cols = np.tile(np.arange(2 * free), task_rows)
        if task_variables:
            eq_rows = np.concatenate((eq_rows, np.arange(m)))
            eq_cols = np.concatenate((eq_cols, 2 * free + np.arange(m)))
    else:
        variables = 4 * free
        velocity = np.column_stack((4 * units, 4 * units + 1))
        achievable = velocity + 2
        a, c = velocity.ravel(), achievable.ravel()
        h_rows = np.concatenate((a, c, a, c))
        h_cols = np.concatenate((a, c, c, a))
        eq_rows = np.repeat(np.arange(task_rows), 2 * free)
        eq_cols = np.tile(a, task_rows)
    lin_rows = task_rows + np.repeat(np.arange(free * per_unit), 2)
    lin_cols = np.repeat(achievable, per_unit, axis=0).ravel()
    upper = h_rows <= h_cols
    rows_total = task_rows + free * per_unit
    return _Structure(
        variables=variables,
        velocity_columns=velocity,
        achievable_columns=achievable,
        hessian=_Pattern.of(h_rows, h_cols, (variables, variables)),
        hessian_upper=_Pattern.of(h_rows[upper], h_cols[upper], (variables, variables)),
        hessian_upper_entries=upper,
        constraints=_Pattern.of(
            np.concatenate((eq_rows, lin_rows)), np.concatenate((eq_cols, lin_cols)), (rows_total, variables)
        ),
    )


@dataclass(frozen=True)
class Program:
    """One step's convex program in canonical form (see the module docstring).

    The matrices are held as their nonzeros on a shared pattern and built as
    ``scipy.sparse`` matrices only when a backend asks (``P``, ``P_upper``, ``K``): a backend
    that keeps its factorization takes the data arrays (``P_upper_values``, ``K_values``),
    and building three sparse matrices per step cost more than Clarabel's solve at n = 8.

    Attributes:
        key: equal keys <=> equal sparsity patterns of P and K (and cone rows).
        structure: the patterns of ``key``.
        hessian_data, constraint_data: nonzeros of P (full symmetric) and K, COO order.
        q: linear term (N,). constant: objective offset, so that the objective is the
            reading's objective (``objective``) over all units, pinned ones included; for the
            task-exact reading it is divided by eps (same minimizer, better resolved by the
            backends), plus a term on anchored units' unused c_i that vanishes at the optimum.
        lower, upper: bounds (rows,) on K x.
        n_eq: the first n_eq rows are equalities.
        cone_columns: (nf, 2) columns of each free unit's achievable part constrained to
            the disk of radius ``max_speed`` (cone mode), or None (polygon mode).
        max_speed: m/s.
        free: indices of the free units (nf,).
        fixed: velocities of the pinned units (n, 2), m/s (rows of free units are zero).
    """

    key: tuple
    structure: _Structure
    hessian_data: np.ndarray
    constraint_data: np.ndarray
    q: np.ndarray
    constant: float
    lower: np.ndarray
    upper: np.ndarray
    n_eq: int
    cone_columns: np.ndarray | None
    max_speed: float
    free: np.ndarray
    fixed: np.ndarray

    @cached_property
    def P(self) -> sp.csc_matrix:
        """Hessian (N, N), full symmetric, CSC."""
        return self.structure.hessian.matrix(self.hessian_data)

    @cached_property
    def P_upper(self) -> sp.csc_matrix:
        """Upper triangle of the Hessian, CSC."""
        return self.structure.hessian_upper.matrix(self.hessian_data[self.structure.hessian_upper_entries])

    @property
    def P_upper_values(self) -> np.ndarray:
        """``P_upper.data`` without building the matrix."""
        return self.structure.hessian_upper.values(self.hessian_data[self.structure.hessian_upper_entries])

    @cached_property
    def K(self) -> sp.csc_matrix:
        """Constraint matrix (rows, N), CSC."""
        return self.structure.constraints.matrix(self.constraint_data)

    @property
    def K_values(self) -> np.ndarray:
        """``K.data`` without building the matrix."""
        return self.structure.constraints.values(self.constraint_data)

    @property
    def velocity_columns(self) -> np.ndarray:
        """(nf, 2) columns of the velocity handed to each free unit."""
        return self.structure.velocity_columns

    @property
    def achievable_columns(self) -> np.ndarray:
        """(nf, 2) columns of each free unit's achievable part."""
        return self.structure.achievable_columns

    @property
    def variables(self) -> int:
        """N, the number of variables."""
        return self.q.shape[0]

    def objective(self, x: np.ndarray) -> float:
        """The program's objective at x (N,), constant included (see ``constant``)."""
        px = self.structure.hessian.apply(self.hessian_data, x)
        return float(0.5 * x @ px + self.q @ x + self.constant)

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velocities handed to the units and their achievable parts, each (n, 2), m/s."""
        velocity, achievable = self.fixed.copy(), self.fixed.copy()
        velocity[self.free] = x[self.velocity_columns]
        achievable[self.free] = x[self.achievable_columns]
        return velocity, achievable

    def violation(self, x: np.ndarray) -> tuple[float, float]:
        """Largest violation of (equality rows, achievable set) at x: |K x - b| over the
        equality rows, and max(K x - upper, ||c_i|| - max_speed) over the others (m/s)."""
        kx = self.structure.constraints.apply(self.constraint_data, x)
        equality = float(np.max(np.abs(kx[: self.n_eq] - self.upper[: self.n_eq]), initial=0.0))
        inside = float(np.max(kx[self.n_eq :] - self.upper[self.n_eq :], initial=0.0))
        if self.cone_columns is not None and self.cone_columns.size:
            speed = np.hypot(x[self.cone_columns[:, 0]], x[self.cone_columns[:, 1]])
            inside = max(inside, float(np.max(speed - self.max_speed)))
        return equality, inside


def regular_directions(rows: np.ndarray, rcond: float) -> np.ndarray:
    """Orthonormal directions E (m, r) of the Gram matrix of ``rows`` (m, nf, 2) that are not
    degenerate (``TaskJacobian``'s criterion): ``E^T J`` has full row rank."""
    return TaskJacobian(rows, rcond).regular_directions()


@dataclass(frozen=True)
class Setup:
    """What ``build`` needs besides the problem, fixed for one step.

    Attributes:
        reading: "achievable-first" or "task-exact".
        speed: "polygon" or "cone".
        normals, offsets: each unit's linear rows (n, k, 2), (n, k) from ``unit_rows``.
        precedence: each unit's precedence velocity p_i (n, 2), m/s: its nominal velocity
            projected onto its achievable set (``inner_projection``).
        interior: a point inside each unit's achievable set (n, 2), m/s.
        pinned: units whose velocity is p_i (n,) bool, eliminated from the program.
        anchored: units kept in the program but drawn to p_i (n,) bool: their term in the
            objective is ``anchor_weight ||v_i - p_i||^2`` (achievable-first) or
            ``anchor_weight ||a_i - p_i||^2`` (task-exact) instead of their usual one.
        rho: task weight of the achievable-first reading (joint stage).
        eps: deviation weight of the task-exact reading.
        anchor_weight: see ``anchored``.
    """

    reading: str
    speed: str
    normals: np.ndarray
    offsets: np.ndarray
    precedence: np.ndarray
    interior: np.ndarray
    pinned: np.ndarray
    anchored: np.ndarray
    rho: float
    eps: float
    anchor_weight: float = 1.0


def build(
    problem: AllocationProblem, setup: Setup, stage: str = "joint", target: np.ndarray | None = None
) -> Program:
    """The program of ``problem`` for one reading and stage.

    Args:
        stage: "joint", or for the achievable-first reading "task" (stage 1 of the strict
            solve: minimize ``||J v - u||^2``) or "deviation" (stage 2: minimize
            ``||v - q'_d||^2`` subject to ``J v = target``).
        target: the stage-1 task velocity ``J v_1`` (m,), for stage "deviation".
    """
    if setup.reading not in READINGS:
        raise ValueError(f"reading must be one of {READINGS}, got {setup.reading!r}")
    if setup.speed not in SPEED_MODELS:
        raise ValueError(f"speed must be one of {SPEED_MODELS}, got {setup.speed!r}")
    if stage not in STAGES or (setup.reading == "task-exact" and stage != "joint"):
        raise ValueError(f"stage {stage!r} does not apply to the {setup.reading} reading")
    rows_all = problem.jacobian.rows
    m = rows_all.shape[0]
    free = np.flatnonzero(~setup.pinned)
    fixed = np.where(setup.pinned[:, None], setup.precedence, 0.0)
    rows = rows_all[:, free, :]
    nominal = problem.nominal[free]
    anchored = setup.anchored[free]
    anchor = setup.precedence[free]
    # What the free units must supply once the pinned ones move at their fixed velocity.
    pinned_task = problem.jacobian.apply(fixed)
    pinned_cost = float(np.sum((fixed - problem.nominal)[setup.pinned] ** 2))
    normals, offsets = setup.normals[free], setup.offsets[free]
    per_unit = normals.shape[1]

    if setup.reading == "achievable-first":
        # Per free unit: weight and target of its deviation term.
        weight = np.where(anchored, setup.anchor_weight, 1.0)
        goal = np.where(anchored[:, None], anchor, nominal)
        w_dev = 0.0 if stage == "task" else 1.0
        hessian = np.repeat(2 * w_dev * weight, 2)
        q = -2 * w_dev * (weight[:, None] * goal).ravel()
        constant = w_dev * float(np.sum(weight[:, None] * goal**2) + pinned_cost)
    else:
        # Scaled by 1/eps: ||a - c||^2 / eps + ||a - q'_d||^2 has the same minimizer, and the
        # backends' absolute tolerances then resolve the eps term (unscaled, Clarabel left
        # errors of 1e-3 m/s in a at eps = 1e-4). An anchored unit's gap term is replaced by
        # anchor_weight ||a_i - p_i||^2 / eps, and its unused c_i is held at an interior point
        # by ||c_i - m_i||^2 (at p_i, on the boundary, Clarabel often ended "AlmostSolved").
        inverse = 1.0 / setup.eps
        gap = np.repeat(np.where(anchored, 0.0, 1.0), 2)
        pull = np.repeat(np.where(anchored, setup.anchor_weight * inverse, 0.0), 2)
        hold = np.repeat(anchored.astype(float), 2)
        interior = setup.interior[free].ravel()
        hessian = np.concatenate(
            (
                2 * (inverse * gap + pull + 1),
                2 * (inverse * gap + hold),
                -2 * inverse * gap,
                -2 * inverse * gap,
            )
        )
        q = np.zeros(4 * free.size)
        linear_a = -2 * (nominal.ravel() + pull * anchor.ravel())
        linear_c = -2 * hold * interior
        q[0::4], q[1::4], q[2::4], q[3::4] = linear_a[0::2], linear_a[1::2], linear_c[0::2], linear_c[1::2]
        constant = float(
            np.sum(nominal**2) + np.sum(pull * anchor.ravel() ** 2) + np.sum(hold * interior**2) + pinned_cost
        )

    if setup.reading == "achievable-first" and stage != "deviation":
        n_eq = m
        rhs = problem.task_velocity - pinned_task
        eq_data = np.concatenate((rows.reshape(m, -1).ravel(), -np.ones(m)))
        w_task = setup.rho if stage == "joint" else 1.0
        hessian = np.concatenate((hessian, np.full(m, 2 * w_task)))
        q = np.concatenate((q, np.zeros(m)))
    else:
        directions = (
            problem.jacobian.regular_directions()
            if free.size == problem.n
            else regular_directions(rows, problem.jacobian.rcond)
        )
        wanted = problem.task_velocity if stage == "joint" else target
        if wanted is None:
            raise ValueError("stage 'deviation' needs the stage-1 task velocity as target")
        rhs = directions.T @ (wanted - pinned_task)
        eq_data = np.einsum("kr,kij->rij", directions, rows).ravel()
        n_eq = directions.shape[1]

    task_rows = n_eq
    if stage == "deviation":
        # Stage 2 keeps J v within a band of STRICT_BAND around the stage-1 task velocity
        # instead of on it: when the task is out of reach, the stage-1 solutions form a face of C
        # (usually one point) and an exact equality leaves no interior, on which Clarabel hit its
        # iteration cap and OSQP declared the problem infeasible.
        band = STRICT_BAND * (1.0 + float(np.max(np.abs(rhs), initial=0.0)))
        eq_data = np.concatenate((eq_data, -eq_data))
        rhs = np.concatenate((rhs + band, band - rhs))
        task_rows, n_eq = 2 * n_eq, 0
    structure = _structure(setup.reading, stage, free.size, per_unit, m, task_rows)
    key = (setup.reading, setup.speed, stage, free.size, per_unit, m, task_rows)
    lower = np.concatenate((rhs[:n_eq], np.full(task_rows - n_eq + free.size * per_unit, -np.inf)))
    upper = np.concatenate((rhs, offsets.ravel()))
    return Program(
        key=key,
        structure=structure,
        hessian_data=hessian,
        constraint_data=np.concatenate((eq_data, normals.ravel())),
        q=q,
        constant=constant,
        lower=lower,
        upper=upper,
        n_eq=n_eq,
        cone_columns=structure.achievable_columns if setup.speed == "cone" else None,
        max_speed=problem.limits.max_speed,
        free=free,
        fixed=fixed,
    )


def objective(
    problem: AllocationProblem,
    setup: Setup,
    velocity: np.ndarray,
    achievable: np.ndarray,
    stage: str = "joint",
) -> float:
    """The objective of ``setup``'s reading over all units at velocities and achievable parts
    (n, 2), m/s, unscaled (the program's own objective is divided by eps for the task-exact
    reading):

    * achievable-first: ``sum_i w_i ||v_i - g_i||^2 + rho ||J v - u||^2`` (stage "task":
      ``||J v - u||^2``; stage "deviation": the first sum), with ``w_i, g_i`` = anchor_weight, p_i
      for anchored units and 1, q'_d,i otherwise;
    * task-exact: ``sum_i ||a_i - c_i||^2 + eps ||a - q'_d||^2``, an anchored unit's gap term being
      ``anchor_weight ||a_i - p_i||^2``.
    """
    anchored = setup.anchored[:, None]
    weight = np.where(anchored, setup.anchor_weight, 1.0)
    if setup.reading == "task-exact":
        gap = np.where(
            anchored, setup.anchor_weight * (velocity - setup.precedence) ** 2, (velocity - achievable) ** 2
        )
        return float(np.sum(gap) + setup.eps * np.sum((velocity - problem.nominal) ** 2))
    goal = np.where(anchored, setup.precedence, problem.nominal)
    residual = problem.jacobian.apply(velocity) - problem.task_velocity
    deviation = float(np.sum(weight * (velocity - goal) ** 2))
    task = float(residual @ residual)
    return {"joint": deviation + setup.rho * task, "task": task, "deviation": deviation}[stage]
