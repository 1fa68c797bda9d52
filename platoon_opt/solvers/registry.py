"""Name -> allocator factory, so that scripts and the CLI pick allocators by name."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from platoon_opt.problem import Allocator

_FACTORIES: dict[str, Callable[..., Allocator]] = {}


def register(name: str) -> Callable[[Callable[..., Allocator]], Callable[..., Allocator]]:
    """Decorator: make ``get_allocator(name, **options)`` call the decorated factory."""

    def decorate(factory: Callable[..., Allocator]) -> Callable[..., Allocator]:
        if name in _FACTORIES:
            raise ValueError(f"allocator name {name!r} is already registered")
        _FACTORIES[name] = factory
        return factory

    return decorate


def get_allocator(name: str, **options: Any) -> Allocator:
    """The allocator registered as ``name``, built with ``options``.

    Raises:
        ValueError: unknown name (the message lists the known ones).
        TypeError: an option the allocator does not take.
    """
    try:
        factory = _FACTORIES[name]
    except KeyError:
        raise ValueError(f"unknown allocator {name!r}; known: {', '.join(available_allocators())}") from None
    return factory(**options)


def available_allocators() -> list[str]:
    """Registered allocator names, sorted."""
    return sorted(_FACTORIES)
