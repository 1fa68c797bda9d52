"""JAX's persistent compilation cache for the study: a second ``reproduce`` loads its compiled
programs from disk instead of compiling them again."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import jax


def cache_folder() -> Path:
    """Where the compiled programs are kept: ``$PLATOON_OPT_JAX_CACHE``, else
    ``$XDG_CACHE_HOME/platoon-opt/jax`` (``~/.cache/platoon-opt/jax``)."""
    given = os.environ.get("PLATOON_OPT_JAX_CACHE")
    if given:
        return Path(given)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "platoon-opt" / "jax"


@functools.cache
def enable_compilation_cache() -> None:
    """Keep every compiled program of this process in ``cache_folder()`` (once per process: the
    command line and each worker process call it)."""
    jax.config.update("jax_compilation_cache_dir", str(cache_folder()))
    # Every program: the engine's take a second or more to compile, the host's kernels less.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
