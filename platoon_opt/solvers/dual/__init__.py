"""The exact O(n) dual allocator ``dual`` (docs/dual.md): one module per part, the allocator in
``allocator``."""

from platoon_opt.solvers.dual import allocator  # noqa: F401  (registration)
