"""The executor's worker processes share the cores: each sizes JAX's thread pool to its share."""

from __future__ import annotations

import os

import pytest

from platoon_opt.study.executor import execute, share_cores

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="CPU affinity is Linux's")


def pool_threads(_: object = None) -> int:
    """Threads of XLA's CPU pool in this process, after a computation (they are named after it)."""
    import jax.numpy as jnp

    jnp.ones(3).sum().block_until_ready()
    names = (open(f"/proc/self/task/{task}/comm").read() for task in os.listdir("/proc/self/task"))
    return sum("XLAEigen" in name for name in names)


def test_share_cores_leaves_the_process_on_every_core():
    before = os.sched_getaffinity(0)
    share_cores(1)  # this process's pool exists already: only the affinity is touched
    assert os.sched_getaffinity(0) == before


def test_workers_size_their_pools_to_their_share_of_the_cores():
    if pool_threads() == 0:
        pytest.skip("this XLA names its pool threads otherwise")
    cores = len(os.sched_getaffinity(0))
    sizes = dict(execute(pool_threads, [0, 1], workers=2))
    assert sizes == {0: max(1, cores // 2), 1: max(1, cores // 2)}
