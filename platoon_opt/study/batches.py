"""A study's runs as batches of the compiled engine.

Runs that share a scenario (after its variant), a run length and an allocator kernel
(``engine.compiled_step``: the same kernel and static options) differ only in their seed and their
allocator's numbers (m, rho, eps, ...): they form a group and run as compiled calls
(``engine.run_batch``) of at most ``BATCH_SIZE`` platoons, the runs that keep their trajectory
(``keep_track``) recorded within their batch. Every batch is compiled for exactly ``BATCH_SIZE``
platoons (the shorter padded) and every batch of a group for the same number of recorded ones, so
that a group compiles one program and a run's numbers do not depend on the study around it (how
many seeds, how many workers): XLA's arithmetic rounds differently in programs compiled for
different batch sizes (docs/engine.md). The first batch of every group is handed out before the
second of any, so that worker processes compile different programs at once and the later batches
load theirs from the persistent compilation cache. Runs whose allocator has no kernel for the
scenario (a host solver: Clarabel, OSQP, CasADi; barriers beyond 32 units) run one by one on the host
(``runs.run_spec``). A run's result is the same dict either way, with ``path`` saying which ran
it ("compiled" or "host").
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from platoon_opt.engine import BATCH_SIZE, CompiledStep, Plant, compiled_step, run_batch
from platoon_opt.errors import AllocationError
from platoon_opt.scenarios import Scenario
from platoon_opt.simulation import batch_scores, batch_trajectory, overflowed
from platoon_opt.study.config import AllocatorFactory
from platoon_opt.study.runs import RunSpec, run_job, run_result
from platoon_opt.study.tracks import track_bytes


class PlannedBatch(NamedTuple):
    """A batch of ``plan_batches``: its runs (indices), the platoons and the recorded platoons its
    group compiles for (``size``, and the most tracks in one batch of the group)."""

    members: tuple[int, ...]
    size: int
    record_size: int


@dataclass(frozen=True)
class BatchJob:
    """Runs that go through the engine in one call (``run_batch_job``), compiled for ``size``
    platoons and ``record_size`` recorded ones (at least the batch's runs and its runs with
    ``keep_track``: the batches of a group share a program)."""

    specs: tuple[RunSpec, ...]
    size: int
    record_size: int


def plan_batches(
    specs: Sequence[RunSpec], factory: AllocatorFactory, *, size: int = BATCH_SIZE
) -> tuple[list[PlannedBatch], list[int]]:
    """Split ``specs`` into batches, each compiled for ``size`` platoons, and host runs (indices).

    A group of runs that can share a call is cut into as few batches as hold it, of sizes as
    even as they can be. (Cutting a small group further to keep every worker busy would not end
    it sooner: a batch costs its ``size`` platoons whatever it holds.) The first batches of all
    groups come first, then the second ones, and so on."""
    groups: dict[Any, list[int]] = {}
    host: list[int] = []
    for index, spec in enumerate(specs):
        scenario = spec.variant.apply(spec.scenario)
        step = compiled_step(spec.config.build(factory), scenario)
        if step is None:
            host.append(index)
            continue
        key = (spec.scenario.name, spec.variant.name, spec.steps, step.kernel, step.static)
        groups.setdefault(key, []).append(index)
    cut = []
    for members in groups.values():
        count = -(-len(members) // size)
        pieces = [tuple(int(i) for i in piece) for piece in np.array_split(np.array(members), count)]
        tracks = max(sum(specs[i].keep_track for i in piece) for piece in pieces)
        cut.append([PlannedBatch(piece, size, tracks) for piece in pieces])
    return [batch for turn in itertools.zip_longest(*cut) for batch in turn if batch is not None], host


def run_batch_job(job: BatchJob, factory: AllocatorFactory) -> list[tuple[dict[str, Any], bytes | None]]:
    """Run a batch and score each run (``runs.run_result``); with ``keep_track``, also each run's
    thinned trajectory.

    Raises:
        AllocationError: a strict run fell back (naming the scenario and the seed).
    """
    first = job.specs[0]
    scenario = first.variant.apply(first.scenario)
    steps = [_kernel_of(spec, factory, scenario) for spec in job.specs]
    starts = [scenario.initial(spec.seed) for spec in job.specs]
    record = [i for i, spec in enumerate(job.specs) if spec.keep_track]
    start, cpu = time.perf_counter(), time.process_time()
    batch = run_batch(
        steps[0],
        Plant.of(scenario),
        [state for state, _ in starts],
        [obstacles for _, obstacles in starts],
        first.steps,
        params=[step.params for step in steps],
        record=record,
        size=job.size,
        record_size=job.record_size,
    )
    share = ((time.perf_counter() - start) / len(job.specs), (time.process_time() - cpu) / len(job.specs))
    out = []
    for i, (spec, step) in enumerate(zip(job.specs, steps)):
        if overflowed(batch, i):
            out.append(run_job(spec, factory, compiled=False))
            continue
        scores, fallback = batch_scores(batch, i, scenario, step)
        if spec.strict and fallback[0]:
            error = AllocationError(
                allocator=step_name(spec, factory), reason=f"fell back: {fallback[0]}", t=fallback[1]
            )
            raise error.within(scenario=_scenario_name(spec), seed=spec.seed)
        track = None
        if spec.keep_track:
            name = step_name(spec, factory)
            track = track_bytes(batch_trajectory(batch, i, scenario, starts[i][1], name, step, spec.seed))
        out.append((run_result(spec, scenario, first.steps, scores, fallback, share, path="compiled"), track))
    return out


def _kernel_of(spec: RunSpec, factory: AllocatorFactory, scenario: Scenario) -> CompiledStep:
    """The kernel of ``spec``'s allocator (``plan_batches`` batched only runs that have one)."""
    step = compiled_step(spec.config.build(factory), scenario)
    if step is None:
        raise ValueError(f"{spec.config.label} has no compiled kernel for {scenario.name}: no batch")
    return step


def step_name(spec: RunSpec, factory: AllocatorFactory) -> str:
    """The allocator's name of ``spec`` (as its trajectories label it)."""
    return spec.config.build(factory).name


def _scenario_name(spec: RunSpec) -> str:
    name = spec.scenario.name
    return name if spec.variant.name == "base" else f"{name} ({spec.variant.name})"
