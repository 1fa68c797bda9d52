"""The convex allocators: one convex program per step, solved by a QP/SOCP backend."""

from platoon_opt.solvers.convex import allocator, casadi_qp, cone  # noqa: F401  (registrations)
