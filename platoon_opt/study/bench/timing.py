"""How the benchmark times and records: wall and CPU clocks, the peak of traced memory, and the
records of one run (``Records``).

Contract: every time is a ``time.perf_counter`` wall time with the process's CPU time
(``time.process_time``) beside it; ``peak_memory`` sees numpy arrays and Python objects, not the
native workspaces of Clarabel and OSQP.
"""

from __future__ import annotations

import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


def clock() -> tuple[float, float]:
    """Now: (wall, CPU) seconds."""
    return time.perf_counter(), time.process_time()


def since(start: tuple[float, float]) -> tuple[float, float]:
    """(wall, CPU) seconds since ``start`` (a ``clock()``)."""
    wall, cpu = clock()
    return wall - start[0], cpu - start[1]


def peak_memory(call: Callable[[], Any]) -> float:
    """Peak of traced memory (MB) during ``call()``: numpy arrays and Python objects."""
    tracemalloc.start()
    try:
        call()
        return tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


@dataclass
class Records:
    """The records of one run (each a dict with a "kind": scale, step, small or closed_loop), and
    where the progress lines go."""

    records: list[dict[str, Any]] = field(default_factory=list)
    log: Callable[[str], None] = print

    def add(self, **record: Any) -> None:
        self.records.append(record)
