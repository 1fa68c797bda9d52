"""The convex allocators: one convex program per step (``formulation``), solved by a QP or SOCP
backend (``backends``) with fallbacks (``allocator``). The five names are one class
(``ConvexAllocator``) with the reading and the speed model fixed per name:

* ``qp``, ``cone``: achievable-first, the speed disk as the inscribed 16-gon or exact;
* ``qp-projection``, ``cone-projection``: task-exact, the exact limit of the paper's iteration;
* ``casadi-qp``: the polygon programs through a ``casadi.conic`` plugin (qpOASES by default, an
  active-set method that shares no code or algorithm with OSQP or Clarabel), a cross-check.
"""

from platoon_opt.solvers.convex.allocator import ConvexAllocator
from platoon_opt.solvers.registry import register

register(
    "qp",
    ConvexAllocator,
    summary="achievable-first QP: min ||v - q'_d||^2 + rho ||J v - u||^2 over the inscribed polygons",
    use="velocities every unit can drive, the task kept as well as the limits allow",
    fixed={"label": "qp", "reading": "achievable-first", "speed": "polygon"},
    hidden=("eps",),
)
register(
    "qp-projection",
    ConvexAllocator,
    summary="task-exact QP: min ||a - c||^2 + eps ||a - q'_d||^2, J a = u, c in the polygons",
    use="the exact limit of the paper's iteration; tracks best in closed loop",
    fixed={"label": "qp-projection", "reading": "task-exact", "speed": "polygon"},
    hidden=("rho", "priority"),
)
register(
    "cone",
    ConvexAllocator,
    summary="qp with the exact speed disk (second-order cone, Clarabel, or the dual)",
    use="as qp, without the polygon's 2 % loss of speed",
    fixed={"label": "cone", "reading": "achievable-first", "speed": "cone"},
    hidden=("eps", "sides"),
)
register(
    "cone-projection",
    ConvexAllocator,
    summary="qp-projection with the exact speed disk (second-order cone, Clarabel, or the dual)",
    use="as qp-projection, without the polygon's 2 % loss of speed",
    fixed={"label": "cone-projection", "reading": "task-exact", "speed": "cone"},
    hidden=("rho", "priority", "sides"),
)
register(
    "casadi-qp",
    ConvexAllocator,
    summary="the qp or qp-projection program through a casadi.conic plugin",
    use="an independent cross-check of the QP backends (dense: small platoons)",
    fixed={"label": "casadi-qp", "speed": "polygon"},
    defaults={"backend": "casadi:qpoases"},
)

__all__ = ["ConvexAllocator"]
