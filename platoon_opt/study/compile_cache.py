"""JAX's persistent compilation cache for the study: a second ``reproduce`` loads its compiled
programs from disk instead of compiling them again."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import jax


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


@functools.cache
def enable_compilation_cache() -> None:
    """Keep every compiled program of this process in ``cache_folder()`` (once per process: the
    command line and each worker process call it); nothing if ``cache_folder()`` is None."""
    folder = cache_folder()
    if folder is None:
        return
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # Every program: the engine's take a second or more to compile, the host's kernels less.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
