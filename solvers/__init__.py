"""Allocators: each turns a ``platoon_opt.AllocationProblem`` into a ``platoon_opt.Allocation``.

``get_allocator(name, **options)`` builds one by name; ``available_allocators()`` lists them.
Every module of this package is imported here, so a module registers its allocators with
``@register(name)`` and needs no other wiring.
"""

import importlib
import pkgutil

from solvers.registry import available_allocators, get_allocator, register

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

__all__ = ["available_allocators", "get_allocator", "register"]
