"""The registered allocators and their options, in words: ``platoon-opt allocators`` prints it and
``docs/allocators.md`` is it (``platoon-opt allocators --markdown``), read from the options'
declarations (``platoon_opt.solvers.options``), so that listing, validation and docs cannot
disagree."""

from __future__ import annotations

from typing import Any

from platoon_opt.solvers.registry import available_allocators, registered


def _value(value: Any) -> str:
    return "None" if value is None else repr(value)


def _cell(text: str) -> str:
    """``text`` as a markdown table cell (a bare | would end the cell)."""
    return text.replace("|", "\\|")


def describe(name: str) -> str:
    """One allocator as plain text: what it solves, when to use it, and every option with its
    default, what it must be and its meaning."""
    entry = registered(name)
    lines = [f"{name}: {entry.summary}", f"  use: {entry.use}", "  options:"]
    width = max((len(option.name) for option in entry.options), default=0)
    for option in entry.options:
        must = f"default {_value(option.default)}; {option.rule.must}"
        lines.append(f"    {option.name:<{width}}  {must}. {option.meaning}")
    return "\n".join(lines)


def summary() -> str:
    """Every allocator, one line each."""
    names = available_allocators()
    width = max(len(name) for name in names)
    return "\n".join(f"{name:<{width}}  {registered(name).summary}" for name in names)


def markdown() -> str:
    """``docs/allocators.md``: a table of the allocators, then each one's options."""
    lines = [
        "# Allocators and their options",
        "",
        "Generated from the options' declarations by `platoon-opt allocators --markdown`; a test keeps",
        "this page equal to that output. `platoon-opt allocators NAME` prints one allocator's options,",
        "and a configuration names them as `NAME:key=value,...` (`--solvers`) or `--option key=value`.",
        "",
        "| allocator | what it solves | when to use it |",
        "|---|---|---|",
    ]
    for name in available_allocators():
        entry = registered(name)
        lines.append(f"| `{name}` | {_cell(entry.summary)} | {_cell(entry.use)} |")
    for name in available_allocators():
        lines += ["", f"## `{name}`", "", "| option | default | must be | meaning |", "|---|---|---|---|"]
        for option in registered(name).options:
            must, meaning = _cell(option.rule.must), _cell(option.meaning)
            lines.append(f"| `{option.name}` | `{_value(option.default)}` | {must} | {meaning} |")
    return "\n".join(lines) + "\n"
