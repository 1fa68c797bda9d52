"""Where a study's runs go: reused from the run cache, batched through the compiled engine
(``batches``), or run one by one on the host (``runs.run_spec``); all through one executor
(in this process, worker processes or a Dask cluster), each finished run stored at once.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from platoon_opt.study.batches import BatchJob, plan_batches, run_batch_job
from platoon_opt.study.cache import ResultCache
from platoon_opt.study.compile_cache import enable_compilation_cache
from platoon_opt.study.config import AllocatorFactory
from platoon_opt.study.executor import Progress, execute
from platoon_opt.study.runs import RunSpec, run_job, trajectory_of
from platoon_opt.trajectory import Trajectory


def _job(item: BatchJob | RunSpec, factory: AllocatorFactory) -> list[tuple[dict[str, Any], bytes | None]]:
    """A worker's job: a batch's runs, or one host run; each run's result and, if asked for, its
    thinned trajectory."""
    enable_compilation_cache()
    if isinstance(item, BatchJob):
        return run_batch_job(item, factory)
    return [run_job(item, factory)]


def run_specs(
    specs: Sequence[RunSpec],
    factory: AllocatorFactory,
    *,
    runs_dir: str | Path | None = None,
    workers: int | None = None,
    scheduler: Any = None,
    fresh: bool = False,
    progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """Run every spec (each at most once) and return their results in the order of ``specs``.

    Runs that can share a compiled call go as batches (``batches.plan_batches``), the others one
    by one; a Dask cluster receives batches too.

    Args:
        factory: ``platoon_opt.solvers.get_allocator`` (module-level, so workers can import it).
        runs_dir: folder of per-run result files; a run whose file holds a matching
            fingerprint is reused, every newly finished run is written there at once.
            None keeps nothing.
        workers, scheduler: where the runs execute (``executor.execute``).
        fresh: ignore finished runs in ``runs_dir`` (they are overwritten).
        progress: advanced once per finished (or reused) run.

    Raises:
        AllocationError: a strict spec's run failed (runs finished before are kept in ``runs_dir``).
    """
    cache = ResultCache(runs_dir, fresh=fresh)
    results: list[dict[str, Any] | None] = [None] * len(specs)
    unique: dict[str, int] = {}
    pending: list[int] = []
    for index, spec in enumerate(specs):
        if spec.key in unique:
            continue
        unique[spec.key] = index
        cached = cache.load(spec.key, spec.fingerprint())
        if cached is not None and spec.strict and cached.get("fallback_steps", 0):
            cached = None  # it fell back: recompute, so that the strict run raises
        if cached is not None:
            results[index] = cached
        else:
            pending.append(index)
    if progress is not None:
        progress.reuse(len(unique) - len(pending))
    batched, host = plan_batches([specs[i] for i in pending], factory)
    groups = [tuple(pending[i] for i in batch.members) for batch in batched]
    # Longest host runs first (smaller time step), so no worker idles at the end behind one.
    singles = sorted((pending[i] for i in host), key=lambda index: -specs[index].steps)
    members = groups + [(index,) for index in singles]
    items: list[BatchJob | RunSpec] = [
        BatchJob(tuple(specs[i] for i in group), batch.size, batch.record_size)
        for group, batch in zip(groups, batched)
    ]
    items += [specs[index] for index in singles]
    for position, finished in execute(
        functools.partial(_job, factory=factory), items, workers=workers, scheduler=scheduler
    ):
        for index, (result, track) in zip(members[position], finished):
            # This process's fingerprint, the one the next call checks: it names the code this
            # process loaded (and its workers imported), even if the files change meanwhile.
            result["fingerprint"] = specs[index].fingerprint()
            cache.store(
                specs[index].key, result["fingerprint"], result, None if track is None else {".npz": track}
            )
            results[index] = result
        if progress is not None:
            progress.advance(len(finished))
    return [results[unique[spec.key]] for spec in specs]  # type: ignore[misc]


def trajectories_of(
    specs: Sequence[RunSpec],
    factory: AllocatorFactory,
    *,
    workers: int | None = None,
    scheduler: Any = None,
) -> list[Trajectory]:
    """Full trajectories of ``specs`` (for figures), computed in parallel like ``run_specs``."""
    trajectories: list[Trajectory | None] = [None] * len(specs)
    for index, trajectory in execute(
        functools.partial(trajectory_of, factory=factory), list(specs), workers=workers, scheduler=scheduler
    ):
        trajectories[index] = trajectory
    return trajectories  # type: ignore[return-value]
