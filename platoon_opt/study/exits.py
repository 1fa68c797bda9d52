"""How a command ends: its exit statuses, the one-line errors, and the stops from outside (Ctrl-C,
or SIGTERM turned into the same unwinding, so that its worker processes are stopped by
``executor.execute`` and what finished stays stored)."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator

from platoon_opt.errors import AllocationError, PlatoonOptError

# Bad input: one line naming the file, field or option and the value.
BAD_INPUT = 2
# A --strict run whose allocation failed or fell back (one line on stderr).
ALLOCATION_FAILED = 3
# After Ctrl-C (128 + SIGINT).
INTERRUPTED = 130
# The shell's status of a command killed by SIGPIPE (128 + 13).
BROKEN_PIPE = 141
# After SIGTERM (128 + its number, as a shell reports a process it ended).
TERMINATED = 128 + signal.SIGTERM


def bad_input(error: PlatoonOptError) -> int:
    """Print bad input as one line and return its status."""
    print(f"platoon-opt: error: {' '.join(str(error).splitlines())}", file=sys.stderr)
    return BAD_INPUT


def allocation_failed(error: AllocationError, note: str = "") -> int:
    """Print a strict run's failure as one line (after any progress line) and return its status."""
    start = "\n" if sys.stderr.isatty() else ""
    print(f"{start}platoon-opt: error: {error}{note}", file=sys.stderr)
    return ALLOCATION_FAILED


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: unwinds the command as Ctrl-C does."""


def stopped(stop: KeyboardInterrupt) -> tuple[str, int]:
    """What stopped a command, and its exit status: SIGTERM (143) or Ctrl-C (130)."""
    return ("terminated", TERMINATED) if isinstance(stop, Terminated) else ("interrupted", INTERRUPTED)


@contextlib.contextmanager
def terminate_on_sigterm() -> Iterator[None]:
    """Within the block, SIGTERM raises ``Terminated`` (Python's default ends the process on the
    spot, leaving its worker processes running); the handler before is restored after. Only the
    main thread can install a handler; elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum: int, frame: object) -> None:
        raise Terminated

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
