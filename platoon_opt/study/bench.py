"""Speed and scale: the allocators from 8 to 100,000 units, the whole control step, and the
closed loop (issue 5). ``run(out_dir)`` writes ``bench.json``, ``bench.md`` and ``bench.png``;
``platoon-opt bench`` calls it.

Everything runs in one process, so that every allocator meets the same machine state; each
figure is a median over repetitions. Wall-clock times (``time.perf_counter``) are reported,
with the CPU time of the process (``time.process_time``) beside them: on a machine shared
with other jobs the wall time includes waiting for a core, the CPU time does not. The load
average before and after the run is recorded.

Parts:

* **scale**: for n = 8 ... 32,768 (and 100,000 for the dual), random problems at a fixed
  density (``scale_problem``): each allocator's time per allocation, its build (posing the
  program) and bare solve separately, its ratio to the dual solving the same program, the
  largest relative difference of its objective from the dual's, and the peak memory of one
  allocation (``tracemalloc``: numpy and Python objects; the native workspaces of Clarabel
  and OSQP are not seen).
* **step**: the whole control step with the dual (nominal velocity and repulsion, allocation,
  unit controllers and vehicles) over consecutive steps of a platoon tracking its target, each
  allocation warm-started from the previous step's, as in a simulation; time and peak memory,
  and the floor: one vectorized pass over the state.
* **small**: n = 8 along the paper scenario's closed loop: the dual's allocation against
  Clarabel's bare solve of the same program (solver updated in place, ``solve()`` alone).
* **closed_loop**: the paper scenario (no obstacles) simulated under each allocator:
  simulated seconds per wall second.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from platoon_opt import (
    AllocationProblem,
    MeanVarianceTask,
    PlatoonState,
    VehicleLimits,
    load_scenario,
    simulate,
)
from platoon_opt.controller import PlatoonController
from platoon_opt.problem import Allocation, Allocator
from platoon_opt.solvers.convex.backends import clarabel_form, clarabel_solver, osqp_solver
from platoon_opt.study.machine import load_average, machine
from platoon_opt.vehicle import step_vehicles, unit_controller

SIZES = (8, 64, 512, 4096, 32768)
DUAL_ONLY_SIZES = (100_000,)
# Mean spacing of the units in scale problems (m): neighbours within d_minr = 1 m are common.
SPACING = 1.5
# A QP allocator whose single allocation took longer than this (s) is not run at larger n.
BUDGET = 30.0


@dataclass(frozen=True)
class Entry:
    """One allocator configuration of the benchmark.

    Attributes:
        label: name in the tables.
        name, options: ``get_allocator(name, **options)``.
        reading, speed: the program it solves (its dual counterpart solves the same one;
            reading "strict": the achievable-first reading under strict priority).
        backend: "dual", "clarabel" or "osqp".
        sizes: problem sizes it is run at (None: every size of the run but dual-only ones).
    """

    label: str
    name: str
    options: dict[str, Any]
    reading: str
    speed: str
    backend: str
    sizes: tuple[int, ...] | None = None

    def build(self) -> Allocator:
        from platoon_opt.solvers import get_allocator

        return get_allocator(self.name, **self.options)


def entries() -> list[Entry]:
    """The allocators measured: the dual in its four programs and under strict priority, and the
    QP allocators that pose the same programs (OSQP at its exact settings, eps 1e-9, for the
    polygon)."""
    af, te = "achievable-first", "task-exact"
    return [
        Entry("dual", "dual", {}, af, "polygon", "dual"),
        Entry("dual cone", "dual", {"speed": "cone"}, af, "cone", "dual"),
        Entry("dual task-exact", "dual", {"reading": te}, te, "polygon", "dual"),
        Entry("dual task-exact cone", "dual", {"reading": te, "speed": "cone"}, te, "cone", "dual"),
        Entry("qp clarabel", "qp", {"backend": "clarabel"}, af, "polygon", "clarabel"),
        Entry("qp osqp", "qp", {"backend": "osqp"}, af, "polygon", "osqp"),
        Entry("cone clarabel", "cone", {}, af, "cone", "clarabel"),
        Entry("qp-projection clarabel", "qp-projection", {"backend": "clarabel"}, te, "polygon", "clarabel"),
        # OSQP needs minutes for the task-exact program beyond a few hundred units.
        Entry(
            "qp-projection osqp", "qp-projection", {"backend": "osqp"}, te, "polygon", "osqp", (8, 64, 512)
        ),
        Entry("cone-projection clarabel", "cone-projection", {}, te, "cone", "clarabel"),
        # Strict priority: Wolfe's stage 1, then the penalized second stage; QP: two programs.
        Entry("dual strict", "dual", {"priority": "strict"}, "strict", "polygon", "dual"),
        Entry(
            "qp strict clarabel",
            "qp",
            {"backend": "clarabel", "priority": "strict"},
            "strict",
            "polygon",
            "clarabel",
        ),
    ]


def repetitions(n: int, backend: str) -> int:
    """Repetitions per size: fewer where one call takes seconds."""
    if backend == "dual":
        return 21 if n <= 4096 else 7
    return 15 if n <= 512 else (5 if n <= 4096 else 2)


def scale_problem(n: int, seed: int) -> AllocationProblem:
    """A platoon of n units spread uniformly at mean spacing ``SPACING`` with random headings,
    tracking a target that moves at 0.8 m/s, 5 mm off the mean and 0.5 % off the variances:
    a mix of achievable, steering-limited and speed-limited nominal velocities."""
    rng = np.random.default_rng(seed)
    side = SPACING * math.sqrt(n)
    limits = VehicleLimits()
    state = PlatoonState(
        x=rng.uniform(0, side, n),
        y=rng.uniform(0, side, n),
        theta=rng.uniform(-np.pi, np.pi, n),
        alpha=rng.uniform(-limits.max_steering, limits.max_steering, n),
        gear=np.ones(n),
    )
    task = MeanVarianceTask()
    value = task.value(state.positions)
    offset = np.array([0.005, 0.005 * value[1], -0.005, -0.005 * value[3]])
    return AllocationProblem.build(
        state,
        task,
        value + offset,
        np.array([0.8, 0.0, 0.0, 0.0]),
        np.array([50.0, 10, 50, 10]),
        limits,
        0.01,
    )


def _clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def _since(start: tuple[float, float]) -> tuple[float, float]:
    wall, cpu = _clock()
    return wall - start[0], cpu - start[1]


def peak_memory(call: Callable[[], Any]) -> float:
    """Peak of traced memory (MB) during ``call()``: numpy arrays and Python objects."""
    tracemalloc.start()
    try:
        call()
        return tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


def _qp_parts(
    allocator, problem: AllocationProblem, backend: str, allocation: Allocation
) -> tuple[float, float]:
    """Build and bare-solve times (s) of a QP allocator's program: posing it
    (``ConvexAllocator.program``) and setting the native solver up, then the solver's ``solve()``
    alone, on a fresh solver object; under strict priority both stages, the second toward the
    allocation's stage-1 task velocity."""
    stages = [("joint", None)]
    if getattr(allocator, "priority", "weighted") == "strict":
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


@dataclass
class Bench:
    """Collects the records of one run."""

    records: list[dict[str, Any]] = field(default_factory=list)
    log: Callable[[str], None] = print

    def add(self, **record: Any) -> None:
        self.records.append(record)


def run_scale(bench: Bench, sizes: tuple[int, ...], dual_only: tuple[int, ...]) -> None:
    """Time per allocation, build and solve, ratio to the dual and memory, per allocator and n."""
    skipped: dict[str, str] = {}
    for n in (*sizes, *dual_only):
        count = max(repetitions(n, "dual"), repetitions(n, "clarabel"))
        problems = [scale_problem(n, seed) for seed in range(count)]
        dual_times: dict[tuple[str, str], float] = {}
        dual_objectives: dict[tuple[str, str], list[float]] = {}
        for entry in entries():
            if entry.backend != "dual" and (n in dual_only or (entry.sizes and n not in entry.sizes)):
                continue
            if entry.label in skipped:
                bench.add(kind="scale", allocator=entry.label, n=n, skipped=skipped[entry.label])
                continue
            reps = repetitions(n, entry.backend)
            allocator = entry.build()
            if entry.backend == "dual" or n <= 4096:
                allocator.allocate(problems[-1])  # first call: imports, caches, workspaces
            walls, cpus, builds, solves, objectives, statuses, evaluations = [], [], [], [], [], set(), []
            for problem in problems[:reps]:
                start = _clock()
                allocation = allocator.allocate(problem)
                wall, cpu = _since(start)
                walls.append(wall)
                cpus.append(cpu)
                objectives.append(float(allocation.info.get("objective", math.nan)))
                statuses.add(allocation.status.split("->")[0][:60])
                if entry.backend == "dual":
                    builds.append(allocation.info["build_time"])
                    solves.append(allocation.solve_time - allocation.info["build_time"])
                    evaluations.append(allocation.info.get("evaluations", 0))
                else:
                    build, solve = _qp_parts(allocator, problem, entry.backend, allocation)
                    builds.append(build)
                    solves.append(solve)
            memory = peak_memory(lambda allocator=allocator, problem=problems[0]: allocator.allocate(problem))
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
            bench.add(**record)
            bench.log(
                f"  n={n:>6} {entry.label:<26} {median * 1e3:10.3f} ms"
                + (f"  x{_ratio(record['ratio_to_dual'])} dual" if "ratio_to_dual" in record else "")
            )
            if entry.backend != "dual" and max(walls) > BUDGET:
                skipped[entry.label] = (
                    f"one allocation took {max(walls):.0f} s at n={n} (budget {BUDGET:.0f} s)"
                )


def _control_step(
    controller: PlatoonController, state: PlatoonState, problem: AllocationProblem, step: int
) -> tuple[tuple[float, float, float], PlatoonState]:
    """Control step ``step`` of a platoon tracking ``problem``'s target from ``state``: times (s)
    of posing the problem (task, Jacobian, repulsion, nominal velocity), of the allocation
    (warm-started from the previous step's), and of the unit controllers and vehicles; and
    the state after the step."""
    limits, dt = problem.limits, problem.dt
    t = problem.t + step * dt
    start = time.perf_counter()
    desired = problem.desired + step * dt * problem.desired_rate
    posed = controller.problem(state, desired, problem.desired_rate, dt, t)
    posed_at = time.perf_counter()
    allocation = controller.allocate(posed)
    allocated_at = time.perf_counter()
    after = step_vehicles(state, unit_controller(state, allocation.velocities, limits, dt), limits, dt)
    return (posed_at - start, allocated_at - posed_at, time.perf_counter() - allocated_at), after


def run_step(bench: Bench, sizes: tuple[int, ...]) -> None:
    """The whole control step with the dual along a closed loop (consecutive steps of a
    platoon tracking its target, each allocation warm-started from the previous step's), and
    the floor, per n."""
    from platoon_opt.solvers import get_allocator

    for n in sizes:
        reps = 15 if n <= 4096 else 5
        problem = scale_problem(n, 0)
        controller = PlatoonController(
            task=problem.task,
            gains=np.array([50.0, 10, 50, 10]),
            limits=problem.limits,
            allocator=get_allocator("dual"),
        )
        _, state = _control_step(controller, problem.state, problem, 0)  # cold start, not timed
        parts = []
        for step in range(1, reps + 1):
            times, state = _control_step(controller, state, problem, step)
            parts.append(times)
        parts = np.array(parts)
        x, y, out = problem.state.x, problem.state.y, np.empty(n)
        floor = []
        for _ in range(reps):
            start = time.perf_counter()
            np.add(x, y, out=out)
            floor.append(time.perf_counter() - start)
        medians = np.median(parts, axis=0)
        record = {
            "kind": "step",
            "allocator": "dual",
            "n": n,
            "repetitions": reps,
            "problem": float(medians[0]),
            "allocate": float(medians[1]),
            "vehicles": float(medians[2]),
            "time": float(np.median(parts.sum(axis=1))),
            "floor": statistics.median(floor),
            "peak_memory_mb": peak_memory(
                lambda controller=controller, state=state, problem=problem, step=reps + 1: _control_step(
                    controller, state, problem, step
                )
            ),
        }
        bench.add(**record)
        bench.log(
            f"  n={n:>6} control step {record['time'] * 1e3:9.3f} ms (problem {medians[0] * 1e3:.3f}, "
            f"allocation {medians[1] * 1e3:.3f}, vehicles {medians[2] * 1e3:.3f}), "
            f"floor {record['floor'] * 1e6:.1f} us, peak {record['peak_memory_mb']:.1f} MB"
        )


def closed_loop_problems(duration: float) -> list[AllocationProblem]:
    """The problems of every step of the paper scenario (no obstacles) under the dual."""
    from platoon_opt.solvers import get_allocator

    problems: list[AllocationProblem] = []
    dual = get_allocator("dual")

    class Recorder:
        name = "recorder"

        def allocate(self, problem: AllocationProblem):
            problems.append(problem)
            return dual.allocate(problem)

    simulate(load_scenario("paper_no_obstacles"), Recorder(), duration=duration)
    return problems


def run_small(bench: Bench, duration: float) -> None:
    """n = 8 along the closed loop: the dual's allocation (warm-started step to step, as in the
    loop) against Clarabel's bare ``solve()`` of the same program, updated in place."""
    from platoon_opt.solvers import get_allocator

    problems = closed_loop_problems(duration)
    for reading, speed, name in (
        ("achievable-first", "polygon", "qp"),
        ("achievable-first", "cone", "cone"),
        ("task-exact", "polygon", "qp-projection"),
        ("task-exact", "cone", "cone-projection"),
    ):
        dual = get_allocator("dual", reading=reading, speed=speed)
        reference = get_allocator(name, **({"backend": "clarabel"} if speed == "polygon" else {}))
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
            start = _clock()
            solver.solve()
            wall, cpu = _since(start)
            bare_wall.append(wall)
            bare_cpu.append(cpu)
            start = _clock()
            allocation = dual.allocate(problem)
            wall, cpu = _since(start)
            dual_wall.append(wall)
            dual_cpu.append(cpu)
            evaluations.append(allocation.info.get("evaluations", 0))
        record = {
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
        bench.add(**record)
        bench.log(
            f"  n=8 {reading} {speed}: dual {record['time'] * 1e6:.0f} us, Clarabel solve() "
            f"{record['clarabel_solve'] * 1e6:.0f} us, ratio {record['ratio']:.2f} "
            f"(CPU {record['cpu_ratio']:.2f})"
        )


def run_closed_loop(bench: Bench, duration: float) -> None:
    """Simulated seconds per wall second of the paper scenario (no obstacles) per allocator."""
    from platoon_opt.solvers import get_allocator

    scenario = load_scenario("paper_no_obstacles")
    configs = [(entry.label, entry.build) for entry in entries() if entry.label != "qp-projection osqp"]
    configs.append(("iterative m=4", lambda: get_allocator("iterative", max_iterations=4)))
    for label, build in configs:
        allocator = build()
        start = _clock()
        trajectory = simulate(scenario, allocator, duration=duration)
        wall, cpu = _since(start)
        record = {
            "kind": "closed_loop",
            "allocator": label,
            "scenario": scenario.name,
            "n": scenario.n,
            "simulated": duration,
            "wall": wall,
            "cpu": cpu,
            "speed": duration / wall,
            "cpu_speed": duration / cpu,
            "allocation_median": float(np.median(trajectory.solve_time)),
            "fell_back": int(np.count_nonzero(trajectory.fell_back)),
        }
        bench.add(**record)
        bench.log(f"  {label:<26} {record['speed']:6.1f} x real time (CPU: {record['cpu_speed']:.1f} x)")


def _ratio(value: float) -> str:
    return f"{value:.2g}" if value < 10 else f"{value:,.0f}"


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.3g}" if seconds < 1 else f"{seconds * 1e3:,.0f}"


def markdown(result: dict[str, Any]) -> str:
    """The tables of a run (bench.json) in markdown."""
    records = result["records"]
    info = result["machine"]
    lines = [
        f"Machine: {info['cpu']}, {info['cores']} cores; load average {result['load_before']:.1f} before, "
        f"{result['load_after']:.1f} after; Python {info['python']}, numpy {info['numpy']}, "
        f"Clarabel {info['clarabel']}, OSQP {info['osqp']}. Times are wall-clock medians (ms).",
        "",
    ]
    scale = [r for r in records if r["kind"] == "scale" and "time" in r]
    labels = list(dict.fromkeys(r["allocator"] for r in scale))
    sizes = sorted({r["n"] for r in scale})
    by = {(r["allocator"], r["n"]): r for r in scale}
    lines += ["**Time per allocation (ms) and ratio to the dual on the same program**", ""]
    lines.append("| allocator | " + " | ".join(f"n = {n:,}" for n in sizes) + " |")
    lines.append("|---|" + "---|" * len(sizes))
    for label in labels:
        cells = []
        for n in sizes:
            r = by.get((label, n))
            if r is None:
                cells.append("")
            else:
                ratio = f" (x{_ratio(r['ratio_to_dual'])})" if "ratio_to_dual" in r else ""
                cells.append(_ms(r["time"]) + ratio)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "**Build / bare solve (ms) and peak traced memory (MB) per allocation**", ""]
    lines.append("| allocator | " + " | ".join(f"n = {n:,}" for n in sizes) + " |")
    lines.append("|---|" + "---|" * len(sizes))
    for label in labels:
        cells = []
        for n in sizes:
            r = by.get((label, n))
            cells.append(
                "" if r is None else f"{_ms(r['build'])} / {_ms(r['solve'])}, {r['peak_memory_mb']:.1f} MB"
            )
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    steps = [r for r in records if r["kind"] == "step"]
    if steps:
        lines += ["", "**Whole control step with the dual, consecutive steps (ms)**", ""]
        lines.append(
            "| n | problem (nominal, repulsion) | allocation | vehicles | step | floor (1 pass) | peak MB |"
        )
        lines.append("|---|---|---|---|---|---|---|")
        for r in steps:
            lines.append(
                f"| {r['n']:,} | {_ms(r['problem'])} | {_ms(r['allocate'])} | {_ms(r['vehicles'])} | "
                f"{_ms(r['time'])} | {r['floor'] * 1e3:.4f} | {r['peak_memory_mb']:.1f} |"
            )
    small = [r for r in records if r["kind"] == "small"]
    if small:
        lines += [
            "",
            f"**n = 8 along the closed loop ({small[0]['steps']} steps): "
            "dual vs Clarabel's bare solve (us)**",
            "",
        ]
        lines.append(
            "| dual allocator | Clarabel solve() of | dual (median) | solve() (median) | ratio | CPU ratio "
            "| passes |"
        )
        lines.append("|---|---|---|---|---|---|---|")
        for r in small:
            lines.append(
                f"| {r['allocator']} | {r['reference']} | {r['time'] * 1e6:.0f} | "
                f"{r['clarabel_solve'] * 1e6:.0f} | {r['ratio']:.2f} | {r['cpu_ratio']:.2f} | "
                f"{r['evaluations']:.2f} |"
            )
    loops = [r for r in records if r["kind"] == "closed_loop"]
    if loops:
        lines += ["", f"**Closed loop, {loops[0]['scenario']} ({loops[0]['simulated']:g} s simulated)**", ""]
        lines.append("| allocator | x real time | x real time (CPU) | allocation median (ms) | fallbacks |")
        lines.append("|---|---|---|---|---|")
        for r in loops:
            lines.append(
                f"| {r['allocator']} | {r['speed']:.1f} | {r['cpu_speed']:.1f} | "
                f"{r['allocation_median'] * 1e3:.3f} | {r['fell_back']} |"
            )
    return "\n".join(lines) + "\n"


def plot(result: dict[str, Any], path: Path) -> None:
    """Log-log time per allocation against n, with the control step and the floor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = result["records"]
    figure, axes = plt.subplots(figsize=(8, 5.5))
    scale = [r for r in records if r["kind"] == "scale" and "time" in r]
    for label in dict.fromkeys(r["allocator"] for r in scale):
        points = sorted((r["n"], r["time"]) for r in scale if r["allocator"] == label)
        style = "-" if label.startswith("dual") else "--"
        axes.loglog(*zip(*points), style, marker="o", markersize=3, label=label)
    steps = sorted((r["n"], r["time"], r["floor"]) for r in records if r["kind"] == "step")
    if steps:
        n, step, floor = zip(*steps)
        axes.loglog(n, step, "k-", linewidth=2, label="control step (dual)")
        axes.loglog(n, floor, "k:", label="floor: one pass over the state")
    axes.set_xlabel("units n")
    axes.set_ylabel("time (s)")
    axes.set_title(
        f"Allocation time against n ({result['machine']['cpu']}, {result['machine']['cores']} cores)"
    )
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7, ncol=2)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def _write(path: Path, text: str) -> None:
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    temporary.replace(path)


def run(
    out_dir: str | Path = "benchmarks/results",
    *,
    sizes: tuple[int, ...] = SIZES,
    dual_only: tuple[int, ...] = DUAL_ONLY_SIZES,
    small_duration: float = 10.0,
    closed_loop_duration: float = 20.0,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run every part and write ``bench.json``, ``bench.md`` and ``bench.png`` to ``out_dir``.

    Args:
        sizes: problem sizes of the scale and step parts; ``dual_only``: sizes for the dual alone.
        small_duration: seconds of the paper scenario whose steps are the n = 8 comparison.
        closed_loop_duration: seconds of the paper scenario simulated per allocator.

    Returns:
        The run: machine, load, arguments and records (as written to bench.json).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bench = Bench(log=log)
    load_before = load_average()
    started = time.perf_counter()
    log("scale: allocation time per n")
    run_scale(bench, sizes, dual_only)
    log("step: the whole control step with the dual")
    run_step(bench, (*sizes, *dual_only))
    log("small: n = 8 along the closed loop")
    run_small(bench, small_duration)
    log("closed loop: the paper scenario")
    run_closed_loop(bench, closed_loop_duration)
    result = {
        "machine": machine(),
        "load_before": load_before,
        "load_after": load_average(),
        "duration": time.perf_counter() - started,
        "command": " ".join(sys.argv),
        "arguments": {
            "sizes": list(sizes),
            "dual_only": list(dual_only),
            "small_duration": small_duration,
            "closed_loop_duration": closed_loop_duration,
        },
        "records": bench.records,
    }
    _write(out / "bench.json", json.dumps(result, indent=1))
    _write(out / "bench.md", markdown(result))
    plot(result, out / "bench.png")
    log(f"wrote {out}/bench.json, bench.md, bench.png in {result['duration']:.0f} s")
    return result


if __name__ == "__main__":
    run(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results")
