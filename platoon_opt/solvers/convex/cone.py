"""The convex allocators with the exact speed cone ``||v_i|| <= v_max`` (Clarabel's
``SecondOrderConeT``) instead of the inscribed polygon: ``cone`` (achievable-first) and
``cone-projection`` (task-exact). Same formulation, precedence rule and fallbacks as
``solvers.qp``; a fallback backend without cones (OSQP by default) solves the polygon program,
an inner approximation, so its answer is still achievable.
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


@register("cone")
def make_cone(
    rho: float = DEFAULT_RHO,
    priority: str = "weighted",
    rate_aware: bool = False,
    fallbacks: tuple[str, ...] | None = None,
    solver_options: Mapping[str, Any] | None = None,
    precedence: str | None = None,
    anchor_weight: float = DEFAULT_ANCHOR_WEIGHT,
) -> ConvexAllocator:
    """Achievable-first SOCP, ``min ||q' - q'_d||^2 + rho ||J q' - u||^2`` over the exact sectors.

    Defaults: rho = 1000, priority "weighted"; Clarabel, then OSQP on the 16-gon; flagged units
    pinned. Options: see ``solvers.qp.ConvexAllocator``."""
    return ConvexAllocator(
        label="cone",
        reading="achievable-first",
        speed="cone",
        rho=rho,
        priority=priority,
        rate_aware=rate_aware,
        backend="clarabel",
        fallbacks=fallbacks,
        solver_options=solver_options,
        precedence=precedence,
        anchor_weight=anchor_weight,
    )


@register("cone-projection")
def make_cone_projection(
    eps: float = DEFAULT_EPS,
    rate_aware: bool = False,
    fallbacks: tuple[str, ...] | None = None,
    solver_options: Mapping[str, Any] | None = None,
    precedence: str | None = None,
    anchor_weight: float = DEFAULT_ANCHOR_WEIGHT,
) -> ConvexAllocator:
    """Task-exact SOCP, ``min ||a - c||^2 + eps ||a - q'_d||^2`` s.t. ``J a = u``, ``c_i`` in the exact
    sectors: the exact limit of the paper's iteration (``gears="model"``) as m grows.

    Defaults: eps = 1e-4; Clarabel, then OSQP on the 16-gon; flagged units anchored with weight 1.
    Options: see ``solvers.qp.ConvexAllocator``."""
    return ConvexAllocator(
        label="cone-projection",
        reading="task-exact",
        speed="cone",
        eps=eps,
        rate_aware=rate_aware,
        backend="clarabel",
        fallbacks=fallbacks,
        solver_options=solver_options,
        precedence=precedence,
        anchor_weight=anchor_weight,
    )
