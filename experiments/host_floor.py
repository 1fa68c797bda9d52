"""The floor of a host-loop step with Clarabel: what a step must cost, whatever the design, when
Clarabel solves on the host (issue 17's target: a closed-loop step at most 1.3x Clarabel's bare
solve). On the qp programs (Clarabel, polygon) of the first 4 s of the paper scenario without
obstacles (n = 8), with one XLA pool thread as a study's workers run, it times per step:

* Clarabel's bare ``solve()``, its numbers updated in place beforehand (the target's unit);
* ``update()`` and ``solve()`` together, the answer copied out: the least a step can do;
* one compiled call per step that takes a small state and the last answer and hands back a
  program's numbers (a design that drives, poses and builds in one call, then solves on the host);
* a compiled ``lax.scan`` whose step calls the host through ``jax.pure_callback``: empty, and
  with Clarabel's update and solve (the whole run in one call, the solver in the callback);
* the model's compiled calls as the host loop makes them (``model_calls``);
* the host loop's step today (``simulate`` with ``qp``, Clarabel);
* that step against Clarabel's bare solve at n = 8 to 200 (``ratio_at``).

Run: ``python experiments/host_floor.py``; results in experiments/host_floor.md.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from platoon_opt.controller import drive_compiled
from platoon_opt.host_loop import _HostSteps, scenario_controller
from platoon_opt.problem import AllocationProblem
from platoon_opt.scenarios import load_scenario
from platoon_opt.simulation import simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.solvers.convex.backends import clarabel_form, clarabel_solver
from platoon_opt.study.bench.cases import closed_loop_problems, convex
from platoon_opt.study.executor import share_cores

REPEATS = 5
# The scenarios and seconds of the ratio against n (``ratio_at``).
LARGER = (("paper_no_obstacles", 4.0), ("curved_field_16", 4.0), ("units_50", 3.0), ("units_200", 2.0))


def median_us(values: list[float]) -> float:
    return statistics.median(values) * 1e6


def model_calls(
    problems: list[AllocationProblem], solver: Any, numbers: tuple[np.ndarray, ...]
) -> tuple[dict[str, float], dict[str, float]]:
    """The model's compiled calls of a host-loop step, medians in us: the problem's pose
    (``AllocationProblem.build``, compiled) and the vehicles' step (``controller.drive_compiled``),
    the two calls of a step before 2026-12-06, and the one call that replaced them
    (``host_loop._HostSteps.moved``: the vehicles' step, the goal and the next pose), each in a
    loop of its own; and that call as the host loop makes it, after Clarabel's update and solve
    of the step's program."""
    scenario = load_scenario("paper_no_obstacles")
    controller = scenario_controller(scenario, get_allocator("qp"), problems[0].obstacles)
    steps = _HostSteps(controller, scenario.goal(controller.task.names), scenario.dt)

    def pose(problem: Any) -> None:
        AllocationProblem.build(
            problem.state,
            problem.task,
            problem.desired,
            problem.desired_rate,
            problem.gains,
            problem.limits,
            problem.dt,
            avoidance=problem.avoidance,
            obstacles=problem.obstacles,
            t=problem.t,
            safety=problem.safety,
            compiled=True,
        )

    def drive(problem: Any) -> None:
        drive_compiled(problem.state, problem.nominal, problem.limits, problem.dt, None)

    def moved(problem: Any) -> None:
        steps.moved(problem.state, problem.nominal, None, problem.t + problem.dt)

    def solve(k: Any) -> None:
        solver.update(**{key: part[k] for key, part in zip("PqAb", numbers)})
        np.array(solver.solve().x)

    tight: dict[str, list[float]] = {"pose": [], "drive": [], "moved": []}
    between: dict[str, list[float]] = {"solve": [], "moved": []}
    for _ in range(REPEATS):
        for name, call in (("pose", pose), ("drive", drive), ("moved", moved)):
            for problem in problems:
                start = time.perf_counter()
                call(problem)
                tight[name].append(time.perf_counter() - start)
        for k, problem in enumerate(problems):
            for name, part, argument in (("solve", solve, k), ("moved", moved, problem)):
                start = time.perf_counter()
                part(argument)
                between[name].append(time.perf_counter() - start)
    return (
        {name: median_us(values) for name, values in tight.items()},
        {name: median_us(values) for name, values in between.items()},
    )


def ratio_at(name: str, seconds: float) -> tuple[int, float, float]:
    """For the scenario ``name`` over its first ``seconds``: n, Clarabel's bare solve of its qp
    programs (the most frequent shape, numbers updated in place beforehand) and the host loop's
    step under ``qp``, medians in us."""
    scenario = load_scenario(name)
    allocator = get_allocator("qp", backend="clarabel")
    problems: list[AllocationProblem] = []

    class Recorder:
        name = "recorder"

        def allocate(self, problem: AllocationProblem) -> Any:
            problems.append(problem)
            return allocator.allocate(problem)

    simulate(scenario, Recorder(), duration=seconds, compiled=False)
    programs = [allocator.program(problem) for problem in problems]
    keys = [program.key for program in programs]
    programs = [program for program in programs if program.key == max(set(keys), key=keys.count)]
    forms = [clarabel_form(program) for program in programs]
    solver = clarabel_solver(programs[0], forms[0])
    bare, loop = [], []
    for _ in range(3):
        for program, form in zip(programs, forms):
            solver.update(P=program.P_upper_values, q=program.q, A=form.matrix.data, b=form.offsets)
            start = time.perf_counter()
            solver.solve()
            bare.append(time.perf_counter() - start)
        start = time.perf_counter()
        trajectory = simulate(scenario, allocator, duration=seconds, compiled=False)
        loop.append((time.perf_counter() - start) / trajectory.steps)
    return scenario.n, median_us(bare), median_us(loop)


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    share_cores(1)
    reference = convex(get_allocator("qp", backend="clarabel"))
    problems = closed_loop_problems(4.0)
    programs = [reference.program(problem) for problem in problems]
    kept = [k for k, program in enumerate(programs) if program.key == programs[0].key]
    problems, programs = [problems[k] for k in kept], [programs[k] for k in kept]
    forms = [clarabel_form(program) for program in programs]
    steps, variables = len(programs), programs[0].variables
    P = np.stack([program.P_upper_values for program in programs])
    q = np.stack([program.q for program in programs])
    A = np.stack([form.matrix.data for form in forms])
    b = np.stack([form.offsets for form in forms])
    solver = clarabel_solver(programs[0], forms[0])
    print(f"{steps} programs of one structure: {variables} variables, {programs[0].K.shape[0]} rows")

    bare, updated = [], []
    for _ in range(REPEATS):
        for k in range(steps):
            solver.update(P=P[k], q=q[k], A=A[k], b=b[k])
            start = time.perf_counter()
            solver.solve()
            bare.append(time.perf_counter() - start)
        for k in range(steps):
            start = time.perf_counter()
            solver.update(P=P[k], q=q[k], A=A[k], b=b[k])
            np.array(solver.solve().x)
            updated.append(time.perf_counter() - start)

    @jax.jit
    def pose(state: dict, answer: jax.Array) -> tuple[dict, tuple]:
        state = {key: value + 1e-3 * answer.sum() for key, value in state.items()}
        scale = state["x"].sum()
        return state, tuple(scale * jnp.ones(part.shape[1]) for part in (P, q, A, b))

    state = {key: jnp.zeros(8) for key in ("x", "y", "theta", "alpha", "gear")}
    answer = np.zeros(variables)
    for _ in range(100):
        state, numbers = pose(state, answer)
    call = []
    for _ in range(REPEATS * steps):
        start = time.perf_counter()
        state, numbers = pose(state, answer)
        numbers = [np.asarray(part) for part in numbers]
        call.append(time.perf_counter() - start)

    shapes = (jax.ShapeDtypeStruct((variables,), jnp.float64),)

    def empty(*_: np.ndarray) -> tuple[np.ndarray]:
        return (np.zeros(variables),)

    def clarabel(Pk: np.ndarray, qk: np.ndarray, Ak: np.ndarray, bk: np.ndarray) -> tuple[np.ndarray]:
        # Copies: the callback's arrays are read-only, and Clarabel's update took 2.5 ms with them.
        solver.update(P=np.array(Pk), q=np.array(qk), A=np.array(Ak), b=np.array(bk))
        return (np.array(solver.solve().x),)

    def scan_time(host) -> float:
        def body(carry, numbers):
            (x,) = jax.pure_callback(host, shapes, *numbers)
            return carry + x.sum(), None

        run = jax.jit(lambda *numbers: jax.lax.scan(body, 0.0, numbers)[0])
        jax.block_until_ready(run(P, q, A, b))
        times = []
        for _ in range(REPEATS):
            start = time.perf_counter()
            jax.block_until_ready(run(P, q, A, b))
            times.append((time.perf_counter() - start) / steps)
        return statistics.median(times) * 1e6

    callback_empty, callback_clarabel = scan_time(empty), scan_time(clarabel)
    tight, interleaved = model_calls(problems, solver, (P, q, A, b))

    scenario = load_scenario("paper_no_obstacles")
    allocator = get_allocator("qp", backend="clarabel")
    simulate(scenario, allocator, duration=0.5)
    loop = []
    for _ in range(3):
        start = time.perf_counter()
        trajectory = simulate(scenario, allocator, duration=4.0)
        loop.append((time.perf_counter() - start) / trajectory.steps)

    unit = median_us(bare)
    rows = [
        ("Clarabel's bare solve()", unit),
        ("update() + solve(), the answer copied", median_us(updated)),
        ("one compiled call: state and answer in, a program's numbers out", median_us(call)),
        ("lax.scan step with an empty pure_callback", callback_empty),
        ("lax.scan step with update() + solve() in a pure_callback", callback_clarabel),
        ("the model's compiled pose (AllocationProblem.build), in a loop of its own", tight["pose"]),
        ("the model's compiled drive, in a loop of its own", tight["drive"]),
        ("the host loop's one call: drive, goal and pose, in a loop of its own", tight["moved"]),
        ("that call, after each update() + solve()", interleaved["moved"]),
        ("update() + solve(), between those calls", interleaved["solve"]),
        ("the host loop's step today (qp, Clarabel)", median_us(loop)),
    ]
    print("| per step | us | / bare solve |\n|---|---|---|")
    for label, value in rows:
        print(f"| {label} | {value:.0f} | {value / unit:.2f}x |")
    print("\n| scenario | n | bare solve (us) | host-loop step (us) | ratio |\n|---|---|---|---|---|")
    for name, seconds in LARGER:
        n, solve, step = ratio_at(name, seconds)
        print(f"| {name} | {n} | {solve:.0f} | {step:.0f} | {step / solve:.2f}x |")


if __name__ == "__main__":
    main()
