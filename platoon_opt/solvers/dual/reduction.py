"""One step's allocation program posed in the dual's standard form (docs/dual.md, sections 1
and 6), and its solution mapped back to the units.

``reduce_program`` keeps the "core" units and poses
``min sum_core w_i ||v_i - g_i||^2 + rho ||J v - u||^2`` over ``v_i in C_i`` (``Reduced``):
the achievable-first program as it is, less its pinned units; the task-exact program with the
handed velocities a eliminated (docs/dual.md, equations (11) to (15)). ``handed_velocities``
maps the standard form's solution back to the velocities handed to the n units and their
achievable parts, each (n, 2) in m/s. Units under the paper's precedence rule are pinned at
their p_i (``precedence_velocities``) or anchored to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from platoon_opt.limits import AchievableSets, inner_projection, unit_rows
from platoon_opt.problem import AllocationProblem
from platoon_opt.safe_sets import SafeSets
from platoon_opt.solvers.dual.coupling import Coupling, inverse_sqrt, task_basis
from platoon_opt.solvers.dual.newton import DualSolution
from platoon_opt.solvers.dual.safe import SafeDualSets
from platoon_opt.solvers.dual.sets import PolygonSets, SectorSets, make_sets


@dataclass(frozen=True)
class Anchors:
    """The anchored units of a task-exact program: their positions among the outer units
    (``anchored``), the core units' positions there (``local``), and their fixed m_i (h_a, 2)."""

    local: np.ndarray
    anchored: np.ndarray
    point: np.ndarray


@dataclass(frozen=True)
class Elimination:
    """What maps a task-exact standard form's solution c back to the handed velocities a
    (docs/dual.md, section 6).

    Attributes:
        outer: the non-pinned units (None: all).
        coupling: K J over them.
        alpha: their weights alpha_i in ``sum alpha_i ||a_i - m_i||^2``.
        target: K t.
        anchors: the anchored units (None: none anchored).
    """

    outer: np.ndarray | None
    coupling: Coupling
    alpha: np.ndarray
    target: np.ndarray
    anchors: Anchors | None


@dataclass(frozen=True)
class Reduced:
    """One step's program in the dual's standard form over its "core" units,
    ``min sum_core w_i ||v_i - g_i||^2 + rho ||J v - u||^2``, and what maps its solution back.

    Achievable-first: the core is every unit but the pinned ones (anchored units take
    ``w_i = anchor_weight``, ``g_i = p_i``). Task-exact: the core is the units that are neither
    pinned nor anchored (their c); a is eliminated (docs/dual.md, section 6), anchored units' c
    is p.

    Attributes:
        core: indices of the core units (None: all units).
        held, precedence: the units under the precedence rule and their p_i (h, 2), m/s.
        dx, dy, weight: g and w of the core units ((n_c,); weight None when all 1).
        sets, coupling, u, rho: the core units' C_i, J (task-exact: K J, K of docs/dual.md,
            equation (12)), u and rho.
        scale, constant: the program's objective = scale * standard form's + constant.
        elimination: task-exact only (None: achievable-first): how a comes back from c.
        to_task, from_task: task-exact only: multipliers of the standard form to those of
            ``J a = t`` in task coordinates (``K^T``, (m, r)) and back (``L^-1 E^T``, (r, m)).
    """

    core: np.ndarray | None
    held: np.ndarray
    precedence: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    weight: np.ndarray | None
    sets: SectorSets | PolygonSets | SafeDualSets
    coupling: Coupling
    u: np.ndarray
    rho: float
    scale: float
    constant: float
    elimination: Elimination | None = None
    to_task: np.ndarray | None = None
    from_task: np.ndarray | None = None


def precedence_velocities(
    problem: AllocationProblem,
    sets: AchievableSets,
    index: np.ndarray,
    speed: str,
    sides: int,
    safe: SafeSets | None = None,
) -> np.ndarray:
    """p_i (len(index), 2), m/s, of the units ``index`` under the precedence rule, as
    ``platoon_opt.solvers.convex.formulation`` takes it: the nominal velocity projected onto the
    exact sector, then shortened along its ray into the polygon (``speed``, ``sides``); with
    barriers (``safe``), projected onto the safe set."""
    if safe is not None:
        return safe.take(index).project(problem.nominal[index])
    units = sets.take(index)
    normals, offsets = unit_rows(units, speed, sides, problem.limits.max_speed)
    return inner_projection(problem.nominal[index], units, normals, offsets)


def reduce_program(
    problem: AllocationProblem,
    sets: AchievableSets,
    *,
    reading: str,
    speed: str,
    sides: int,
    rule: str,
    rho: float,
    eps: float,
    anchor_weight: float,
    safe: SafeSets | None = None,
) -> Reduced:
    """The program of ``reading`` for ``problem`` over the sets ``sets`` (n units) in the dual's
    standard form (docs/dual.md, sections 1 and 6), units under the precedence rule pinned or
    anchored (``rule``, ``anchor_weight``); ``speed``, ``sides``, ``rho``, ``eps`` as the
    allocator's options; with barriers, ``safe``'s sets (docs/safety.md) in place of ``sets``."""

    def core_sets(index: np.ndarray | None) -> SectorSets | PolygonSets | SafeDualSets:
        if safe is not None:
            return SafeDualSets.of(safe if index is None else safe.take(index))
        return make_sets(sets if index is None else sets.take(index), speed, sides)

    d, u, coupling = problem.nominal, problem.task_velocity, Coupling.of(problem.jacobian.rows)
    held = problem.exempt.nonzero()[0]
    precedence = (
        precedence_velocities(problem, sets, held, speed, sides, safe) if held.size else np.zeros((0, 2))
    )
    pin = rule == "pin" and held.size > 0
    free = (~problem.exempt).nonzero()[0] if pin else None
    if pin:
        # Pinned units leave the program; the task they serve leaves it with them.
        u = u - coupling.take(held).apply(precedence[:, 0], precedence[:, 1])
    deviation = float(np.sum((precedence - d[held]) ** 2)) if held.size else 0.0
    if reading == "achievable-first":
        goal, weight = d if free is None else d[free], None
        if held.size and not pin:
            goal, weight = d.copy(), np.ones(problem.n)
            goal[held], weight[held] = precedence, anchor_weight
        return Reduced(
            free,
            held,
            precedence,
            np.ascontiguousarray(goal[:, 0]),
            np.ascontiguousarray(goal[:, 1]),
            weight,
            core_sets(free),
            coupling if free is None else coupling.take(free),
            u,
            rho,
            1.0,
            deviation if pin else 0.0,
        )
    # Task-exact: a is eliminated over the non-pinned ("outer") units, each a_i weighted by
    # alpha_i = 1 + eps (free) or anchor_weight + eps (anchored) around m_i; J a = t holds
    # on the regular directions E of the outer units' J J^T, and K = (E^T J A^-1 J^T E)^-1/2 E^T.
    w = anchor_weight
    outer = coupling if free is None else coupling.take(free)
    anchored = held if held.size and not pin else None
    alpha = np.full(outer.jx.shape[1], 1 + eps)
    if anchored is not None:
        alpha[anchored] = w + eps
    gram = problem.jacobian.orthogonal_gram
    if free is None and anchored is None and gram is not None:
        # Rows orthogonal in closed form, every unit weighted alike: E picks the regular rows
        # and E^T J A^-1 J^T E = diag(gram) / (1 + eps), no eigendecomposition.
        # K = diag(scale) E^T, and the map back diag(1 / scale) E^T, without forming diag(scale).
        basis = problem.jacobian.regular_directions()
        scale = np.sqrt((1 + eps) / gram[basis.argmax(axis=0)])
        projection, to_task, from_task = basis.T * scale[:, None], basis * scale, basis.T / scale[:, None]
    else:
        basis = task_basis(outer, problem.jacobian.rcond)
        root = inverse_sqrt(basis.T @ outer.gram(1.0 / alpha) @ basis)
        projection, to_task, from_task = root @ basis.T, basis @ root, np.linalg.solve(root, basis.T)
    scaled = outer.transform(projection)
    target = projection @ u
    core = free
    core_target = target  # K t less what the anchored units' fixed a_i = m_i serve
    anchors = None
    if anchored is not None:
        core = (~problem.exempt).nonzero()[0]
        anchors = Anchors(core, anchored, (w * precedence + eps * d[held]) / (w + eps))
        core_target = target - scaled.take(anchored).apply(anchors.point[:, 0], anchors.point[:, 1])
    inner = scaled if anchors is None else scaled.take(anchors.local)
    index = slice(None) if core is None else core
    dx, dy = np.ascontiguousarray(d[index, 0]), np.ascontiguousarray(d[index, 1])
    shifted = (1 + eps) * core_target - eps * inner.apply(dx, dy)
    return Reduced(
        core,
        held,
        precedence,
        dx,
        dy,
        None,
        core_sets(core),
        inner,
        shifted,
        1.0 / (eps * (1 + eps)),
        eps / (1 + eps),
        eps * deviation if pin else w * eps / (w + eps) * deviation,
        elimination=Elimination(free, scaled, alpha, target, anchors),
        to_task=to_task,
        from_task=from_task,
    )


def handed_velocities(
    problem: AllocationProblem, reduced: Reduced, solution: DualSolution, *, eps: float
) -> tuple[np.ndarray, np.ndarray]:
    """The handed velocities and their achievable parts (n, 2): v and v; or, task-exact,
    ``a = m - A^-1 J^T K^T K (J m - t)`` over the outer units and c."""
    core = slice(None) if reduced.core is None else reduced.core
    achievable = np.empty((problem.n, 2))
    if reduced.held.size:
        achievable[reduced.held] = reduced.precedence
    achievable[core, 0], achievable[core, 1] = solution.vx, solution.vy
    exact = reduced.elimination
    if exact is None:  # achievable-first: v is handed out, its own achievable part
        return achievable, achievable
    mx, my = (solution.vx + eps * reduced.dx) / (1 + eps), (solution.vy + eps * reduced.dy) / (1 + eps)
    if exact.anchors is not None:
        mx, my = np.empty(exact.alpha.size), np.empty(exact.alpha.size)
        mx[exact.anchors.local] = (solution.vx + eps * reduced.dx) / (1 + eps)
        my[exact.anchors.local] = (solution.vy + eps * reduced.dy) / (1 + eps)
        mx[exact.anchors.anchored], my[exact.anchors.anchored] = (
            exact.anchors.point[:, 0],
            exact.anchors.point[:, 1],
        )
    tx, ty = exact.coupling.apply_transpose(exact.coupling.apply(mx, my) - exact.target)
    velocities = achievable.copy()
    outer = slice(None) if exact.outer is None else exact.outer
    velocities[outer, 0], velocities[outer, 1] = mx - tx / exact.alpha, my - ty / exact.alpha
    return velocities, achievable
