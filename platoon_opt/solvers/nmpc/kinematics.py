"""The exact kinematics of one interval of the horizon in CasADi symbols (docs/nmpc.md, Eq. 1.6).

``interval_states`` moves units through the interval's simulation steps; the shooting
(``compiled.unit_interval``) keeps the last state, and the task rows between the nodes
(``residuals``, Eq. 2.1) the positions on the way. Its arithmetic is elementwise, so the same
function moves one unit (scalars) or all of them at once (columns).
"""

from __future__ import annotations

from typing import Any

import casadi as ca

State = tuple[Any, Any, Any, Any]


def interval_states(
    state: State, speed: Any, end_angle: Any, substeps: int, dt: float, length: float, reach: float | None
) -> list[State]:
    """(x, y, theta, alpha) after each of ``substeps`` steps of ``dt`` s from ``state`` at the
    signed ``speed`` (m/s), the steering moving toward ``end_angle`` (rad) linearly (``reach``
    None) or by at most ``reach`` rad a step (the rate limit), then held; ``length`` is the
    unit's (m). Positions are the tips' (m), angles in rad.

    Each step mirrors ``step_vehicles``: the steering moves first, then the tip follows the arc of
    constant speed and steering; the chord's ``sin(c)/c`` is its Taylor series (the turn per step
    is at most v_max dt / d, 0.04 rad at the paper's values: error < 1e-16).
    """
    x, y, theta, start_angle = state
    alpha, change = start_angle, end_angle - start_angle
    states = []
    for j in range(1, substeps + 1):
        if reach is None:
            alpha = alpha + change / substeps
        elif j < substeps:
            alpha = start_angle + ca.fmin(ca.fmax(change, -j * reach), j * reach)
        else:
            # The rate rows (1.5) bound the change by the interval's reach, so a clip here
            # would only add a kink at that bound, where IPOPT's line search then stalls.
            alpha = start_angle + change
        turn = speed / length * ca.sin(alpha) * dt
        half = turn / 2
        chord = speed * dt * (1 - half**2 / 6 + half**4 / 120)
        direction = theta + alpha + half
        x = x + chord * ca.cos(direction)
        y = y + chord * ca.sin(direction)
        theta = theta + turn
        states.append((x, y, theta, alpha))
    return states
