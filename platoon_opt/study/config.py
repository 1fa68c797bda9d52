"""Allocator configurations as plain data, and the one parser of ``key=value`` text.

A configuration is a registry name and its options (``AllocatorConfig``); the command line's
``--solvers qp:rho=100,backend=osqp`` and ``--option rho=100`` go through ``parse_config`` and
``parse_options``. Values are Python literals where they parse (numbers, True, tuples), else
strings.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from platoon_opt.allocation import Allocator

AllocatorFactory = Callable[..., Allocator]


@dataclass(frozen=True)
class AllocatorConfig:
    """One allocator configuration as plain data.

    Attributes:
        name: the allocator's registry name (``solvers.get_allocator(name, **options)``).
        options: keyword options as sorted ``(key, value)`` pairs (JSON-serialisable values).
        label: the configuration's name in tables and file names, unique within a study
            ("m=4" for the paper's iteration, else the name and its options).
    """

    name: str
    options: tuple[tuple[str, Any], ...] = ()
    label: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("AllocatorConfig.name must be a registry name, got ''")
        object.__setattr__(self, "options", tuple(sorted(dict(self.options).items())))
        if not self.label:
            text = ",".join(f"{k}={v}" for k, v in self.options)
            object.__setattr__(self, "label", f"{self.name}:{text}" if text else self.name)

    @classmethod
    def make(cls, name: str, label: str = "", **options: Any) -> AllocatorConfig:
        """``AllocatorConfig.make("qp", backend="osqp")``."""
        return cls(name, tuple(options.items()), label)

    @property
    def iteration_count(self) -> int | None:
        """The paper's m for the iterative allocator, else None."""
        if self.name != "iterative":
            return None
        return int(dict(self.options).get("max_iterations", 4))

    def build(self, factory: AllocatorFactory) -> Allocator:
        """The allocator object, from ``factory(name, **options)``."""
        return factory(self.name, **dict(self.options))

    def as_dict(self) -> dict[str, Any]:
        """``{"name", "options", "label"}`` for JSON."""
        return {"name": self.name, "options": dict(self.options), "label": self.label}


def iterative_configs(iterations: Sequence[int]) -> list[AllocatorConfig]:
    """The paper's iteration for each m in ``iterations``, labelled "m=<m>"."""
    return [AllocatorConfig.make("iterative", f"m={m}", max_iterations=int(m)) for m in iterations]


# Longer texts are kept as text: Python's parser runs out of stack (MemoryError, RecursionError)
# on a few thousand nested operators ("-----...1"), and no option value is that long.
LITERAL_LENGTH = 1000


def parse_value(text: str) -> Any:
    """A Python literal where ``text`` is one (``100``, ``1e-4``, ``True``, ``(4, 1, 4, 1)``; also
    ``true`` and ``false``, as a scenario file writes them), else the text itself (``osqp``)."""
    if text in ("true", "false"):
        return text == "true"
    if len(text) > LITERAL_LENGTH:
        return text
    try:
        return ast.literal_eval(text)
    except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError):
        return text


def parse_options(pairs: Sequence[str], what: str = "--option") -> dict[str, Any]:
    """``["rho=100", "backend=osqp"]`` -> ``{"rho": 100, "backend": "osqp"}``.

    Raises:
        ValueError: a pair that is not ``name=value``, or a name given twice (the last would
            count and the first, perhaps a bad value, would go unchecked); the message names
            ``what``.
    """
    options: dict[str, Any] = {}
    given: dict[str, str] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"{what} must look like name=value, got {pair!r}")
        if key in given:
            raise ValueError(f"{what}: option {key} must be given once, got {given[key]!r} and {pair!r}")
        given[key] = pair
        options[key] = parse_value(text)
    return options


def parse_config(text: str) -> AllocatorConfig:
    """``"qp"``, ``"qp:backend=osqp,rho=100"`` or ``"m=3"`` (the paper's iteration) as a config.

    Raises:
        ValueError: malformed text.
    """
    match = re.fullmatch(r"m=(\d+)", text)
    if match:
        return iterative_configs([int(match.group(1))])[0]
    name, colon, rest = text.partition(":")
    # Commas inside brackets belong to a value: "nmpc:task_weights=(4,1,4,1),intervals=20".
    pairs = re.split(r",(?![^([]*[)\]])", rest) if colon else []
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", name) or not all(pairs):
        raise ValueError(f"solver must look like NAME or NAME:key=value,..., got {text!r}")
    return AllocatorConfig(name, tuple(parse_options(pairs, f"an option of {text!r}").items()))


def default_configs(available: Sequence[str], iterations: Sequence[int] = range(9)) -> list[AllocatorConfig]:
    """The paper's iteration for every m in ``iterations`` (m = 0 first: the baseline), then
    every other registered allocator with its default options, in name order."""
    return iterative_configs(iterations) + [
        AllocatorConfig(name) for name in available if name != "iterative"
    ]
