"""The fuzzer's argument lists (``platoon_opt.study.fuzz``): ``simulate`` and ``compare`` with
random flags, values of every type and sign, missing values, unknown flags, and ``--option`` and
``--solvers`` strings of every kind for every allocator.

A generated list says what it must do: ``must_fail`` when any value breaks its flag's rule (exit
2 with one line), else it must run (exit 0) and leave the files a run leaves. Valid values are
kept small (a few steps, one or two seeds), so a case costs milliseconds; values that
are valid but only slow (a billion seeds, a huge iteration count) are not generated.
"""

from __future__ import annotations

import random
from typing import NamedTuple

from platoon_opt.solvers import available_allocators
from platoon_opt.solvers.options import Choice, Choices, Flag, Integer, Number, Numbers, Option, Table
from platoon_opt.solvers.registry import registered

SHIPPED = ("paper_obstacles", "paper_no_obstacles", "paper_covariance")
# Task components of the shipped scenarios (nmpc's task_weights needs one weight each).
COMPONENTS = {"paper_obstacles": 4, "paper_no_obstacles": 4, "paper_covariance": 5}
# Names every case folder holds (``fuzz_oracle.layout``): a file that is no scenario, a folder.
EXISTING_FILE, EXISTING_FOLDER = "existing.txt", "folder"
# Values that break any numeric flag.
BAD_NUMBERS = ("-1", "-0.5", "abc", "", " ", "nan", "inf", "-inf", "1e400", "0x10", "9" * 5000, "--", "1,2")
BAD_INTEGERS = (*BAD_NUMBERS, "1.5", "1e3", "None", "[1]")
# ... and any count, which must be >= 1 ("-0" is 0).
BAD_COUNTS = (*BAD_INTEGERS, "0", "-0")
# Allocators cheap enough to run in a case (nmpc: a short horizon, built once per structure).
# nmpc's options that shape its CasADi model (each new value costs seconds to build).
NMPC_MODEL = ("intervals", "resolve_every", "backend", "max_iterations")
CHEAP = ("iterative", "iterative", "iterative", "qp", "dual", "cone", "qp-projection", "cone-projection")


class Arguments(NamedTuple):
    """A generated argument list.

    Attributes:
        kind: the family and its variant ("simulate:bad-seed").
        argv: the arguments (after ``platoon-opt``).
        must_fail: some value breaks a documented rule.
        command: the command that runs if no value breaks a rule ("simulate" or "compare").
        out: the output folder a run writes, relative to the case folder.
        steps: the steps of each run, or 0 (a bad --duration).
        figures: whether a run draws its figures.
    """

    kind: str
    argv: tuple[str, ...]
    must_fail: bool
    command: str = ""
    out: str = ""
    steps: int = 0
    figures: bool = False


class _Builder:
    """Collects flags, their values and whether any is bad."""

    def __init__(self, rng: random.Random, *words: str) -> None:
        self.rng, self.argv, self.bad, self.notes = rng, list(words), False, [words[0] if words else "none"]

    def flag(self, name: str, good: tuple[str, ...], bad: tuple[str, ...], bad_share: float = 0.15) -> str:
        """Add ``name`` with a good value, or (with ``bad_share``) a bad one; returns the value."""
        if self.rng.random() < bad_share:
            self.bad = True
            self.notes.append(f"bad{name}")
            value = self.rng.choice(bad)
        else:
            value = self.rng.choice(good)
        self.argv += [name, value]
        return value

    def spoil(self, share: float) -> None:
        """With ``share``: an unknown flag, a flag without its value, or a stray word."""
        if self.rng.random() >= share:
            return
        self.bad = True
        how = self.rng.choice(("unknown", "missing", "stray"))
        self.notes.append(how)
        if how == "unknown":
            self.argv.insert(self.rng.randint(1, len(self.argv)), self.rng.choice(("--bogus", "-z", "---x")))
        elif how == "missing":
            self.argv.append(self.rng.choice(("--duration", "--out", "--seed", "--option", "--solver")))
        else:
            self.argv.append(self.rng.choice(("extra", "1", "-")))

    def done(self, command: str, out: str, steps: int = 0, figures: bool = False) -> Arguments:
        kind = ":".join(self.notes[:3])
        return Arguments(kind, tuple(self.argv), self.bad, command, out, steps, figures)


def _out(b: _Builder, default: str) -> str:
    """--out: mostly a fresh folder; sometimes absent (the default), or a bad one."""
    if b.rng.random() < 0.1:
        return default
    return b.flag("--out", ("out", "out/deeper", "."), ("", EXISTING_FILE, f"{EXISTING_FILE}/sub"), 0.1)


def _figures(b: _Builder) -> bool:
    """--no-figures but for one case in twenty (figures are the slow part)."""
    if b.rng.random() < 0.95:
        b.argv.append("--no-figures")
        return False
    return True


def _steps(b: _Builder, dt: float = 0.01) -> int:
    """--duration of a few steps (or a bad one); returns the steps."""
    steps = b.rng.randint(1, 5)
    value = b.flag("--duration", (repr(steps * dt),), (*BAD_NUMBERS, "0", repr(dt / 10), "1e308"), 0.15)
    return steps if value == repr(steps * dt) else 0


def option_value(option: Option, rng: random.Random, components: int) -> tuple[str, bool]:
    """A text for ``option`` and whether it breaks the option's rule."""
    rule = option.rule
    bad: list[str] = ["'x'", "None", "float('nan')", "1e999", "-1e999", "(", "()", "{'a': 1}", "[" * 300]
    bad += ["-" * 10_000 + "1", "~" * 999 + "1", "-" * 999 + "1", "1j", "b'x'", "{1, 2}", "...", "9" * 5000]
    good: list[str] = []
    if isinstance(rule, Number):
        low = rule.above if rule.above is not None else rule.at_least
        base = 0.0 if low is None else low
        good = [repr(base + 1.0), repr(base + 0.25), "10"]
        bad += ["True", "'1'", repr(base - 1.0)] + ([repr(rule.above)] if rule.above is not None else [])
    elif isinstance(rule, Integer):
        good = [str(rule.at_least + k) for k in range(3)]
        bad += ["1.5", "True", str(rule.at_least - 1), "'3'"]
    elif isinstance(rule, Flag):
        good, bad = ["True", "False"], [*bad, "1", "0", "'True'"]
    elif isinstance(rule, Choice):
        good = [repr(value) for value in rule.choices()] + list(rule.choices())
        bad += ["'nope'", "1", "''", repr(rule.choices()[0].upper() + "x")]
    elif isinstance(rule, Choices):
        names = rule.of.choices()
        good = [repr((names[0],)), repr(tuple(names[:2])), names[0], "()"]  # (): no name at all
        bad.remove("()")
        bad += ["('nope',)", "(1,)", "[None]"]
    elif isinstance(rule, Numbers):
        good = [repr(tuple([1.0] * components)), repr(tuple(range(1, components + 1)))]
        bad += [repr((1.0,) * (components - 1)), repr((1.0,) * (components + 1)), "(-1,) * 4", "(1, 'a')"]
    elif isinstance(rule, Table):
        good, bad = ["{}"], [*bad[:2], "1", "[1]"]
    if option.default is None:
        bad.remove("None")
        good.append("None")
    if rng.random() < 0.3:
        return rng.choice(bad), True
    return rng.choice(good), False


def _options(b: _Builder, solver: str, components: int, count: int) -> None:
    """``count`` --option pairs for ``solver``: valid, broken values, unknown names, bad pairs."""
    options = registered(solver).options
    given: set[str] = set()
    for _ in range(count):
        roll = b.rng.random()
        if roll < 0.08 or not options:
            b.bad = True
            b.notes.append("bad-pair")
            b.argv += ["--option", b.rng.choice(("=1", "rho", "rho==1", "1rho=1", "rho =1", "", "a-b=1"))]
        elif roll < 0.15:
            b.bad = True
            b.notes.append("unknown-option")
            b.argv += ["--option", b.rng.choice(("bogus=1", "Rho=1", "max_iteration=2", "_state=1"))]
        else:
            option = b.rng.choice(options)
            if solver == "nmpc" and option.name in NMPC_MODEL:
                continue  # each value is a model to build: seconds, not milliseconds
            if (option.name == "max_iterations" and solver == "iterative") or option.name in given:
                continue  # each option once: a repeated one is refused, whatever the values
            given.add(option.name)
            value, broken = option_value(option, b.rng, components)
            b.bad |= broken
            if broken:
                b.notes.append(f"bad-{option.name}")
            b.argv += ["--option", f"{option.name}={value}"]


def simulate(rng: random.Random, options_heavy: bool = False) -> Arguments:
    """``platoon-opt simulate`` with random flags (``options_heavy``: mostly --option pairs)."""
    scenario = rng.choice(SHIPPED)
    bad_scenario = rng.random() < (0.03 if options_heavy else 0.1)
    if bad_scenario:
        scenario = rng.choice(("nope", "", ".", EXISTING_FILE, EXISTING_FOLDER, "missing.toml", "paper"))
    b = _Builder(rng, "simulate", scenario)
    b.bad |= bad_scenario
    solver = rng.choice(available_allocators() if options_heavy else CHEAP)
    if rng.random() < 0.05:
        solver, b.bad = rng.choice(("nope", "", "QP", "iterative:max_iterations=2")), True
    b.argv += ["--solver", solver]
    if solver == "nmpc":
        b.argv += ["--option", "intervals=2", "--option", "resolve_every=2"]
    if solver in available_allocators():
        count = rng.randint(1, 3) if options_heavy else int(rng.random() < 0.2)
        _options(b, solver, COMPONENTS.get(scenario, 4), count)
    if rng.random() < 0.2:
        value = b.flag("--iterations", ("0", "1", "3"), BAD_INTEGERS, 0.3)
        b.bad |= solver != "iterative" and value in ("0", "1", "3")
    if rng.random() < 0.4:
        b.flag("--seed", ("0", "1", "17", "123456789012345678901234567890"), (*BAD_INTEGERS, "-7"), 0.3)
    steps = _steps(b)
    out = _out(b, "platoon-opt-results/simulate")
    if rng.random() < 0.1:
        b.argv.append("--strict")
    figures = _figures(b)
    b.spoil(0.05)
    return b.done("simulate", out, steps, figures)


def _config(rng: random.Random, b: _Builder) -> str:
    """A --solvers configuration: m=M, NAME or NAME:key=value,... (or a bad one)."""
    roll = rng.random()
    if roll < 0.4:
        return f"m={rng.randint(0, 4)}"
    if roll < 0.75:
        return rng.choice(("qp", "dual", "cone", "qp-projection", "iterative"))
    if roll < 0.9:
        name = rng.choice(("qp", "dual", "iterative", "cone"))
        pairs, seen = [], set()
        for _ in range(rng.randint(1, 2)):
            option = rng.choice(registered(name).options)
            if option.name == "max_iterations":
                continue
            b.bad |= option.name in seen  # an option given twice is an error
            seen.add(option.name)
            value, broken = option_value(option, rng, 4)
            if "," in value or ":" in value:
                value, broken = repr(option.default), False
            b.bad |= broken
            pairs.append(f"{option.name}={value}")
        return f"{name}:{','.join(pairs)}" if pairs else name
    b.bad = True
    b.notes.append("bad-config")
    return rng.choice(("m=-1", "", ":", "qp:", "qp:rho", "nope", "qp:rho=-1", "m=x", "qp:bogus=1", "a b"))


def compare(rng: random.Random) -> Arguments:
    """``platoon-opt compare`` with random scenarios, configurations and flags."""
    b = _Builder(rng, "compare")
    count = rng.choice((1, 1, 2, 0))
    b.bad |= count == 0
    b.argv += rng.sample(["paper_obstacles", "paper_no_obstacles"], count)
    if rng.random() < 0.05:
        b.argv.append(rng.choice(("nope", EXISTING_FILE, EXISTING_FOLDER)))
        b.bad = True
    configs = [_config(rng, b) for _ in range(rng.randint(1, 2))]
    if len(set(configs)) < len(configs):
        b.bad = True  # each configuration once
    b.argv += ["--solvers", *configs]
    b.flag("--seeds", ("1", "2"), BAD_COUNTS, 0.15)
    if rng.random() < 0.3:
        b.flag("--first-seed", ("0", "3"), BAD_INTEGERS, 0.3)
    steps = _steps(b)
    b.flag("--workers", ("1",), BAD_COUNTS, 0.1)
    for flag in ("--fresh", "--strict"):
        if rng.random() < 0.1:
            b.argv.append(flag)
    out = _out(b, "platoon-opt-results/compare")
    figures = _figures(b)
    b.spoil(0.05)
    return b.done("compare", out, steps, figures)


ARGV_FAMILIES = ("argv-simulate", "argv-options", "argv-compare")


def arguments(family: str, rng: random.Random) -> Arguments:
    """A random argument list of ``family``."""
    if family == "argv-simulate":
        return simulate(rng)
    if family == "argv-options":
        return simulate(rng, options_heavy=True)
    if family == "argv-compare":
        return compare(rng)
    raise ValueError(f"no argument family {family!r}")
