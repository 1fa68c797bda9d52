"""Allocator options, declared once: as fields of the allocator's dataclass.

An ``Option`` names one option, its default, its meaning and a ``Rule`` (what a value must be).
``Option.field()`` makes it a dataclass field; ``options_of(cls)`` reads them back in field
order; ``check_options(instance, allocator)`` validates and normalises them in ``__post_init__``.
The registry (``platoon_opt.solvers.registry``), the command line's listing and the options
table of ``docs/allocators.md`` all read these declarations.

A value that breaks its rule raises ``OptionError`` with one line:
``option rho of qp must be a number > 0, got -1``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from platoon_opt.errors import OptionError


class Rule:
    """What a value must be: ``must`` says it in words (for listings and docs), ``accept`` returns
    the value normalised or raises ``ValueError`` with what it must be (for the error message:
    ``must`` unless the rule has more to say, as a ``Choice`` of installed backends)."""

    must: str

    def accept(self, value: Any) -> Any:
        raise NotImplementedError


def _is_number(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, numbers.Real) and math.isfinite(value)


@dataclass(frozen=True)
class Number(Rule):
    """A finite number, optionally ``> above`` or ``>= at_least``, and ``<= at_most``."""

    above: float | None = None
    at_least: float | None = None
    at_most: float | None = None

    @property
    def must(self) -> str:  # type: ignore[override]
        if self.above is not None:
            text = f"a number > {self.above:g}"
        elif self.at_least is not None:
            text = f"a number >= {self.at_least:g}"
        else:
            text = "a finite number"
        return text if self.at_most is None else f"{text} and <= {self.at_most:g}"

    def accept(self, value: Any) -> float:
        if not _is_number(value):
            raise ValueError(self.must)
        if (
            (self.above is not None and not value > self.above)
            or (self.at_least is not None and not value >= self.at_least)
            or (self.at_most is not None and not value <= self.at_most)
        ):
            raise ValueError(self.must)
        return value


@dataclass(frozen=True)
class Integer(Rule):
    """An integer ``>= at_least``."""

    at_least: int = 0

    @property
    def must(self) -> str:  # type: ignore[override]
        return f"an integer >= {self.at_least}"

    def accept(self, value: Any) -> int:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < self.at_least:
            raise ValueError(self.must)
        return int(value)


@dataclass(frozen=True)
class Flag(Rule):
    """True or False."""

    must = "True or False"

    def accept(self, value: Any) -> bool:
        if not isinstance(value, bool):
            raise ValueError(self.must)
        return value


@dataclass(frozen=True)
class Choice(Rule):
    """One of ``values`` (a tuple, or a function returning one, for choices known only at run
    time, such as the installed backends; ``described`` then says what they are in words)."""

    values: tuple[str, ...] | Callable[[], Sequence[str]]
    described: str = ""

    def choices(self) -> tuple[str, ...]:
        return tuple(self.values() if callable(self.values) else self.values)

    def _listed(self) -> str:
        return "one of " + ", ".join(repr(value) for value in self.choices())

    @property
    def must(self) -> str:  # type: ignore[override]
        return self.described or self._listed()

    def accept(self, value: Any) -> str:
        if not isinstance(value, str) or value not in self.choices():
            raise ValueError(self._listed())
        return value


@dataclass(frozen=True)
class Choices(Rule):
    """A tuple of names from ``of`` (a single name counts as a tuple of one)."""

    of: Choice

    @property
    def must(self) -> str:  # type: ignore[override]
        return f"a tuple of names, each {self.of.must}"

    def accept(self, value: Any) -> tuple[str, ...]:
        names = (value,) if isinstance(value, str) else value
        if not isinstance(names, (tuple, list)) or not all(
            isinstance(name, str) and name in self.of.choices() for name in names
        ):
            raise ValueError(f"a tuple of names, each {self.of._listed()}")
        return tuple(names)


@dataclass(frozen=True)
class Numbers(Rule):
    """A non-empty tuple of finite numbers, each ``>= at_least``."""

    at_least: float | None = None

    @property
    def must(self) -> str:  # type: ignore[override]
        bound = "" if self.at_least is None else f" >= {self.at_least:g}"
        return f"a tuple of numbers{bound}"

    def accept(self, value: Any) -> tuple[float, ...]:
        if not isinstance(value, (tuple, list)) or not value or not all(_is_number(v) for v in value):
            raise ValueError(self.must)
        if self.at_least is not None and any(v < self.at_least for v in value):
            raise ValueError(self.must)
        return tuple(float(v) for v in value)


@dataclass(frozen=True)
class Table(Rule):
    """A mapping of setting names to values (passed on to a solver)."""

    must = "a mapping of settings"

    def accept(self, value: Any) -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            raise ValueError(self.must)
        return value


@dataclass(frozen=True)
class Option:
    """One allocator option.

    Attributes:
        name: the option's name, which is its dataclass field's name.
        default: its value when not given; None may stand for a default that depends on other
            options (``meaning`` says which).
        meaning: one line, with units.
        rule: what a value must be; None is accepted only where the default is None.
    """

    name: str
    default: Any
    meaning: str
    rule: Rule

    def field(self, **extra: Any) -> Any:
        """This option as a dataclass field (``rho: float = RHO.field()``); ``extra`` goes to
        ``dataclasses.field``."""
        return dataclasses.field(default=self.default, metadata={"option": self}, **extra)

    def check(self, allocator: str, value: Any) -> Any:
        """``value`` normalised, or ``OptionError`` naming the allocator, the option, what it must be
        and the value."""
        if value is None and self.default is None:
            return None
        try:
            return self.rule.accept(value)
        except (TypeError, ValueError) as error:
            also = " or None" if self.default is None else ""
            raise OptionError(
                f"option {self.name} of {allocator} must be {error}{also}, got {value!r}"
            ) from None


def options_of(cls: type) -> tuple[Option, ...]:
    """The options declared as fields of dataclass ``cls``: its own in field order, then those it
    inherits (the shared safety options, ``solvers.safety.SafetyOptions``), so that listings
    start with what is particular to the allocator."""
    own: list[Option] = []
    inherited: list[Option] = []
    for item in dataclasses.fields(cls):
        option = item.metadata.get("option")
        if option is not None:
            if option.name != item.name:
                raise TypeError(f"{cls.__name__}.{item.name} declares option {option.name!r}")
            (own if item.name in cls.__dict__.get("__annotations__", {}) else inherited).append(option)
    return (*own, *inherited)


def check_options(instance: Any, allocator: str) -> None:
    """Validate and normalise every option field of a frozen dataclass instance in place."""
    for option in options_of(type(instance)):
        object.__setattr__(instance, option.name, option.check(allocator, getattr(instance, option.name)))
