"""The machine a measurement ran on, for the records of the bench, the soak and the timing
experiments: CPU model, cores, Python, numpy, Clarabel and OSQP versions, platform, and the
load average (a time on a shared machine includes waiting for a core)."""

from __future__ import annotations

import math
import os
import platform
from pathlib import Path
from typing import Any

import clarabel
import numpy as np
import osqp

# Linux names the CPU model here; elsewhere ``platform.processor()`` is the best there is.
CPUINFO = Path("/proc/cpuinfo")


def cpu_model() -> str:
    """The CPU's model name (``platform.processor()`` where /proc/cpuinfo has none)."""
    try:
        for line in CPUINFO.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def machine() -> dict[str, Any]:
    """CPU model, cores, Python, numpy, Clarabel and OSQP versions and the platform."""
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "clarabel": clarabel.__version__,
        "osqp": osqp.__version__,
        "platform": platform.platform(),
    }


def load_average() -> float:
    """The 1-minute load average (NaN where the system keeps none, e.g. Windows)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return math.nan
