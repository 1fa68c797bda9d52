"""JAX's persistent compilation cache for the study: a second ``reproduce`` loads its compiled
programs from disk instead of compiling them again.

Programs are kept by the size of the XLA CPU thread pool they were compiled for
(``<folder>/pool-<threads>``): XLA splits a program's loops over the pool it is compiled for,
and JAX's cache key leaves the pool out. A step of one platoon of 32,768 units compiled in a
process with one pool thread and loaded into one with two ran 1.45-1.5x slower there than the
same step compiled there (docs/engine.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import jax


@dataclass
class _Process:
    """Whether this process keeps its programs (``enable_compilation_cache``), and the threads of
    its pool as ``executor.share_cores`` sized it (None: XLA's default)."""

    enabled: bool = False
    threads: int | None = None


_STATE = _Process()


def cache_folder() -> Path | None:
    """Where the compiled programs are kept: ``$PLATOON_OPT_JAX_CACHE``, else
    ``$XDG_CACHE_HOME/platoon-opt/jax`` (``~/.cache/platoon-opt/jax``); None if that variable is
    "off"."""
    given = os.environ.get("PLATOON_OPT_JAX_CACHE")
    if given == "off":
        return None
    if given:
        return Path(given)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "platoon-opt" / "jax"


def pool_threads() -> int:
    """The threads of this process's XLA CPU pool: as ``executor.share_cores`` sized it, else
    XLA's default, one per CPU the process may use."""
    if _STATE.threads is not None:
        return _STATE.threads
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def enable_compilation_cache() -> None:
    """Keep every compiled program of this process in ``cache_folder()``, under its pool's size
    (the command line and each worker process call it); nothing if ``cache_folder()`` is None."""
    if _STATE.enabled or cache_folder() is None:
        return
    _STATE.enabled = True
    # Every program: the engine's take a second or more to compile, the host's kernels less.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _point_at_pool()


def sized_pool(threads: int) -> None:
    """Record that this process's pool has ``threads`` threads (``executor.share_cores``, before
    the first compilation) and keep its programs under that size."""
    _STATE.threads = threads
    if _STATE.enabled:
        _point_at_pool()


def _point_at_pool() -> None:
    folder = cache_folder()
    if folder is not None:
        jax.config.update("jax_compilation_cache_dir", str(folder / f"pool-{pool_threads()}"))
