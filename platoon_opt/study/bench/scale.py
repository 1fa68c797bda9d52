"""The scale part: each allocator's time per allocation against n on ``cases.scale_problem``
(build and bare solve apart), its ratio to the dual on the same program, its objective's
difference from the dual's, and the peak traced memory of one allocation.

Contract: one record of kind "scale" per (allocator, n): measured, or ``skipped`` with the reason
once a QP allocator's single allocation has exceeded ``BUDGET``.
"""

from __future__ import annotations

import functools
import math
import statistics
import time
from typing import Any

from platoon_opt.allocation import Allocation
from platoon_opt.problem import AllocationProblem
from platoon_opt.solvers.convex import ConvexAllocator
from platoon_opt.solvers.convex.backends import clarabel_solver, osqp_solver
from platoon_opt.study.bench import cases
from platoon_opt.study.bench.cases import convex, scale_problem
from platoon_opt.study.bench.report import ratio_text
from platoon_opt.study.bench.timing import Records, clock, peak_memory, since

# A QP allocator whose single allocation took longer than this (s) is not run at larger n.
BUDGET = 30.0


def qp_parts(
    allocator: ConvexAllocator, problem: AllocationProblem, backend: str, allocation: Allocation
) -> tuple[float, float]:
    """Build and bare-solve times (s) of a QP allocator's program: posing it
    (``ConvexAllocator.program``) and setting the native solver up, then the solver's ``solve()``
    alone, on a fresh solver object; under strict priority both stages, the second toward the
    allocation's stage-1 task velocity."""
    stages = [("joint", None)]
    if allocator.priority == "strict":
        stages = [("task", None), ("deviation", allocation.info["stage1_task_velocity"])]
    build = solve = 0.0
    for stage, target in stages:
        start = time.perf_counter()
        program = allocator.program(problem, stage, target)
        if backend == "clarabel":
            solver = clarabel_solver(program)
            built = time.perf_counter()
            solver.solve()
        else:
            solver = osqp_solver(program)
            built = time.perf_counter()
            solver.solve(raise_error=False)
        build, solve = build + built - start, solve + time.perf_counter() - built
    return build, solve


def run_scale(records: Records, sizes: tuple[int, ...], dual_only: tuple[int, ...]) -> None:
    """Time per allocation, build and solve, ratio to the dual and memory, per allocator and n."""
    skipped: dict[str, str] = {}
    for n in (*sizes, *dual_only):
        count = max(cases.repetitions(n, "dual"), cases.repetitions(n, "clarabel"))
        problems = [scale_problem(n, seed) for seed in range(count)]
        dual_times: dict[tuple[str, str], float] = {}
        dual_objectives: dict[tuple[str, str], list[float]] = {}
        for entry in cases.entries():
            if entry.backend != "dual" and (n in dual_only or (entry.sizes and n not in entry.sizes)):
                continue
            if entry.label in skipped:
                records.add(kind="scale", allocator=entry.label, n=n, skipped=skipped[entry.label])
                continue
            reps = cases.repetitions(n, entry.backend)
            allocator = entry.build()
            if entry.backend == "dual" or n <= 4096:
                allocator.allocate(problems[-1])  # first call: imports, caches, workspaces
            walls, cpus, builds, solves, objectives, statuses, evaluations = [], [], [], [], [], set(), []
            for problem in problems[:reps]:
                start = clock()
                allocation = allocator.allocate(problem)
                wall, cpu = since(start)
                walls.append(wall)
                cpus.append(cpu)
                objectives.append(float(allocation.info.get("objective", math.nan)))
                statuses.add(allocation.status.split("->")[0][:60])
                if entry.backend == "dual":
                    builds.append(allocation.info["build_time"])
                    solves.append(allocation.solve_time - allocation.info["build_time"])
                    evaluations.append(allocation.info.get("evaluations", 0))
                else:
                    build, solve = qp_parts(convex(allocator), problem, entry.backend, allocation)
                    builds.append(build)
                    solves.append(solve)
            memory = peak_memory(functools.partial(allocator.allocate, problems[0]))
            median = statistics.median(walls)
            key = (entry.reading, entry.speed)
            record: dict[str, Any] = {
                "kind": "scale",
                "allocator": entry.label,
                "n": n,
                "repetitions": reps,
                "time": median,
                "cpu_time": statistics.median(cpus),
                "build": statistics.median(builds),
                "solve": statistics.median(solves),
                "peak_memory_mb": memory,
                "status": sorted(statuses),
            }
            if entry.backend == "dual":
                dual_times[key] = median
                dual_objectives[key] = objectives
                record["evaluations"] = statistics.median(evaluations)
            elif key in dual_times:
                record["ratio_to_dual"] = median / dual_times[key]
                reference = dual_objectives[key][: len(objectives)]
                record["objective_rel_diff"] = max(
                    abs(mine - theirs) / max(abs(theirs), 1e-12)
                    for mine, theirs in zip(objectives, reference)
                )
            records.add(**record)
            records.log(
                f"  n={n:>6} {entry.label:<26} {median * 1e3:10.3f} ms"
                + (f"  x{ratio_text(record['ratio_to_dual'])} dual" if "ratio_to_dual" in record else "")
            )
            if entry.backend != "dual" and max(walls) > BUDGET:
                skipped[entry.label] = (
                    f"one allocation took {max(walls):.0f} s at n={n} (budget {BUDGET:.0f} s)"
                )
