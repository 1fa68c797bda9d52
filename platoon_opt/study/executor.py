"""One executor for every study: in this process, in a process pool, or on a Dask cluster; and
one progress display (tqdm) for all of them.

``execute(function, items)`` yields ``(index, function(item))`` as items finish, in any order;
the consumer stores each result at once (``platoon_opt.study.cache``), so an interrupted study
loses only the items under way. Worker processes are spawned, not forked: JAX runs threads, and a
forked child can inherit a lock one of them held (a forked pool worker hung at its start here).
A spawned worker imports what it runs afresh, so ``function`` must be importable by name (a
module-level function, or a ``functools.partial`` of one). The workers share the cores: each
sizes JAX's thread pool to its share of them (``share_cores``).
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TextIO

import jax
from tqdm import tqdm

from platoon_opt.study.compile_cache import sized_pool

# Off a terminal (logs, CI) the progress line is written at most this often (s).
LOG_INTERVAL = 30.0


def default_workers() -> int:
    """One worker process per CPU."""
    return os.cpu_count() or 1


def share_cores(threads: int) -> None:
    """Size the thread pool in which XLA runs this process's compiled code to ``threads`` of the
    CPUs it may use, and keep the programs it compiles with those of that pool size
    (``compile_cache.sized_pool``). Call it before the process's first JAX computation (a pool
    worker's initializer): later the pool keeps its size.

    XLA sizes that pool from the process's CPU affinity when the first computation creates the
    CPU client, so the affinity is narrowed for that moment and then restored, for every thread
    of the process (the pool's threads start meanwhile and inherit the narrowed set): the process
    still runs on any core. Worker processes are a study's parallelism, and a pool thread per core
    in each of them makes them contend: one platoon of 8 units ran its closed loop about 1.6x
    faster with one thread than with two on a 2-core machine (docs/engine.md).
    """
    if not hasattr(os, "sched_setaffinity"):  # macOS, Windows: the pool keeps its size
        return
    every = os.sched_getaffinity(0)
    chosen = set(sorted(every)[: max(1, threads)])
    os.sched_setaffinity(0, chosen)
    try:
        jax.devices()  # creates the CPU client and its pool
    finally:
        _on_cores(every)
    sized_pool(len(chosen))


def _on_cores(cores: set[int]) -> None:
    """Let every thread of this process run on ``cores``. ``os.sched_setaffinity(0, ...)`` sets the
    calling thread's alone, and the threads XLA started while the set was narrowed would keep it:
    every worker's compiled code would run on the same first core."""
    for thread in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(thread), cores)
        except ProcessLookupError:  # the thread ended meanwhile
            pass


# How often (s) a worker process looks whether the process that started it is still there.
PARENT_POLL = 1.0


def start_worker(threads: int, parent: int) -> None:
    """A pool worker's initializer: ``share_cores(threads)``, and a watch on the process that
    started it (pid ``parent``): when that process is gone (killed, even with SIGKILL, so that
    it could not stop its workers) the worker exits instead of running on with nobody to take
    its results."""
    share_cores(threads)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL)
        os._exit(1)

    threading.Thread(target=watch, name="platoon-opt-parent-watch", daemon=True).start()


def execute(
    function: Callable[[Any], Any],
    items: Sequence[Any],
    *,
    workers: int | None = None,
    scheduler: Any = None,
) -> Iterator[tuple[int, Any]]:
    """Yield ``(index, function(item))`` as each item finishes.

    Args:
        function: a module-level function (workers unpickle it), or a ``functools.partial`` of one.
        workers: processes (default ``default_workers()``); 1 runs in this process.
        scheduler: a Dask scheduler address or ``distributed.Client``: run there instead.

    Pending work is cancelled, and running workers terminated, if the consumer stops (Ctrl-C, an
    error, SIGTERM through the command line's handler); workers whose parent process is killed
    outright exit within ``PARENT_POLL`` seconds (``start_worker``).
    """
    if not items:
        return
    workers = default_workers() if workers is None else workers
    if scheduler is not None:
        yield from _execute_dask(function, items, scheduler)
    elif workers <= 1 or len(items) == 1:
        for index, item in enumerate(items):
            yield index, function(item)
    else:
        processes = min(workers, len(items))
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        pool = ProcessPoolExecutor(
            max_workers=processes,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=start_worker,
            initargs=(cores // processes, os.getpid()),
        )
        futures = {pool.submit(function, item): index for index, item in enumerate(items)}
        try:
            for future in as_completed(futures):
                yield futures[future], future.result()
        except BaseException:
            # Stop the work under way instead of letting the interpreter wait for it (its results
            # would be dropped anyway).
            _terminate_workers(pool)  # before shutdown, which forgets the processes
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()


def _terminate_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate the pool's worker processes (Python >= 3.14 has a method for it)."""
    if hasattr(pool, "terminate_workers"):
        pool.terminate_workers()
        return
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.terminate()


def _execute_dask(
    function: Callable[[Any], Any], items: Sequence[Any], scheduler: Any
) -> Iterator[tuple[int, Any]]:
    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ImportError as error:  # an optional dependency, looked for only when asked
        raise ImportError(
            "a Dask scheduler needs dask.distributed: pip install 'platoon-opt[dask]'"
        ) from error
    client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
    try:
        futures = {client.submit(function, item, pure=False): index for index, item in enumerate(items)}
        try:
            for future in dask_completed(futures):
                yield futures[future], future.result()
        finally:
            client.cancel(list(futures))
    finally:
        if client is not scheduler:
            client.close()


class Progress:
    """A progress bar of finished items on a stream (default stderr): done, reused, elapsed and
    time left. On a terminal it is redrawn in place; elsewhere (logs, CI) it appears only once the
    work has taken ``LOG_INTERVAL`` seconds, then at most every ``LOG_INTERVAL`` seconds and at
    the end, so that short work writes nothing but its result.

    Attributes:
        done: items finished, reused ones included.
        reused: items taken from an earlier call instead of computed.
    """

    def __init__(self, total: int, label: str, *, unit: str = "runs", stream: TextIO | None = None) -> None:
        stream = stream if stream is not None else sys.stderr
        terminal = bool(getattr(stream, "isatty", lambda: False)())
        self.done = self.reused = 0
        self._bar = tqdm(
            total=total,
            desc=label,
            unit=unit,
            file=stream,
            dynamic_ncols=terminal,
            ncols=None if terminal else 100,
            mininterval=0.2 if terminal else LOG_INTERVAL,
            delay=0.0 if terminal else LOG_INTERVAL,
            ascii=not terminal,
        )

    def reuse(self, count: int) -> None:
        """Count ``count`` items taken from an earlier call."""
        self.reused += count
        if self.reused:
            self._bar.set_postfix_str(f"{self.reused} reused", refresh=False)
        self.advance(count)

    def advance(self, count: int = 1) -> None:
        """Count ``count`` more finished items."""
        self.done += count
        self._bar.update(count)

    @property
    def computed(self) -> int:
        """Items finished by this call."""
        return self.done - self.reused

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
