"""Scaling a convex program for its backends (docs/programs.md, section 4): velocities in units
of v_max, the task auxiliary and the task-exact velocities shifted so that every right-hand side
is 0, rows of unit norm, the objective divided by its value for one unit off by v_max in the
least-weighted term. ``formulation.build`` poses the program in the reading's variables ``x`` and
hands the backends ``y`` with ``x = column_offset + column_scale * y``.

Shapes: nf free units, m task components, N variables; velocities in m/s.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from platoon_opt.solvers.convex.patterns import Structure


def columns(
    reading: str,
    structure: Structure,
    rows: np.ndarray,
    rhs: np.ndarray,
    eq_data: np.ndarray,
    max_speed: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The map ``x = offset + scale * y`` (each (N,)) from the backends' variables to the
    reading's (docs/programs.md, section 4):

    * velocities in units of max_speed;
    * achievable-first, the auxiliary ``s = J v - u`` shifted by ``u`` (so that ``y`` is the
      task velocity served, ``J v``, and the equality rows' right-hand side is 0) and in units
      of ``max_speed ||J_k||`` (what ``J_k v`` can reach): with gains of 1e6, ``u`` reached
      1e6 m/s, and Clarabel's tolerances, relative to the right-hand side, let the sector rows
      (right-hand side 0) be violated by 1e-6 m/s or reported infeasibility;
    * task-exact, each handed velocity ``a`` shifted by the least-norm solution ``a0`` of the
      equality rows: ``a - a0`` lies in the null space of the rows and is of the size of the
      achievable parts, whatever ``u``.
    """
    offset = np.zeros(structure.variables)
    scale = np.full(structure.variables, max_speed)
    n_eq = rhs.shape[0]
    nf = rows.shape[1]
    if reading == "achievable-first" and 2 * nf < structure.variables:
        reach = max_speed * np.sqrt(np.einsum("kij,kij->k", rows, rows))
        floor = max(float(np.max(reach, initial=0.0)), max_speed)
        offset[2 * nf :] = -rhs
        scale[2 * nf :] = np.where(reach > 1e-12 * floor, reach, floor)
    elif reading == "task-exact" and n_eq:
        block = eq_data[: n_eq * 2 * nf].reshape(n_eq, 2 * nf)
        particular = block.T @ np.linalg.lstsq(block @ block.T, rhs, rcond=None)[0]
        offset[structure.velocity_columns.ravel()] = particular
    return offset, scale


def objective_scale(reading: str, eps: float, max_speed: float) -> float:
    """What the objective is divided by (m^2/s^2): its value for a deviation of max_speed on the
    term weighted least (eps for the task-exact reading), so that the backends' absolute
    tolerances resolve that term. At v_max^2 alone Clarabel failed on fewer task-exact programs
    (0 instead of 3 of 2,000), but the eps term was then resolved only to about
    sqrt(1e-9 / eps) v_max (2e-4 m/s left at the apex of the zero-nominal problems); the
    minimizer's accuracy comes first (docs/programs.md, section 4)."""
    return max_speed**2 * (eps if reading == "task-exact" else 1.0)


class Scaled(NamedTuple):
    """A program's data in the backends' variables ``y`` (``x = column_offset + column_scale * y``),
    what ``Program`` holds: the nonzeros of P and K (COO order), q, the constant (the reading's
    units), the bounds on K y, each row's factor, and the speed disk's radius in y."""

    hessian_data: np.ndarray
    constraint_data: np.ndarray
    q: np.ndarray
    constant: float
    lower: np.ndarray
    upper: np.ndarray
    row_scale: np.ndarray
    cone_radius: float


def scale(
    structure: Structure,
    *,
    hessian_data: np.ndarray,
    constraint_data: np.ndarray,
    q: np.ndarray,
    constant: float,
    lower: np.ndarray,
    upper: np.ndarray,
    max_speed: float,
    offset: np.ndarray,
    column_scale: np.ndarray,
    objective_scale: float,
    scale_rows: bool,
) -> Scaled:
    """The program of the reading's data (``x``) in the backends' variables ``y`` with
    ``x = offset + column_scale * y``, each row of K divided by its norm in y (if ``scale_rows``),
    the objective by ``objective_scale``."""
    h, c = structure.hessian, structure.constraints
    shifted_q = q + h.apply(hessian_data, offset)
    constant += float(0.5 * offset @ h.apply(hessian_data, offset) + q @ offset)
    column_data = constraint_data * column_scale[c.cols]
    norms = np.sqrt(np.bincount(c.rows, weights=column_data**2, minlength=c.shape[0]))
    row_scale = 1.0 / np.where(norms > 0, norms, 1.0) if scale_rows else np.ones(c.shape[0])
    shift = c.apply(constraint_data, offset)
    return Scaled(
        hessian_data=hessian_data * column_scale[h.rows] * column_scale[h.cols] / objective_scale,
        constraint_data=column_data * row_scale[c.rows],
        q=column_scale * shifted_q / objective_scale,
        constant=constant,
        lower=row_scale * (lower - shift),
        upper=row_scale * (upper - shift),
        row_scale=row_scale,
        cone_radius=max_speed / float(column_scale[0]) if column_scale.size else 1.0,
    )
