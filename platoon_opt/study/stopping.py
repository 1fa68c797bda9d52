"""How a command is stopped from outside: Ctrl-C, or SIGTERM turned into the same unwinding, so
that its worker processes are stopped (``executor.execute``) and what finished stays stored."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

# Exit status after SIGTERM (128 + its number, as a shell reports a process it ended).
TERMINATED = 128 + signal.SIGTERM
# Exit status after Ctrl-C (128 + SIGINT).
INTERRUPTED = 130


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
