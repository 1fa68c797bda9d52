"""The command line's input checks: a parser whose every error is one line, the types of its
numeric flags, and output folders.

Each check names the flag and the value (``argument --seeds: must be an integer >= 1, got '0'``);
``main`` prints it as ``platoon-opt: error: ...`` and exits 2. A value is checked where it enters:
a flag's type here, a scenario-dependent bound (``--duration`` against the scenario's step) by
``Scenario.run_steps``.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from platoon_opt.errors import ConfigurationError
from platoon_opt.scenario_checks import MAX_UNITS

# Counts beyond these are refused rather than attempted: a study of more seeds, or a soak or fuzz
# run of more cases, is no command anyone means (its plan alone would not fit in memory).
MAX_SEEDS = 1_000_000
MAX_CASES = 100_000_000


class UsageError(ConfigurationError):
    """Bad command-line input: printed as one line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors raise ``UsageError`` (one line) instead of printing the
    usage and exiting; its subcommands' parsers are of this class too."""

    def error(self, message: str) -> NoReturn:
        text = " ".join(message.split())
        raise UsageError(f"{text} (see {self.prog} --help)")


def _text(value: str) -> str:
    return repr(value) if len(value) <= 40 else repr(value[:37] + "...")


def integer(at_least: int, at_most: int | None = None) -> Callable[[str], int]:
    """A flag's type: an integer in [at_least, at_most]."""
    rule = f"an integer >= {at_least}" if at_most is None else f"an integer in [{at_least}, {at_most:,}]"

    def parse(value: str) -> int:
        try:
            number = int(value.strip(), 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {rule}, got {_text(value)}") from None
        if number < at_least or (at_most is not None and number > at_most):
            raise argparse.ArgumentTypeError(f"must be {rule}, got {_text(value)}")
        return number

    parse.__name__ = "integer"
    return parse


def seconds(value: str) -> float:
    """A flag's type: a finite number of seconds > 0 (the scenario's step bounds it further)."""
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not math.isfinite(number) or number <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds > 0, got {_text(value)}")
    return number


def fraction(value: str) -> float:
    """A flag's type: a number in [0, 1]."""
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not 0.0 <= number <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1], got {_text(value)}")
    return number


SEED = integer(0)
COUNT = integer(1, MAX_SEEDS)
SIZE = integer(2, MAX_UNITS)
CASES = integer(1, MAX_CASES)


def output_folder(text: str, flag: str = "--out") -> Path:
    """``text`` as an output folder the command can make and write (it is made when the first file
    is written): ``UsageError`` naming ``flag`` if it is empty, names an existing file, lies under
    a file, or its nearest existing folder is not writable."""
    if not text.strip():
        raise UsageError(f"{flag} must name a folder, got {text!r}")
    folder = Path(text)
    try:
        if folder.exists() and not folder.is_dir():
            raise UsageError(f"{flag} must be a folder, got {text!r}, an existing file")
        existing = next(parent for parent in (folder, *folder.absolute().parents) if parent.exists())
        if not existing.is_dir():
            raise UsageError(f"{flag} must be a folder, got {text!r}, under the file {str(existing)!r}")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise UsageError(f"{flag} {text!r}: cannot write in {str(existing)!r} (permission denied)")
    except OSError as error:
        raise UsageError(f"{flag} {text!r}: {error.strerror or error}") from None
    return folder
