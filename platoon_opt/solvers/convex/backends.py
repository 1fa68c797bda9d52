"""Backends that solve a ``formulation.Program``: OSQP and Clarabel through their own APIs
(persistent workspaces), any other ``qpsolvers`` solver, and CasADi's ``conic`` plugins.

Backend names:

* ``"osqp"``: OSQP's own API. One workspace per program structure (``Program.key``) is kept
  across steps; later steps only update the numbers (``update(Px=, Ax=, q=, l=, u=)``, so the
  symbolic factorization is reused) and start from the previous solution (OSQP's
  ``warm_starting``). Tolerances are tight and the iteration cap raised (``OSQP_SETTINGS``):
  at OSQP's defaults the result is not exact, and at eps 1e-6 with the default cap about 0.3 %
  of the steps ended in "max iter" (docs/programs.md, section 5).
* ``"clarabel"``: Clarabel's own API, the only backend for the exact speed cone
  (``clarabel.SecondOrderConeT``). For a strongly convex program one solver per structure,
  its numbers updated in place; the update keeps the first data's equilibration, so a failure
  or a rejected answer of a kept solver is retried with a new one. A program that is not
  strongly convex (task-exact, strict priority's first stage) gets a new solver every time
  (docs/programs.md, section 4). An interior-point method takes no warm start.
* any other name in ``qpsolvers.available_solvers``, or ``"qpsolvers:<name>"`` for any of them
  (osqp and clarabel included): ``qpsolvers.solve_problem`` with the previous solution of the
  same structure as ``initvals`` (used by the solvers that accept it). A new solver is set up at
  every step. OSQP and Clarabel get the tolerances of their own backends
  (``QPSOLVERS_SETTINGS``), any other solver its defaults.
* ``"casadi:<plugin>"``: ``casadi.conic`` with a plugin shipped in the casadi wheel (qpoases,
  osqp, daqp, qrqp, proxqp, highs). One conic Function per structure: its sparsity
  patterns are those of the program. The plugin's memory carries a solve to the next (qpOASES
  hot-starts from the last active set); a failure after a hot start is retried once cold, with a
  new Function, so that an unrelated earlier program cannot change the answer. What the plugins
  print to stdout (qpOASES's licence banner, at any ``printLevel``) is dropped.

``solve`` raises ``BackendFailure`` (or whatever the backend raises) when no solution is
returned; the caller validates the solution and falls back. ``osqp_solver``, ``clarabel_form``
and ``clarabel_solver`` are what the OSQP and Clarabel backends set up for a program (public, so
that the benchmark can time a bare solve of the same data).
"""

from __future__ import annotations

import ctypes
import os
import sys
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, redirect_stdout
from dataclasses import dataclass
from functools import cache
from typing import Any, NamedTuple

import casadi
import clarabel
import numpy as np
import osqp
import qpsolvers
import scipy.sparse as sp

from platoon_opt.errors import PlatoonOptError
from platoon_opt.solvers.convex.formulation import Program

# OSQP's defaults (eps 1e-3, 4000 iterations) are far from exact. With these, polishing
# (an active-set refinement) usually makes the result exact to round-off.
OSQP_SETTINGS: dict[str, Any] = {
    "eps_abs": 1e-9,
    "eps_rel": 1e-9,
    "max_iter": 100_000,
    "polishing": True,
    "polish_refine_iter": 10,
    "warm_starting": True,
    "verbose": False,
}
# At Clarabel's default tolerances (1e-8) about one random test problem in ten overshoots a
# limit by 1e-7 to 2e-7 m/s; at 1e-9 none did, and in closed loop 1 step in 4500 ended
# "AlmostSolved" (at 1e-10: 50).
#
# Every program here is feasible and its objective bounded below (strictly convex in the velocities,
# C contains 0), so a certificate of infeasibility is always a numerical artefact: it is asked for
# to 1e-12 instead of 1e-8. At 1e-8, task-exact cone programs with gains of 1e6 ended
# "DualInfeasible" (6 of 10,000 soak problems), and solve to optimal at 1e-12.
#
# A fresh solver that fails is retried once without equilibration (``_clarabel``): of 3,600
# cone-projection programs with barriers (tests/conftest.py::safe_problem, seeds 0-2,999 crowded
# and 0-599 not), 5 ended "AlmostSolved" with equilibration (objectives near -1e5 in scaled units,
# stopped at iteration 10-12 with residuals near 1e-10) and all 5 solved without it, while
# without it alone 19 others failed.
CLARABEL_SETTINGS: dict[str, Any] = {
    "verbose": False,
    "tol_feas": 1e-9,
    "tol_gap_abs": 1e-9,
    "tol_gap_rel": 1e-9,
    "tol_infeas_abs": 1e-12,
    "tol_infeas_rel": 1e-12,
}
# qpsolvers' own interfaces to OSQP and Clarabel get the same tolerances as their native backends
# (at OSQP's defaults the answer violated the limits by up to 6e-4 m/s and every step of a run
# fell back); qpsolvers sets ``verbose`` itself.
QPSOLVERS_SETTINGS: dict[str, dict[str, Any]] = {
    "osqp": {k: v for k, v in OSQP_SETTINGS.items() if k != "verbose"},
    "clarabel": {k: v for k, v in CLARABEL_SETTINGS.items() if k != "verbose"},
}
CASADI_PLUGIN_OPTIONS: dict[str, dict[str, Any]] = {
    "qpoases": {"printLevel": "none"},
    "qrqp": {"print_iter": False, "print_header": False, "print_info": False},
    "osqp": {"osqp": {k: v for k, v in OSQP_SETTINGS.items() if k != "warm_starting"}},
    "highs": {"highs": {"output_flag": False}},
    # At its default eps_abs (1e-5) proxqp's answers broke the limits by 1e-7 to 2e-6 m/s and were
    # refused on 54-81 % of the achievable-first steps of three scenarios' first second; at 1e-9
    # on none of them (experiments/backends.py).
    "proxqp": {"proxqp": {"eps_abs": 1e-9, "eps_rel": 0.0}},
}
# The QP plugins of casadi's wheel offered as "casadi:<plugin>". Not hpipm: it reads the
# program's sparsity as an optimal control problem's stages, and on these programs its
# interface refuses the structure or the solve fails, at every step.
CASADI_PLUGINS = ("qpoases", "osqp", "daqp", "qrqp", "proxqp", "highs")
# Workspaces kept per allocator (structures differ by the number of free units, stages, ...).
CACHE_SIZE = 8


class BackendFailure(PlatoonOptError, RuntimeError):
    """A backend returned no usable solution; the message is its status."""


@dataclass(frozen=True)
class Solved:
    """A backend's answer: solution x (N,), its iteration count, its status string, and whether
    it came from a solver kept from earlier programs (``reused``)."""

    x: np.ndarray
    iterations: int
    status: str
    reused: bool = False  # from state kept from earlier programs: retried ``fresh`` if rejected


def supports_cone(backend: str) -> bool:
    """Whether ``backend`` handles the second-order cone (only Clarabel here)."""
    return backend == "clarabel"


@cache
def known_backends() -> tuple[str, ...]:
    """Backend names that can be used here: qpsolvers' installed solvers (osqp and clarabel through
    their own APIs), ``qpsolvers:<name>`` for each of them, and ``casadi:<plugin>`` for the
    ``CASADI_PLUGINS`` this casadi build can load."""
    installed = sorted(qpsolvers.available_solvers)
    return (
        *sorted({"osqp", "clarabel", *installed}),
        *(f"qpsolvers:{name}" for name in installed),
        *(f"casadi:{plugin}" for plugin in CASADI_PLUGINS if casadi.has_conic(plugin)),
    )


class Workspaces:
    """Backend state kept across steps (LRU over ``CACHE_SIZE`` structures): OSQP and Clarabel
    solvers, CasADi functions, and the last solution of each structure (for warm starts).
    Not thread-safe: use one allocator per thread or process. Pickling or copying an allocator
    leaves its workspaces behind (the native solvers cannot be pickled)."""

    def __init__(self) -> None:
        self._entries: OrderedDict[tuple, Any] = OrderedDict()

    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self._entries = OrderedDict()

    def get(self, key: tuple) -> Any:
        entry = self._entries.get(key)
        if entry is not None:
            self._entries.move_to_end(key)
        return entry

    def put(self, key: tuple, entry: Any) -> None:
        self._entries[key] = entry
        self._entries.move_to_end(key)
        while len(self._entries) > CACHE_SIZE:
            self._entries.popitem(last=False)


def solve(
    program: Program, backend: str, workspaces: Workspaces, options: Mapping[str, Any], fresh: bool = False
) -> Solved:
    """Solve ``program`` with ``backend`` and extra backend ``options`` (merged over the defaults);
    with ``fresh``, without the state kept from earlier programs (a new Clarabel solver).

    Raises:
        BackendFailure: the backend reported anything but an exact solve.
        ValueError: a cone program for a backend without cones.
    """
    if program.cone_columns is not None and not supports_cone(backend):
        raise ValueError(f"backend {backend!r} cannot handle the speed cone")
    if backend == "osqp":
        return _osqp(program, workspaces, options)
    if backend == "clarabel":
        return _clarabel(program, workspaces, options, fresh)
    if backend.startswith("casadi:"):
        return _casadi(program, backend[len("casadi:") :], workspaces, options)
    return _qpsolvers(program, backend.removeprefix("qpsolvers:"), workspaces, options)


def osqp_solver(program: Program, options: Mapping[str, Any] | None = None) -> osqp.OSQP:
    """An OSQP solver set up for ``program`` (``OSQP_SETTINGS`` with ``options`` over them)."""
    solver = osqp.OSQP()
    solver.setup(
        P=program.P_upper,
        q=program.q,
        A=program.K,
        l=program.lower,
        u=program.upper,
        **{**OSQP_SETTINGS, **(options or {})},
    )
    return solver


def _osqp(program: Program, workspaces: Workspaces, options: Mapping[str, Any]) -> Solved:

    key = ("osqp", program.key)
    solver = workspaces.get(key)
    if solver is None:
        solver = osqp_solver(program, options)
        workspaces.put(key, solver)
    else:
        solver.update(
            q=program.q, l=program.lower, u=program.upper, Px=program.P_upper_values, Ax=program.K_values
        )
    result = solver.solve(raise_error=False)
    if result.info.status != "solved":
        raise BackendFailure(result.info.status)
    return Solved(np.array(result.x), int(result.info.iter), result.info.status)


def _stack_rows(top: sp.csc_matrix, bottom: sp.csc_matrix) -> tuple[sp.csc_matrix, np.ndarray]:
    """[top; bottom] in CSC with every stored entry (explicit zeros too) kept, so the pattern of
    the result depends only on the patterns of the inputs; and where top's entries went in the
    result's data (top.nnz,)."""
    top_counts, bottom_counts = np.diff(top.indptr), np.diff(bottom.indptr)
    indptr = np.concatenate(([0], np.cumsum(top_counts + bottom_counts)))
    starts = indptr[:-1]
    top_at = np.repeat(starts - top.indptr[:-1], top_counts) + np.arange(top.nnz)
    bottom_at = np.repeat(starts + top_counts - bottom.indptr[:-1], bottom_counts) + np.arange(bottom.nnz)
    data = np.empty(top.nnz + bottom.nnz)
    indices = np.empty(top.nnz + bottom.nnz, dtype=np.int64)
    data[top_at], data[bottom_at] = top.data, bottom.data
    indices[top_at], indices[bottom_at] = top.indices, bottom.indices + top.shape[0]
    shape = (top.shape[0] + bottom.shape[0], top.shape[1])
    return sp.csc_matrix((data, indices, indptr), shape=shape), top_at


class ClarabelForm(NamedTuple):
    """A program in Clarabel's form ``A x + s = b, s in K`` (``clarabel_form``).

    Attributes:
        matrix: A (CSC): the rows of ``Program.K``, then the cone rows.
        k_entries: where K's stored entries sit in ``matrix.data`` (K.nnz,): an in-place update
            writes ``Program.K_values`` there (the cone rows' entries never change).
        offsets: b.
        cones: the cones of the rows, in order.
    """

    matrix: sp.csc_matrix
    k_entries: np.ndarray
    offsets: np.ndarray
    cones: list


def clarabel_form(program: Program) -> ClarabelForm:
    """The data Clarabel is given for ``program``: equality rows (zero cone), one-sided rows
    (nonnegative cone), then per free unit in cone mode ``s = (cone_radius, c_x, c_y)`` in a
    second-order cone."""
    rows = program.K.shape[0]
    cones: list = []
    if program.n_eq:
        cones.append(clarabel.ZeroConeT(program.n_eq))
    if rows > program.n_eq:
        cones.append(clarabel.NonnegativeConeT(rows - program.n_eq))
    if program.cone_columns is None or not program.cone_columns.size:
        return ClarabelForm(program.K, np.arange(program.K.nnz), _clarabel_offsets(program), cones)
    units = program.cone_columns.shape[0]
    soc = sp.csc_matrix(
        (
            -np.ones(2 * units),
            (np.arange(3 * units).reshape(units, 3)[:, 1:].ravel(), program.cone_columns.ravel()),
        ),
        shape=(3 * units, program.variables),
    )
    cones.extend(clarabel.SecondOrderConeT(3) for _ in range(units))
    A, k_at = _stack_rows(program.K, soc)
    return ClarabelForm(A, k_at, _clarabel_offsets(program), cones)


def clarabel_solver(
    program: Program, form: ClarabelForm | None = None, options: Mapping[str, Any] | None = None
) -> clarabel.DefaultSolver:
    """A Clarabel solver set up for ``program`` in its ``form`` (``clarabel_form(program)`` if
    None), with ``CLARABEL_SETTINGS`` and ``options`` over them."""
    form = clarabel_form(program) if form is None else form
    settings = clarabel.DefaultSettings()
    for name, value in {**CLARABEL_SETTINGS, **(options or {})}.items():
        setattr(settings, name, value)
    return clarabel.DefaultSolver(program.P_upper, program.q, form.matrix, form.offsets, form.cones, settings)


def _clarabel_offsets(program: Program) -> np.ndarray:
    """Clarabel's b: the upper bounds of K x, then (cone_radius, 0, 0) per cone-mode unit."""
    if program.cone_columns is None or not program.cone_columns.size:
        return program.upper.copy()
    offsets = np.zeros(3 * program.cone_columns.shape[0])
    offsets[0::3] = program.cone_radius
    return np.concatenate((program.upper, offsets))


@dataclass
class _ClarabelWorkspace:
    """A Clarabel solver kept for one program structure: its A's data, and where K's nonzeros
    sit in it (the cone rows' entries never change)."""

    solver: Any
    A_values: np.ndarray
    K_at: np.ndarray


def _clarabel(program: Program, workspaces: Workspaces, options: Mapping[str, Any], fresh: bool) -> Solved:
    """Solve a strongly convex program with the kept solver of its structure, its numbers
    updated in place (saving the set-up: 0.8 ms a step at n = 8, the solve 0.26 ms), else a new one.
    The update keeps the equilibration Clarabel computed for the data it was set up with; on
    unrelated data that scaling can be far off (problems a fresh solver solved ended
    "AlmostSolved" or "DualInfeasible"), so a failure of a kept solver is retried at once with a
    new one, and an answer the caller rejects is solved again ``fresh`` (``Solved.reused``). A
    program that is not strongly convex (task-exact, strict's first stage) gets a new solver
    every time: along its flat directions a stale equilibration moved the answer by up to
    1e-3 m/s (objectives 1e-6 relative apart), more than an answer may depend on earlier calls."""
    fresh = fresh or not program.strongly_convex
    key = ("clarabel", program.key)
    workspace = None if fresh else workspaces.get(key)
    reused = workspace is not None and workspace.solver.is_data_update_allowed()
    if workspace is not None and reused:
        workspace.A_values[workspace.K_at] = program.K_values
        workspace.solver.update(
            P=program.P_upper_values, q=program.q, A=workspace.A_values, b=_clarabel_offsets(program)
        )
    else:
        form = clarabel_form(program)
        workspace = _ClarabelWorkspace(
            clarabel_solver(program, form, options), form.matrix.data.copy(), form.k_entries
        )
        workspaces.put(key, workspace)
    result = workspace.solver.solve()
    if result.status != clarabel.SolverStatus.Solved:
        if reused:
            return _clarabel(program, workspaces, options, fresh=True)
        if options.get("equilibrate_enable", True):
            # Without equilibration the same program takes more iterations and fails more often
            # alone, but not on the programs that fail with it (measured: see CLARABEL_SETTINGS).
            retried = clarabel_solver(program, None, {**options, "equilibrate_enable": False}).solve()
            if retried.status == clarabel.SolverStatus.Solved:
                return Solved(np.array(retried.x), int(result.iterations + retried.iterations), "solved")
        raise BackendFailure(str(result.status))
    return Solved(np.array(result.x), int(result.iterations), "solved", reused=reused)


def _qpsolvers(program: Program, backend: str, workspaces: Workspaces, options: Mapping[str, Any]) -> Solved:

    eq = slice(0, program.n_eq)
    ineq = slice(program.n_eq, None)
    problem = qpsolvers.Problem(
        P=program.P,
        q=program.q,
        G=program.K[ineq] if program.K.shape[0] > program.n_eq else None,
        h=program.upper[ineq] if program.K.shape[0] > program.n_eq else None,
        A=program.K[eq] if program.n_eq else None,
        b=program.upper[eq] if program.n_eq else None,
    )
    key = ("qpsolvers", backend, program.key)
    options = {**QPSOLVERS_SETTINGS.get(backend, {}), **options}
    if backend == "osqp":
        # OSQP's solve() warns (PendingDeprecationWarning) unless told whether to raise: failures
        # are read from the solution here, as in ``_osqp``.
        options = {"raise_error": False, **options}
    solution = qpsolvers.solve_problem(problem, solver=backend, initvals=workspaces.get(key), **options)
    if solution is None or not solution.found or solution.x is None:
        raise BackendFailure("no solution found")
    workspaces.put(key, np.array(solution.x))
    return Solved(np.array(solution.x), 0, "solved")


# The C library of this process, for fflush (the native solvers print through C's stdio).
_C_STDIO = ctypes.CDLL(None)


@contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Writes to stdout dropped while inside, the native ones to file descriptor 1 and CasADi's
    through ``sys.stdout``: qpOASES prints its licence banner whenever a solver object is made,
    whatever its ``printLevel`` (the option is applied after the constructor printed), and some
    messages at any print level. Not thread-safe (as the workspaces): another thread's output
    to stdout while inside is dropped too."""
    sys.stdout.flush()
    _C_STDIO.fflush(None)  # what C's stdout buffered before goes out, not to devnull
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            # CasADi's Python build sends its plugins' messages through sys.stdout, not fd 1.
            with redirect_stdout(devnull):
                yield
    finally:
        # C's stdout is buffered (fully, when not a terminal): flush what was written inside to
        # devnull before the descriptor is restored, or it would come out later.
        _C_STDIO.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)


@dataclass
class _CasadiEntry:
    """A casadi conic Function kept for one program structure, its sparsity patterns, and
    whether it has solved before (then the plugin's memory holds that solve: qpOASES hot-starts
    from its active set)."""

    function: Any
    hessian: Any
    constraints: Any
    used: bool = False


def _casadi_entry(program: Program, plugin: str, options: Mapping[str, Any]) -> _CasadiEntry:
    P, K = program.P, program.K
    hessian = casadi.Sparsity(P.shape[0], P.shape[1], P.indptr.tolist(), P.indices.tolist())
    constraints = casadi.Sparsity(K.shape[0], K.shape[1], K.indptr.tolist(), K.indices.tolist())
    plugin_options = {"error_on_fail": False, "print_time": False}
    plugin_options.update(CASADI_PLUGIN_OPTIONS.get(plugin, {}))
    plugin_options.update(options)
    with _quiet_stdout():
        function = casadi.conic("allocation", plugin, {"h": hessian, "a": constraints}, plugin_options)
    return _CasadiEntry(function, hessian, constraints)


def _casadi(program: Program, plugin: str, workspaces: Workspaces, options: Mapping[str, Any]) -> Solved:
    """Solve with a kept Function, which may start from the previous solve of its structure (a
    qpOASES hot start); if that fails, once more with a new Function, cold: a hot start from an
    unrelated program made qpOASES end in "premature homotopy termination" on programs that it
    solves from scratch, and the answer must not depend on earlier calls."""
    key = ("casadi", plugin, program.key)
    entry = workspaces.get(key)
    if entry is None:
        entry = _casadi_entry(program, plugin, options)
        workspaces.put(key, entry)
    solved, status = _casadi_solve(entry, program)
    if solved is None and entry.used:
        entry = _casadi_entry(program, plugin, options)
        workspaces.put(key, entry)
        solved, status = _casadi_solve(entry, program)
    entry.used = True
    if solved is None:
        raise BackendFailure(status)
    return solved


def _casadi_solve(entry: _CasadiEntry, program: Program) -> tuple[Solved | None, str]:
    """One call of ``entry``'s Function on ``program``: the solution, or None and the status."""
    P, K = program.P, program.K
    with _quiet_stdout():
        result = entry.function(
            h=casadi.DM(entry.hessian, P.data),
            g=program.q,
            a=casadi.DM(entry.constraints, K.data),
            lba=program.lower,
            uba=program.upper,
        )
    stats = entry.function.stats()
    status = str(stats.get("return_status", "failed" if not stats.get("success") else "solved"))
    if not stats.get("success", False):
        return None, status
    x = np.array(result["x"]).ravel()
    return Solved(x, int(stats.get("iter_count", 0) or 0), status), status
