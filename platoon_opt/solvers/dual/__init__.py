"""The exact O(n) dual allocator."""

from platoon_opt.solvers.dual import allocator  # noqa: F401  (registration)
