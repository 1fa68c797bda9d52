"""The executor's worker processes share the cores (each sizes JAX's thread pool to its share),
and stop when the command that started them is ended."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from platoon_opt.study.executor import PARENT_POLL, execute, share_cores

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="CPU affinity is Linux's")


def _threads() -> list[str]:
    """This process's threads (their ids), after a computation: XLA's pool has started."""
    import jax.numpy as jnp

    jnp.ones(3).sum().block_until_ready()
    return os.listdir("/proc/self/task")


def pool_threads(_: object = None) -> int:
    """Threads of XLA's CPU pool in this process (they are named after it)."""
    names = (open(f"/proc/self/task/{task}/comm").read() for task in _threads())
    return sum("XLAEigen" in name for name in names)


def test_share_cores_leaves_the_process_on_every_core():
    before = os.sched_getaffinity(0)
    share_cores(1)  # this process's pool exists already: only the affinity is touched
    assert os.sched_getaffinity(0) == before


def thread_affinities(_: object = None) -> set[frozenset[int]]:
    """The CPU sets of this process's threads, XLA's pool among them."""
    affinities: set[frozenset[int]] = set()
    for thread in _threads():
        try:
            affinities.add(frozenset(os.sched_getaffinity(int(thread))))
        except ProcessLookupError:  # the thread ended meanwhile
            pass
    return affinities


def test_every_thread_of_a_worker_runs_on_every_core():
    """XLA's pool threads start while ``share_cores`` narrows the affinity: they get the whole set
    back too, or every worker computes on the first core alone."""
    every = frozenset(os.sched_getaffinity(0))
    for affinities in dict(execute(thread_affinities, [0, 1], workers=2)).values():
        assert affinities == {every}


def test_workers_size_their_pools_to_their_share_of_the_cores():
    if pool_threads() == 0:
        pytest.skip("this XLA names its pool threads otherwise")
    cores = len(os.sched_getaffinity(0))
    sizes = dict(execute(pool_threads, [0, 1], workers=2))
    assert sizes == {0: max(1, cores // 2), 1: max(1, cores // 2)}


def sleep_in_worker(folder: str) -> None:
    """Write this worker's pid into ``folder`` and sleep far longer than a test waits."""
    Path(folder, str(os.getpid())).write_text("")
    time.sleep(600)


_POOL = """
import sys
from platoon_opt.study.exits import stopped, terminate_on_sigterm
from platoon_opt.study.executor import execute
from tests.study.test_executor import sleep_in_worker
try:
    with terminate_on_sigterm():
        list(execute(sleep_in_worker, [sys.argv[1]] * 2, workers=2))
except KeyboardInterrupt as stop:
    sys.exit(stopped(stop)[1])
"""


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, gone but not reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0] != "Z"
    except (FileNotFoundError, IndexError):
        return False


def _wait(condition, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.1)
    return condition()


@pytest.mark.parametrize("signal_number", [signal.SIGTERM, signal.SIGKILL])
def test_workers_stop_when_their_command_is_ended(tmp_path, signal_number):
    """SIGTERM: the command stops its workers and exits 143. SIGKILL (no handler can run): each
    worker sees its parent gone and exits within PARENT_POLL seconds."""
    root = Path(__file__).resolve().parents[2]
    parent = subprocess.Popen([sys.executable, "-c", _POOL, str(tmp_path)], cwd=root)
    try:
        assert _wait(lambda: len(list(tmp_path.iterdir())) == 2, 120), "the workers did not start"
        workers = [int(path.name) for path in tmp_path.iterdir()]
        parent.send_signal(signal_number)
        status = parent.wait(30)
        assert status == (143 if signal_number == signal.SIGTERM else -signal.SIGKILL)
        assert _wait(lambda: not any(_alive(pid) for pid in workers), 10 * PARENT_POLL)
    finally:
        parent.kill()
