"""Allocators by name: what each solves, when to use it, and its options.

``register`` records an allocator class under a name, with options fixed by that name (``qp``
and ``cone`` are one class with two speed models), options that do not apply to it, and defaults
changed for it; the options a user may set are the class's declared options
(``platoon_opt.solvers.options``) less the fixed and the hidden ones. ``get_allocator(name,
**options)`` checks the names, builds the allocator (which checks the values) and reports any
bad input as ``OptionError``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from platoon_opt.allocation import Allocation, Allocator
from platoon_opt.errors import OptionError
from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.options import Option, options_of


@runtime_checkable
class PromisingAllocator(Allocator, Protocol):
    """An allocator that states what it guarantees about its answers, for the property tests and
    the soak."""

    @property
    def promise(self) -> str:
        """In words: which velocities it keeps inside which achievable set."""
        ...

    def promised_excess(self, problem: AllocationProblem, allocation: Allocation) -> float | None:
        """How far (m/s) the farthest velocity it promises to keep achievable lies outside its set
        (0 inside), or None if it promises nothing for this allocation."""
        ...


@dataclass(frozen=True)
class Registered:
    """An allocator name.

    Attributes:
        name: the name (``get_allocator(name)``).
        cls: the allocator class, a dataclass whose fields declare its options.
        summary: what it solves, one line.
        use: when to use it, one line.
        fixed: options this name sets and a user may not.
        hidden: options that do not apply to this name (they keep their defaults).
        defaults: options whose default this name changes.
    """

    name: str
    cls: type
    summary: str
    use: str
    fixed: Mapping[str, Any] = field(default_factory=dict)
    hidden: tuple[str, ...] = ()
    defaults: Mapping[str, Any] = field(default_factory=dict)

    @property
    def options(self) -> tuple[Option, ...]:
        """The options a user may set, with this name's defaults."""
        return tuple(
            dataclasses.replace(option, default=self.defaults.get(option.name, option.default))
            for option in options_of(self.cls)
            if option.name not in self.fixed and option.name not in self.hidden
        )

    def build(self, **options: Any) -> PromisingAllocator:
        """The allocator with ``options``; ``OptionError`` for an unknown option or a bad value."""
        valid = [option.name for option in self.options]
        for key in options:
            if key not in valid:
                raise OptionError(f"unknown option {key!r} for {self.name}; valid: {', '.join(valid)}")
        try:
            return self.cls(**{**self.defaults, **options, **self.fixed})
        except OptionError:
            raise
        except (TypeError, ValueError) as error:
            raise OptionError(f"{self.name}: {error}") from None


_REGISTRY: dict[str, Registered] = {}


def register(
    name: str,
    cls: type,
    *,
    summary: str,
    use: str,
    fixed: Mapping[str, Any] | None = None,
    hidden: tuple[str, ...] = (),
    defaults: Mapping[str, Any] | None = None,
) -> None:
    """Make ``get_allocator(name, **options)`` build ``cls`` (see ``Registered``)."""
    if name in _REGISTRY:
        raise ValueError(f"allocator name {name!r} is already registered")
    _REGISTRY[name] = Registered(name, cls, summary, use, dict(fixed or {}), hidden, dict(defaults or {}))


def registered(name: str) -> Registered:
    """The registration of ``name``; ``OptionError`` listing the known names if there is none."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise OptionError(f"unknown allocator {name!r}; known: {', '.join(available_allocators())}") from None


def get_allocator(name: str, **options: Any) -> PromisingAllocator:
    """The allocator registered as ``name``, built with ``options``.

    Raises:
        OptionError: an unknown name or option, or a bad value (one line naming them).
    """
    return registered(name).build(**options)


def available_allocators() -> list[str]:
    """Registered allocator names, sorted."""
    return sorted(_REGISTRY)
