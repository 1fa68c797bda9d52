"""Allocators: each turns a ``platoon_opt.AllocationProblem`` into a ``platoon_opt.Allocation``.

``get_allocator(name, **options)`` builds one by name; ``available_allocators()`` lists them.
"""

from platoon_opt.solvers import convex, dual, iterative, nmpc  # noqa: F401  (registrations)
from platoon_opt.solvers.registry import available_allocators, get_allocator, register

__all__ = ["available_allocators", "get_allocator", "register"]
