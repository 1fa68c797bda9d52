"""The convex allocation programs of one step as sparse matrices, shared by every backend.

``build(problem, setup, stage, target)`` poses the achievable-first program (``qp``, ``cone``;
variables ``[v_1, ..., v_nf, s]`` with ``s = J v - u``, so that the Hessian stays diagonal; stages
"joint", "task" and "deviation" of strict priority) or the task-exact one (``qp-projection``,
``cone-projection``; variables ``[a_1, c_1, a_2, c_2, ...]``) in the canonical form
``min 1/2 x^T P x + q^T x + constant`` subject to ``lower <= K x <= upper`` (the first ``n_eq``
rows equalities; in cone mode each free unit's achievable part also in the speed disk), then
scaled for the backends: ``x = column_offset + column_scale * y``, rows divided by their norms,
the objective by v_max^2 (task-exact: eps v_max^2; ``Program``; docs/programs.md, section 4).
Pinned units leave the program, anchored ones stay drawn to their precedence velocity; equalities
are imposed on the regular directions of the free units' ``J J^T`` only. The sparsity pattern
depends only on ``Program.key``, so backends keep a factorization across steps; nonzeros are
O(n m). The mathematics and the reasons: docs/programs.md, sections 2-4.

Shapes: n units, nf free units, m task components; velocities (n, 2) in m/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from platoon_opt.problem import AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.solvers.convex import scaling
from platoon_opt.solvers.convex.patterns import Structure, structure
from platoon_opt.solvers.programs import READINGS, SPEED_MODELS, STRICT_BAND
from platoon_opt.tasks import TaskJacobian

# Stages of the achievable-first reading: "joint" (rho-weighted), "task" and "deviation"
# (the strict lexicographic solve); the task-exact reading has the single stage "joint".
STAGES = ("joint", "task", "deviation")


@dataclass(frozen=True)
class Program:
    """One step's convex program in canonical form (see the module docstring), as the backends
    are given it: scaled (docs/programs.md, section 4). The variables of the reading, ``x`` in
    its units (m/s; task velocities for the auxiliary ``s``), are
    ``column_offset + column_scale * y`` for the backends' variables ``y``; each row of
    ``lower <= K x <= upper`` is multiplied by ``row_scale``; the objective is divided by
    ``objective_scale``. Every method below takes the backends' ``y`` and answers in the
    reading's units.

    The matrices are held as their nonzeros on a shared pattern and built as
    ``scipy.sparse`` matrices only when a backend asks (``P``, ``P_upper``, ``K``): a backend
    that keeps its factorization takes the data arrays (``P_upper_values``, ``K_values``),
    and building three sparse matrices per step cost more than Clarabel's solve at n = 8.

    Attributes:
        key: equal keys <=> equal sparsity patterns of P and K (and cone rows).
        structure: the patterns of ``key``.
        hessian_data, constraint_data: nonzeros of P (full symmetric) and K, COO order (scaled).
        q: linear term (N,), scaled.
        constant: objective offset in the reading's units, so that ``objective`` is the
            reading's objective over all units, pinned ones included (plus, for the task-exact
            reading, a term on anchored units' unused c_i that vanishes at the optimum).
        lower, upper: bounds (rows,) on K y (scaled).
        n_eq: the first n_eq rows are equalities.
        cone_columns: (nf, 2) columns of each free unit's achievable part constrained to
            the disk ``||y_c|| <= cone_radius`` (cone mode), or None (polygon mode).
        cone_radius: the speed disk's radius in the backends' units (max_speed over the
            velocity scale).
        max_speed: m/s.
        free: indices of the free units (nf,).
        fixed: velocities of the pinned units (n, 2), m/s (rows of free units are zero).
        column_offset, column_scale: (N,) the map from y to x.
        row_scale: (rows,) what each row of K, lower and upper was multiplied by.
        objective_scale: what the objective was divided by.
        equality_scale: 1 + the largest right-hand side of the equality rows before the
            shift (what ``EQUALITY_TOLERANCE`` is relative to).
    """

    key: tuple
    structure: Structure
    hessian_data: np.ndarray
    constraint_data: np.ndarray
    q: np.ndarray
    constant: float
    lower: np.ndarray
    upper: np.ndarray
    n_eq: int
    cone_columns: np.ndarray | None
    cone_radius: float
    max_speed: float
    free: np.ndarray
    fixed: np.ndarray
    column_offset: np.ndarray
    column_scale: np.ndarray
    row_scale: np.ndarray
    objective_scale: float
    equality_scale: float

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
    def strongly_convex(self) -> bool:
        """Whether P is positive definite: the achievable-first reading's "joint" and
        "deviation" stages, whose Hessian is a diagonal of positive weights. Strict priority's
        "task" stage prices only ``J v - u``, and the task-exact objective is flat along the
        velocities the eps term alone decides between (docs/programs.md, section 4)."""
        reading, _, stage = self.key[:3]
        return reading == "achievable-first" and stage != "task"

    @property
    def variables(self) -> int:
        """N, the number of variables."""
        return self.q.shape[0]

    def original(self, y: np.ndarray) -> np.ndarray:
        """The reading's variables x (N,) of the backends' y (N,)."""
        return self.column_offset + self.column_scale * y

    def scaled(self, x: np.ndarray) -> np.ndarray:
        """The backends' y (N,) of the reading's variables x (N,)."""
        return (x - self.column_offset) / self.column_scale

    def objective(self, y: np.ndarray) -> float:
        """The reading's objective at the backends' y (N,), constant included (see ``constant``)."""
        py = self.structure.hessian.apply(self.hessian_data, y)
        return float(self.objective_scale * (0.5 * y @ py + self.q @ y) + self.constant)

    def unpack(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velocities handed to the units and their achievable parts, each (n, 2), m/s."""
        x = self.original(y)
        velocity, achievable = self.fixed.copy(), self.fixed.copy()
        velocity[self.free] = x[self.velocity_columns]
        achievable[self.free] = x[self.achievable_columns]
        return velocity, achievable

    def violation(self, y: np.ndarray) -> tuple[float, float]:
        """Largest violation of (equality rows, achievable set) at the backends' y, in the
        reading's units: |K x - b| over the equality rows, and max(K x - upper,
        ||c_i|| - max_speed) over the others (m/s)."""
        residual = (self.structure.constraints.apply(self.constraint_data, y) - self.upper) / self.row_scale
        equality = float(np.max(np.abs(residual[: self.n_eq]), initial=0.0))
        inside = float(np.max(residual[self.n_eq :], initial=0.0))
        if self.cone_columns is not None and self.cone_columns.size:
            x = self.original(y)
            speed = np.hypot(x[self.cone_columns[:, 0]], x[self.cone_columns[:, 1]])
            inside = max(inside, float(np.max(speed - self.max_speed)))
        return equality, inside


def regular_directions(rows: np.ndarray, rcond: float) -> np.ndarray:
    """Orthonormal directions E (m, r) of the Gram matrix of ``rows`` (m, nf, 2) that are not
    degenerate (``TaskJacobian``'s criterion): ``E^T J`` has full row rank."""
    return TaskJacobian.of(rows, rcond).regular_directions()


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
        safe: the safe sets whose barrier rows ``normals`` holds (None without safety): what
            the allocator projects onto when it moves a solution into the sets.
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
    safe: SafeSets | None = None


def build(
    problem: AllocationProblem,
    setup: Setup,
    stage: str = "joint",
    target: np.ndarray | None = None,
    scaled: bool = True,
) -> Program:
    """The program of ``problem`` for one reading and stage, as the backends are given it.

    Args:
        stage: "joint", or for the achievable-first reading "task" (stage 1 of the strict
            solve: minimize ``||J v - u||^2``) or "deviation" (stage 2: minimize
            ``||v - q'_d||^2`` subject to ``J v = target``).
        target: the stage-1 task velocity ``J v_1`` (m,), for stage "deviation".
        scaled: False gives the program in the reading's own variables and rows (column map
            the identity, row and objective scales 1): the same minimizer, badly conditioned
            for the backends; what tests check the scaled solutions against.
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
        # ||a - c||^2 + eps ||a - q'_d||^2 per unit. An anchored unit's gap term is replaced by
        # anchor_weight ||a_i - p_i||^2, and its unused c_i is held at an interior point by
        # eps ||c_i - m_i||^2 (at p_i, on the boundary, Clarabel often ended "AlmostSolved").
        eps = setup.eps
        gap = np.repeat(np.where(anchored, 0.0, 1.0), 2)
        pull = np.repeat(np.where(anchored, setup.anchor_weight, 0.0), 2)
        hold = np.repeat(np.where(anchored, eps, 0.0), 2)
        interior = setup.interior[free].ravel()
        hessian = np.concatenate((2 * (gap + pull + eps), 2 * (gap + hold), -2 * gap, -2 * gap))
        q = np.zeros(4 * free.size)
        linear_a = -2 * (eps * nominal.ravel() + pull * anchor.ravel())
        linear_c = -2 * hold * interior
        q[0::4], q[1::4], q[2::4], q[3::4] = linear_a[0::2], linear_a[1::2], linear_c[0::2], linear_c[1::2]
        constant = float(
            eps * np.sum(nominal**2)
            + np.sum(pull * anchor.ravel() ** 2)
            + np.sum(hold * interior**2)
            + eps * pinned_cost
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
    equality_scale = 1.0 + float(np.max(np.abs(rhs), initial=0.0))

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
    shape = structure(setup.reading, stage, free.size, per_unit, m, task_rows)
    key = (setup.reading, setup.speed, stage, free.size, per_unit, m, task_rows)
    lower = np.concatenate((rhs[:n_eq], np.full(task_rows - n_eq + free.size * per_unit, -np.inf)))
    upper = np.concatenate((rhs, offsets.ravel()))
    constraint_data = np.concatenate((eq_data, normals.ravel()))
    max_speed = problem.limits.max_speed
    if scaled:
        offset, column_scale = scaling.columns(setup.reading, shape, rows, rhs[:n_eq], eq_data, max_speed)
    else:
        offset, column_scale = np.zeros(shape.variables), np.ones(shape.variables)
    objective_scale = scaling.objective_scale(setup.reading, setup.eps, max_speed) if scaled else 1.0
    data = scaling.scale(
        shape,
        hessian_data=hessian,
        constraint_data=constraint_data,
        q=q,
        constant=constant,
        lower=lower,
        upper=upper,
        max_speed=max_speed,
        offset=offset,
        column_scale=column_scale,
        objective_scale=objective_scale,
        scale_rows=scaled,
    )
    return Program(
        key=key,
        structure=shape,
        **data._asdict(),
        n_eq=n_eq,
        cone_columns=shape.achievable_columns if setup.speed == "cone" else None,
        max_speed=max_speed,
        free=free,
        fixed=fixed,
        column_offset=offset,
        column_scale=column_scale,
        objective_scale=objective_scale,
        equality_scale=equality_scale,
    )


def objective(
    problem: AllocationProblem,
    setup: Setup,
    velocity: np.ndarray,
    achievable: np.ndarray,
    stage: str = "joint",
) -> float:
    """The objective of ``setup``'s reading over all units at velocities and achievable parts
    (n, 2), m/s (``Program.objective`` is the same function of the backends' variables):

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
