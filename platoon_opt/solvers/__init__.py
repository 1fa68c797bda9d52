"""Allocators: each turns a ``platoon_opt.AllocationProblem`` into a ``platoon_opt.Allocation``.

``get_allocator(name, **options)`` builds one by name; ``available_allocators()`` lists them.
Importing this package also lets scenario files name the CasADi-defined task kinds
(``symbolic_mean_variance``, ``symbolic_covariance``: ``platoon_opt.solvers.symbolic``).
"""

from platoon_opt.scenarios import register_task
from platoon_opt.solvers import convex, dual, iterative, nmpc  # noqa: F401  (registrations)
from platoon_opt.solvers.registry import available_allocators, get_allocator, register
from platoon_opt.solvers.symbolic import covariance_task, symbolic_mean_variance_task

register_task("symbolic_mean_variance", symbolic_mean_variance_task)
register_task("symbolic_covariance", covariance_task)

__all__ = ["available_allocators", "get_allocator", "register"]
