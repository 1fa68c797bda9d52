"""One step's allocation program posed in the dual's standard form (docs/dual.md, sections 1
and 6), and its solution mapped back to the units, as JAX kernels with static shapes.

``reduce_program`` poses ``min sum_core w_i ||v_i - g_i||^2 + rho ||J v - u||^2`` over
``v_i in C_i`` (``newton.Standard``) over all n units, the "core" ones marked by a mask: the
achievable-first program as it is, its pinned units masked out; the task-exact program with the
handed velocities a eliminated (docs/dual.md, equations (11) to (15)), over the units that are
neither pinned nor anchored. Units under the paper's precedence rule are pinned at their p_i or
anchored to it by masks and weights, never by taking subsets. ``handed_velocities`` maps the
standard form's solution back to the velocities handed to the n units and their achievable
parts, each (n, 2) in m/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp

from platoon_opt.arrays import pytree
from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.dual.coupling import cholesky, gram, solve_lower, task_basis
from platoon_opt.solvers.dual.newton import Solution, Standard


@pytree(data=("outer", "anchored", "rows", "alpha", "target", "point"))
@dataclass(frozen=True)
class Elimination:
    """What maps a task-exact standard form's solution c back to the handed velocities a
    (docs/dual.md, section 6).

    Attributes:
        outer: (n,) 1.0 for the units whose a is eliminated (every unit not pinned).
        anchored: (n,) 1.0 for the anchored units (their c is p_i, their m_i fixed).
        rows: K J over the outer units (m, n, 2) (zero rows for the directions left out).
        alpha: the weights alpha_i (n,) of ``sum alpha_i ||a_i - m_i||^2``.
        target: K t (m,).
        point: the anchored units' fixed m_i (n, 2) (equation (15); unused elsewhere).
    """

    outer: Any
    anchored: Any
    rows: Any
    alpha: Any
    target: Any
    point: Any


@pytree(data=("program", "held", "precedence", "scale", "constant", "to_task", "from_task", "elimination"))
@dataclass(frozen=True)
class Reduced:
    """One step's program in the dual's standard form and what maps its solution back.

    Attributes:
        program: the standard form (``newton.Standard``).
        held: (n,) bool, the units under the precedence rule; precedence: their p_i (n, 2), m/s
            (computed for every unit: the fallback hands them all out).
        scale, constant: the program's objective = scale * standard form's + constant.
        to_task, from_task: (m, m): the standard form's multipliers to those of the task rows in
            task coordinates (``K^T``; the identity for achievable-first) and back.
        elimination: task-exact only (None: achievable-first): how a comes back from c.
    """

    program: Standard
    held: Any
    precedence: Any
    scale: Any
    constant: Any
    to_task: Any
    from_task: Any
    elimination: Elimination | None


def _share(rows: Any, velocity: Any, mask: Any) -> Any:
    """J v (m,) of the units ``mask`` (n,) alone."""
    return jnp.einsum("kij,ij->k", rows, velocity * mask[:, None])


def reduce_program(
    problem: AllocationProblem,
    sets: Any,
    precedence: Any,
    *,
    reading: str,
    rule: str,
    rho: Any,
    eps: Any,
    anchor_weight: Any,
) -> Reduced:
    """The program of ``reading`` for ``problem`` (n units, m rows) over the dual's sets ``sets``
    in the standard form (docs/dual.md, sections 1 and 6), units under the precedence rule
    (``problem.exempt``) pinned at or anchored to ``precedence`` (n, 2) by ``rule`` ("pin" or
    "anchor", with ``anchor_weight``); ``rho``, ``eps`` as the allocator's options."""
    d, u, rows = (
        jnp.asarray(problem.nominal),
        jnp.asarray(problem.task_velocity),
        jnp.asarray(problem.jacobian.rows),
    )
    m, n = rows.shape[0], rows.shape[1]
    held = jnp.asarray(problem.exempt)
    heldf = held.astype(float)
    free = 1.0 - heldf
    gap = precedence - d
    deviation = jnp.sum(heldf * jnp.sum(gap * gap, axis=1))
    pin = rule == "pin"
    ones, identity = jnp.ones(n), jnp.eye(m)
    radius = problem.limits.max_speed
    if pin:
        # Pinned units leave the program; the task they serve leaves it with them.
        u = u - _share(rows, precedence, heldf)
    if reading == "achievable-first":
        if pin:
            program = Standard(d[:, 0], d[:, 1], ones, free, rows * free[None, :, None], u, rho, sets, radius)
            return Reduced(program, held, precedence, 1.0, deviation, identity, identity, None)
        weight = jnp.where(held, anchor_weight, 1.0)
        goal = jnp.where(held[:, None], precedence, d)
        program = Standard(goal[:, 0], goal[:, 1], weight, ones, rows, u, rho, sets, radius)
        return Reduced(program, held, precedence, 1.0, 0.0, identity, identity, None)
    # Task-exact: a is eliminated over the non-pinned ("outer") units, each a_i weighted by
    # alpha_i = 1 + eps (free) or anchor_weight + eps (anchored) around m_i; J a = t holds on the
    # regular directions E of the outer units' J J^T, and K = L^-1 E^T with L L^T = E^T J A^-1 J^T E.
    outer = free if pin else ones
    anchored = jnp.zeros(n) if pin else heldf
    alpha = jnp.where(anchored > 0, anchor_weight + eps, 1.0 + eps)
    outer_rows = rows * outer[None, :, None]
    if pin:
        vectors, regular = task_basis(outer_rows, problem.jacobian.rcond)
    else:  # every unit is outer: the model's eigenvectors of J J^T are the outer units'
        vectors, regular = jnp.asarray(problem.jacobian.vectors), jnp.asarray(problem.jacobian.regular)
    basis = vectors * regular[None, :]
    # Directions left out get an identity block, so that their rows of K are 0 and their
    # multipliers decouple (and stay 0).
    matrix = basis.T @ gram(outer_rows, 1.0 / alpha) @ basis + jnp.diag(jnp.where(regular, 0.0, 1.0))
    factor, _ = cholesky(matrix)
    projection = solve_lower(factor, basis.T)  # K (m, m)
    scaled = jnp.einsum("rk,kij->rij", projection, outer_rows)
    target = projection @ u
    point = (anchor_weight * precedence + eps * d) / (anchor_weight + eps)
    # K t less what the anchored units' fixed a_i = m_i serve; the core is the free units.
    core_rows = scaled * free[None, :, None]
    core_target = target - _share(scaled, point, anchored)
    shifted = (1 + eps) * core_target - eps * _share(core_rows, d, free)
    program = Standard(
        d[:, 0], d[:, 1], ones, free, core_rows, shifted, 1.0 / (eps * (1 + eps)), sets, radius
    )
    constant = eps * deviation if pin else anchor_weight * eps / (anchor_weight + eps) * deviation
    return Reduced(
        program,
        held,
        precedence,
        eps / (1 + eps),
        constant,
        projection.T,
        factor.T @ basis.T,
        Elimination(outer, anchored, scaled, alpha, target, point),
    )


def handed_velocities(reduced: Reduced, solution: Solution, eps: Any) -> tuple[Any, Any]:
    """The handed velocities and their achievable parts (n, 2): v and v; or, task-exact,
    ``a = m - A^-1 J^T K^T K (J m - t)`` over the outer units (equation (12)) and c. Units outside
    the core (pinned; task-exact: anchored too) have p_i as their achievable part (pinned ones as
    their velocity)."""
    v = jnp.stack((solution.vx, solution.vy), axis=1)
    achievable = jnp.where(reduced.program.core[:, None] > 0, v, reduced.precedence)
    exact = reduced.elimination
    if exact is None:  # achievable-first: v is handed out, its own achievable part
        return achievable, achievable
    d = jnp.stack((reduced.program.dx, reduced.program.dy), axis=1)
    point = jnp.where(exact.anchored[:, None] > 0, exact.point, (v + eps * d) / (1 + eps))
    residual = _share(exact.rows, point, exact.outer) - exact.target
    a = point - jnp.einsum("r,rij->ij", residual, exact.rows) / exact.alpha[:, None]
    return jnp.where(exact.outer[:, None] > 0, a, reduced.precedence), achievable
