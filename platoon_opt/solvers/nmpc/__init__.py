"""The receding-horizon allocator."""

from platoon_opt.solvers.nmpc import allocator  # noqa: F401  (registration)
