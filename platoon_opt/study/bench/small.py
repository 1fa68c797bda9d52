"""The small part: n = 8 along the paper scenario's closed loop, the dual's allocation
(warm-started step to step, as in the loop) against Clarabel's bare ``solve()`` of the same
program (``ConvexAllocator.program``, the solver updated in place, ``solve()`` alone timed).

Contract: one record of kind "small" per (reading, speed model), with medians over the steps.
"""

from __future__ import annotations

import statistics
from typing import Any

from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex.backends import clarabel_form, clarabel_solver
from platoon_opt.study.bench.cases import closed_loop_problems, convex
from platoon_opt.study.bench.timing import Records, clock, since


def run_small(records: Records, duration: float) -> None:
    """n = 8 along the closed loop: the dual's allocation (warm-started step to step, as in the
    loop) against Clarabel's bare ``solve()`` of the same program, updated in place."""
    problems = closed_loop_problems(duration)
    for reading, speed, name in (
        ("achievable-first", "polygon", "qp"),
        ("achievable-first", "cone", "cone"),
        ("task-exact", "polygon", "qp-projection"),
        ("task-exact", "cone", "cone-projection"),
    ):
        dual = get_allocator("dual", reading=reading, speed=speed)
        reference = convex(get_allocator(name, **({"backend": "clarabel"} if speed == "polygon" else {})))
        solvers: dict[tuple, Any] = {}
        dual_wall, dual_cpu, bare_wall, bare_cpu, evaluations = [], [], [], [], []
        for problem in problems:
            program = reference.program(problem)
            form = clarabel_form(program)
            solver = solvers.get(program.key)
            if solver is None:
                solver = solvers[program.key] = clarabel_solver(program, form)
            else:
                solver.update(P=program.P_upper_values, q=program.q, A=form.matrix.data, b=form.offsets)
            start = clock()
            solver.solve()
            wall, cpu = since(start)
            bare_wall.append(wall)
            bare_cpu.append(cpu)
            start = clock()
            allocation = dual.allocate(problem)
            wall, cpu = since(start)
            dual_wall.append(wall)
            dual_cpu.append(cpu)
            evaluations.append(allocation.info.get("evaluations", 0))
        record: dict[str, Any] = {
            "kind": "small",
            "allocator": dual.name,
            "reference": f"{name} clarabel solve()",
            "n": 8,
            "steps": len(problems),
            "time": statistics.median(dual_wall),
            "cpu_time": statistics.median(dual_cpu),
            "mean_time": statistics.fmean(dual_wall),
            "clarabel_solve": statistics.median(bare_wall),
            "clarabel_solve_cpu": statistics.median(bare_cpu),
            "clarabel_mean": statistics.fmean(bare_wall),
            "ratio": statistics.median(dual_wall) / statistics.median(bare_wall),
            "cpu_ratio": statistics.median(dual_cpu) / statistics.median(bare_cpu),
            "evaluations": statistics.fmean(evaluations),
        }
        records.add(**record)
        records.log(
            f"  n=8 {reading} {speed}: dual {record['time'] * 1e6:.0f} us, Clarabel solve() "
            f"{record['clarabel_solve'] * 1e6:.0f} us, ratio {record['ratio']:.2f} "
            f"(CPU {record['cpu_ratio']:.2f})"
        )
