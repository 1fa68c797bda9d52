"""``casadi-qp``: the polygon QPs of ``solvers.qp`` solved by a ``casadi.conic`` plugin shipped in
the casadi wheel, as a cross-check of OSQP and Clarabel.

The same is available as ``backend="casadi:<plugin>"`` of ``qp`` and ``qp-projection``; this name
only picks the reading. The default plugin, qpOASES, is an active-set method, so it shares no
code or algorithm with OSQP (ADMM) or Clarabel (interior point). It works on dense matrices:
use it on small platoons.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from platoon_opt.solvers.convex.allocator import (
    DEFAULT_ANCHOR_WEIGHT,
    DEFAULT_EPS,
    DEFAULT_RHO,
    ConvexAllocator,
)
from platoon_opt.solvers.registry import register

DEFAULT_PLUGIN = "qpoases"


@register("casadi-qp")
def make_casadi_qp(
    reading: str = "achievable-first",
    plugin: str = DEFAULT_PLUGIN,
    rho: float = DEFAULT_RHO,
    eps: float = DEFAULT_EPS,
    priority: str = "weighted",
    sides: int = 16,
    rate_aware: bool = False,
    fallbacks: tuple[str, ...] | None = None,
    solver_options: Mapping[str, Any] | None = None,
    precedence: str | None = None,
    anchor_weight: float = DEFAULT_ANCHOR_WEIGHT,
) -> ConvexAllocator:
    """The ``qp`` (reading "achievable-first") or ``qp-projection`` (reading "task-exact") program
    through ``casadi.conic(..., plugin)``.

    Defaults: achievable-first, plugin qpoases, rho = 1000, eps = 1e-4, 16 sides, the reading's
    precedence default; Clarabel on failure.
    ``solver_options`` are casadi conic options (plugin options nested as the plugin expects)."""
    return ConvexAllocator(
        label="casadi-qp",
        reading=reading,
        speed="polygon",
        rho=rho,
        eps=eps,
        priority=priority,
        sides=sides,
        rate_aware=rate_aware,
        backend=f"casadi:{plugin}",
        fallbacks=fallbacks,
        solver_options=solver_options,
        precedence=precedence,
        anchor_weight=anchor_weight,
    )
