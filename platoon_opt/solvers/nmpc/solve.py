"""The receding horizon's solves: Gauss-Newton SQP (``sqp``) and IPOPT (``ipopt``).

Both take the horizon of the problem's structure, a start U (N, n, 2) within the input bounds
(N, n, 2) and the residual parameters p, and return a ``HorizonSolution``; neither raises on
a failed solve (its status starts with "failed"). The SQP is docs/nmpc.md, section 4; the
NLP, section 5.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.nmpc.box_qp import BlockLowRank, BoxSolution, active_set_newton, projected_newton
from platoon_opt.solvers.nmpc.compiled import Horizon
from platoon_opt.solvers.nmpc.interior import interior_point, lifted_clarabel
from platoon_opt.solvers.nmpc.linearization import Linearization

# Levenberg-Marquardt term on the Gauss-Newton Hessian: keeps it positive definite when a
# smoothness weight is 0.
_DAMPING = 1e-8
_IPOPT_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
# From this many inputs on (on the split) the interior point solves the SQP's QP before the
# active-set exchange is tried: its cost does not grow with how far the coupling rows make the
# Hessian from an M-matrix, where the exchange's cycles and restarts do (docs/nmpc.md, 4.3).
INTERIOR_FIRST_FROM = 2000


class HorizonSolution(NamedTuple):
    """One solve of the horizon.

    Attributes:
        inputs: U (N, n, 2): each unit's speed (m/s, signed) over interval k and steering
            angle (rad) at its end.
        states: Z (N, n, 4): the node states x, y (m), theta, alpha (rad) at the end of each
            interval (the SQP's simulated from U; IPOPT's its variables, the gaps closed to
            its tolerance).
        status: "converged", "max_iterations", "stalled" (SQP), "optimal", "acceptable"
            (IPOPT), or "failed:<why>".
        iterations: SQP or IPOPT iterations.
        cost: the least-squares cost 1/2 ||r||^2 at the solution (docs/nmpc.md, Eq. 1.1).
    """

    inputs: np.ndarray
    states: np.ndarray
    status: str
    iterations: int
    cost: float


def sqp(
    problem: AllocationProblem,
    horizon: Horizon,
    U: np.ndarray,
    p: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    max_iterations: int,
    step_tolerance: float,
) -> HorizonSolution:
    """Gauss-Newton SQP in the inputs U (N, n, 2) within bounds (N, n, 2), the node states
    simulated from them (docs/nmpc.md, section 4): at most ``max_iterations`` iterations,
    converged when no input step exceeds ``step_tolerance`` of its range."""
    N, n, limits = horizon.N, problem.n, problem.limits
    z0 = _state_array(problem)
    scale = np.array([limits.max_speed, limits.max_steering])
    # The clearance rows of the pairs that can meet within the bounds.
    speed = float(np.max(np.abs([low[..., 0], high[..., 0]])))
    pairs = horizon.clearance.near(z0[:, :2], speed) if horizon.clearance else None

    def simulate(inputs: np.ndarray) -> tuple[np.ndarray, float]:
        (states,) = horizon.rollout(z0.T, _to_columns(inputs))
        states = _from_columns(states.reshape(4, -1, order="F"), N, n)
        (residual,) = horizon.residual(_to_columns(states), _to_columns(inputs), p)
        if pairs is not None:
            residual = np.concatenate((residual, pairs.residual(states)))
        return states, 0.5 * float(residual @ residual)

    Z, cost, guess = *simulate(U), None
    for iteration in range(1, max_iterations + 1):
        starts = np.concatenate((z0[None], Z[:-1]))
        _, A, B = horizon.shoot_jacobian(_to_columns(starts), _to_columns(U))
        # Column-major (4, 4 N n) and (4, 2 N n): block k n + i holds unit i's interval k.
        A = A.reshape(4, 4, n, N, order="F").transpose(3, 2, 0, 1)
        B = B.reshape(4, 2, n, N, order="F").transpose(3, 2, 0, 1)
        # Sensitivities of the simulated states, unit by unit: dZ_{k+1} = A_k dZ_k + B_k dU_k
        # with dZ_0 = 0, so dZ_{k+1} = sum_j G[k, j] dU_j (docs/nmpc.md, Eq. 4.1).
        G = np.zeros((N, N, n, 4, 2))
        G[0, 0] = B[0]
        for k in range(1, N):
            G[k, :k] = A[k][None] @ G[k - 1, :k]
            G[k, k] = B[k]
        residual, z_values, u_values = horizon.residual_jacobian(_to_columns(Z), _to_columns(U), p)
        linearization = horizon.chain(residual, z_values, u_values, G)
        if pairs is not None:
            linearization = linearization.with_coupling(*pairs.linearization(Z, G))
        # The step in the chain's unit-major order, (n, N, 2).
        step_low, step_high = (low - U).transpose(1, 0, 2).ravel(), (high - U).transpose(1, 0, 2).ravel()
        gradient = linearization.gradient()
        x, why, guess = _step(horizon, linearization, gradient, step_low, step_high, U, guess)
        if x is None:
            return HorizonSolution(U, Z, f"failed:qp {why}".rstrip(), iteration, cost)
        step = x.reshape(n, N, 2).transpose(1, 0, 2)
        # Backtrack on the cost of the simulated trajectory (Armijo, against the decrease the
        # Gauss-Newton model predicts): full steps oscillate between the bounds when many
        # inputs saturate, as in a cold start.
        predicted = float(gradient @ x + 0.5 * (np.sum(linearization.product(x) ** 2) + _DAMPING * x @ x))
        fraction = 1.0
        for _ in range(8):
            trial = np.clip(U + fraction * step, low, high)
            trial_states, trial_cost = simulate(trial)
            if trial_cost <= cost + 1e-4 * fraction * predicted:
                break
            fraction /= 2
        else:
            return HorizonSolution(U, Z, "stalled", iteration, cost)
        U, Z, cost = trial, trial_states, trial_cost
        if fraction * np.max(np.abs(step) / scale) <= step_tolerance:
            return HorizonSolution(U, Z, "converged", iteration, cost)
    return HorizonSolution(U, Z, "max_iterations", max_iterations, cost)


def _step(
    horizon: Horizon,
    linearization: Linearization,
    gradient: np.ndarray,
    step_low: np.ndarray,
    step_high: np.ndarray,
    U: np.ndarray,
    guess: BoxSolution | None,
) -> tuple[np.ndarray | None, str, BoxSolution | None]:
    """The Gauss-Newton step x ((2 N n,), the chain's unit-major order) within the bounds (and
    the rate rows), or None and why; and the active sets for the next iteration's guess.

    With box constraints alone: the active-set Newton method on the Hessian split into one
    block per unit and the coupling rows (from ``guess``, the previous iteration's sets); if
    it does not end, DAQP on the dense Hessian and then projected Newton from the method's best
    point. Above ``box_qp.DENSE_UP_TO`` inputs (the split) the interior point of
    ``interior.interior_point`` comes first from ``INTERIOR_FIRST_FROM`` inputs on and after the
    active-set method below that, then the other of the two, then Clarabel on the lifted QP.
    With rate rows: DAQP alone, and its failure is the step's (docs/nmpc.md, section 4.3).
    """
    blocks = linearization.blocks()
    diagonal = np.arange(linearization.block)
    blocks[:, diagonal, diagonal] += _DAMPING
    split = BlockLowRank(blocks, linearization.coupling)
    if not horizon.rate_rows and split.is_split:
        # Not DAQP: it works on the dense QP, its iterations growing with the bounds it holds
        # (at n = 50 it ran out of them on every QP it was given, 0.8 s each; at n = 200 it ran
        # for minutes: docs/nmpc.md, section 4.3).
        def exchange() -> BoxSolution | None:
            solution = active_set_newton(split, gradient, step_low, step_high, guess)
            return solution if solution.x is not None else None

        def interior() -> BoxSolution | None:
            return interior_point(split, gradient, step_low, step_high)

        first, second = (interior, exchange) if split.size >= INTERIOR_FIRST_FROM else (exchange, interior)
        for solver in (first, second, lambda: lifted_clarabel(split, gradient, step_low, step_high)):
            if (solution := solver()) is not None:
                return solution.x, "", solution
        return None, "active set, interior point and clarabel", guess
    if not horizon.rate_rows:
        guess = active_set_newton(split, gradient, step_low, step_high, guess)
        if guess.x is not None:
            return guess.x, "", guess
    hessian = split.dense()
    rows = _rate_rows(U, horizon.rate_bound) if horizon.rate_rows else (np.zeros(0),) * 3
    # The horizon of an allocator with backend "sqp" has DAQP's QP (``horizon_for``).
    qp = horizon.qp
    if qp is None:
        raise ValueError(
            "the SQP step needs DAQP's QP: a horizon built for backend 'sqp', dense or with rate rows"
        )
    # DAQP's x, else (box constraints alone) projected Newton's; None if no solver answers. A
    # failed DAQP's x is not a step: DAQP leaves its output as the previous QP left it, which may
    # be another solve's, of another allocator (the horizon is shared).
    x: np.ndarray | None
    x, *_ = qp(hessian, gradient, *rows, step_low, step_high)
    stats = qp.stats()
    if stats.get("success", False) and np.all(np.isfinite(x)):
        return x, "", guess
    why = _daqp_failure(stats, finite=bool(np.all(np.isfinite(x))))
    if horizon.rate_rows:
        # Projected Newton keeps box constraints alone, not the rate rows.
        return None, why, guess
    x = projected_newton(split, gradient, step_low, step_high, start=guess.start if guess else None)
    return x, "" if x is not None else why, guess


# DAQP's exit flags (its constants.h) that are failures.
_DAQP_EXITS = {-1: "infeasible", -2: "cycling", -3: "unbounded", -4: "iteration limit"}


def _daqp_failure(stats: dict[str, object], finite: bool) -> str:
    """Why DAQP's answer is not a step, from its stats: its exit flag and what it means, or a
    non-finite x reported as a success."""
    status = stats.get("return_status", "")
    if stats.get("success", False) and not finite:
        return "daqp non-finite step"
    meaning = _DAQP_EXITS.get(status) if isinstance(status, int) else None
    return f"daqp {status} {meaning}" if meaning else f"daqp {status}".rstrip()


def _rate_rows(U: np.ndarray, rate_bound: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows D dU in [lower, upper] keeping |a_{k+1} - a_k| <= rate_bound (k = 0..N-2); the
    columns of dU unit-major, as the chain's."""
    N, n = U.shape[:2]
    difference = np.zeros((N - 1, n, n, N, 2))
    for i in range(n):
        difference[:, i, i, 1:, 1] += np.eye(N - 1)
        difference[:, i, i, :-1, 1] -= np.eye(N - 1)
    change = U[1:, :, 1] - U[:-1, :, 1]
    return (
        difference.reshape(-1, 2 * N * n),
        (-rate_bound - change).reshape(-1),
        (rate_bound - change).reshape(-1),
    )


def ipopt(
    problem: AllocationProblem,
    horizon: Horizon,
    U: np.ndarray,
    p: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
) -> HorizonSolution:
    """IPOPT on the multiple-shooting NLP (docs/nmpc.md, section 5), from U and its simulated
    states; its iteration cap is the horizon's."""
    # The horizon of an allocator with backend "ipopt" has the NLP (``horizon_for``).
    nlp = horizon.nlp
    if nlp is None:
        raise ValueError("the IPOPT solve needs the NLP: a horizon built for backend 'ipopt'")
    N, n, limits = horizon.N, problem.n, problem.limits
    (states,) = horizon.rollout(_state_array(problem).T, _to_columns(U))
    Z = _from_columns(states.reshape(4, -1, order="F"), N, n)
    z_low = np.broadcast_to([-np.inf, -np.inf, -np.inf, -limits.max_steering], (N, n, 4))
    z_high = np.broadcast_to([np.inf, np.inf, np.inf, limits.max_steering], (N, n, 4))
    rate_bound = horizon.rate_bound
    n_rates = n * (N - 1) if horizon.rate_rows else 0
    result = nlp(
        x0=np.concatenate((_to_columns(U).reshape(-1, order="F"), _to_columns(Z).reshape(-1, order="F"))),
        p=np.concatenate((_state_array(problem).reshape(-1), p)),
        lbx=np.concatenate(
            (_to_columns(low).reshape(-1, order="F"), _to_columns(z_low).reshape(-1, order="F"))
        ),
        ubx=np.concatenate(
            (_to_columns(high).reshape(-1, order="F"), _to_columns(z_high).reshape(-1, order="F"))
        ),
        lbg=np.concatenate((np.zeros(4 * n * N), np.full(n_rates, -rate_bound))),
        ubg=np.concatenate((np.zeros(4 * n * N), np.full(n_rates, rate_bound))),
    )
    stats = nlp.stats()
    status, iterations = stats.get("return_status", "unknown"), int(stats.get("iter_count", 0))
    x = np.asarray(result["x"]).reshape(-1)
    split = 2 * n * N
    U = _from_columns(x[:split].reshape(2, -1, order="F"), N, n)
    Z = _from_columns(x[split:].reshape(4, -1, order="F"), N, n)
    cost = float(result["f"])
    if status not in _IPOPT_SUCCESS:
        return HorizonSolution(U, Z, f"failed:{status}", iterations, cost)
    return HorizonSolution(U, Z, "optimal" if status == "Solve_Succeeded" else "acceptable", iterations, cost)


def _state_array(problem: AllocationProblem) -> np.ndarray:
    """The current unit states (n, 4): x, y, theta, alpha."""
    state = problem.state
    return np.column_stack((state.x, state.y, state.theta, state.alpha))


def _to_columns(array: np.ndarray) -> np.ndarray:
    """(N, n, c) -> (c, N n), column k n + i: the horizon's layout."""
    N, n, c = array.shape
    return array.reshape(N * n, c).T


def _from_columns(columns: np.ndarray, N: int, n: int) -> np.ndarray:
    """(c, N n) -> (N, n, c)."""
    return np.asarray(columns).T.reshape(N, n, -1)
