"""JAX's persistent compilation cache: a second process loads what the first compiled."""

from __future__ import annotations

import os
import subprocess
import sys
import time

# A process that enables the cache and runs one second of the paper scenario under m = 4 in the
# engine, printing how long that took (compile included).
_SCRIPT = """
import time
from platoon_opt.study.compile_cache import enable_compilation_cache
enable_compilation_cache()
from platoon_opt import load_scenario, simulate
from platoon_opt.solvers import get_allocator
start = time.perf_counter()
simulate(load_scenario("paper_no_obstacles"), get_allocator("iterative", max_iterations=4), duration=1.0)
print(time.perf_counter() - start)
"""


def _run(env: dict[str, str]) -> float:
    done = subprocess.run(
        [sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, check=True
    )
    return float(done.stdout.split()[-1])


def test_a_second_process_loads_the_compiled_programs(tmp_path):
    env = {**os.environ, "PLATOON_OPT_JAX_CACHE": str(tmp_path / "jax")}
    _run(env)
    entries = list((tmp_path / "jax").rglob("*"))
    assert entries, "the first process wrote the compiled programs"
    mtimes = {p: p.stat().st_mtime_ns for p in entries}
    time.sleep(0.01)
    _run(env)
    # Nothing compiled again: the second process wrote no entry and changed none.
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "jax").rglob("*")} == mtimes


def test_off_leaves_the_cache_alone(tmp_path):
    env = {**os.environ, "PLATOON_OPT_JAX_CACHE": "off", "XDG_CACHE_HOME": str(tmp_path)}
    _run(env)
    assert not (tmp_path / "platoon-opt").exists()


# As _SCRIPT, in a process whose pool ``share_cores`` sizes to one thread after the cache is
# enabled (the command line's order: ``main`` enables it, ``bench --threads 1`` sizes the pool).
_ONE_THREAD = _SCRIPT.replace(
    "enable_compilation_cache()\n",
    "enable_compilation_cache()\nfrom platoon_opt.study.executor import share_cores\nshare_cores(1)\n",
)


def test_programs_are_kept_by_the_size_of_the_pool_they_were_compiled_for(tmp_path):
    """A program compiled for one pool size runs at another's speed there (1.45-1.5x slower at
    n = 32,768: docs/engine.md), so each size has its own folder."""
    env = {**os.environ, "PLATOON_OPT_JAX_CACHE": str(tmp_path / "jax")}
    subprocess.run([sys.executable, "-c", _ONE_THREAD], env=env, capture_output=True, check=True)
    assert [p.name for p in (tmp_path / "jax").iterdir()] == ["pool-1"]
    _run(env)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert {p.name for p in (tmp_path / "jax").iterdir()} == {"pool-1", f"pool-{cores}"}
