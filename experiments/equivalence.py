"""Is the compiled engine the numpy model it replaced? The committed 20-seed study, rerun.

Reruns the configurations of ``results/seeds20`` with today's code (m = 0..8 compiled;
``qp-projection`` and ``cone-projection`` on the host with Clarabel, and through the compiled dual)
and compares each run's metrics to 1e-6 relative: the iteration with ``results.json``, the Clarabel
rows with the old model (commit 0f05fd0, run in a subprocess with that tree on PYTHONPATH; the
committed Clarabel rows predate it), the dual rows with today's Clarabel rows. For each diverging
run it compares the trajectories of both models step by step: the first step where they differ by
more than 1e-12, the largest one-step jump of the difference after that, and the discrete
decisions (gears, precedence flags, Eqs. 6 and 7, nearest obstacle and neighbour, the iteration's
sweeps and gear sides, clips, fallbacks) that differ at that step; and a twin run of the old model
whose initial state differs by 1e-15 in one coordinate. Last, every verdict of the report, from
the committed file, the old model and today's runs (``platoon_opt.study.statistics``).

    git -C /work/main worktree add /tmp/old 0f05fd0
    nice -n 10 python experiments/equivalence.py --old-tree /tmp/old --out /tmp/equivalence

Writes OUT/equivalence.json; finished runs are kept under OUT/runs and OUT/old-runs (a rerun
resumes). The functions that touch the model import ``platoon_opt`` lazily: the script runs itself
under the old tree too (``--old-worker``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

SCENARIOS = ("paper_no_obstacles", "paper_obstacles")
SEEDS = list(range(20))  # the study's; --seeds picks fewer for a trial
ITERATION = tuple(f"m={m}" for m in range(9))
CLARABEL = ("qp-projection", "cone-projection")
DUAL = tuple(f"{c}:backend=dual" for c in CLARABEL)
METRICS = tuple(
    "mean_position mean_position_after_transient var_x var_x_after_transient var_y var_y_after_transient "
    "gear_flips min_clearance min_unit_distance time_inside_obstacles".split()
)
STATE = ("x", "y", "theta", "alpha", "gear")
PERTURBATION = 1e-15  # added to unit 0's x in the old model's twin run


def _spec(run):
    from platoon_opt.scenarios import load_scenario
    from platoon_opt.study.config import parse_config
    from platoon_opt.study.runs import RunSpec
    from platoon_opt.study.variants import BASE

    return RunSpec(load_scenario(run[0]), BASE, parse_config(run[1]), run[2])


def trajectory(job):
    """(run, compiled, perturb): the run's states and metrics, with whichever model is imported."""
    from platoon_opt.metrics import integrated_errors
    from platoon_opt.simulation import simulate
    from platoon_opt.solvers import get_allocator

    run, compiled, perturb = job
    spec = _spec(run)
    kind, initial = type(spec.scenario), type(spec.scenario).initial

    def shifted(self, seed=0):
        state, obstacles = initial(self, seed)
        x = state.x.copy()
        x[0] += perturb
        return type(state)(x, state.y, state.theta, state.alpha, state.gear), obstacles

    kind.initial = shifted
    try:
        extra = {} if compiled is None else {"compiled": compiled}
        track = simulate(spec.scenario, spec.config.build(get_allocator), seed=run[2], **extra)
    finally:
        kind.initial = initial
    scores = integrated_errors(track, spec.scenario.transient)
    return {f: np.asarray(getattr(track, f), dtype=float) for f in STATE}, {k: scores[k] for k in METRICS}


def tracks(jobs):
    """``trajectory`` of every job, in two worker processes."""
    from platoon_opt.study.executor import execute

    done = dict(execute(trajectory, jobs, workers=2))
    return [done[i] for i in range(len(jobs))]


def _wrap(angle):
    return np.pi - np.mod(np.pi - angle, 2 * np.pi)


def decisions(run, step, state):
    """Every discrete decision of the step from ``state``, per unit: {name: (values, margins)}, the
    margin being how far the deciding quantity lies from its threshold (m, rad, m/s or rad/s)."""
    from platoon_opt.controller import PlatoonController
    from platoon_opt.limits import AchievableSets
    from platoon_opt.solvers import get_allocator
    from platoon_opt.vehicle import PlatoonState

    spec = _spec(run)
    sc, lim, av, t = spec.scenario, spec.scenario.limits, spec.scenario.avoidance, step * spec.scenario.dt
    obstacles, task, allocator = sc.initial(run[2])[1], sc.task(), spec.config.build(get_allocator)
    control = PlatoonController(task, sc.gains, lim, allocator, av, obstacles, safety=sc.safety)
    st = PlatoonState(*(np.array(state[k], dtype=float) for k in STATE))
    problem = control.problem(st, *sc.desired_at(task.names, t)[:2], sc.dt, t)
    allocation = control.allocate(problem)
    v, n, out, rows = allocation.velocities, st.n, {}, np.arange(st.n)
    pos = np.stack((st.x, st.y), axis=1)
    if len(obstacles):  # Eq. 6, its precedence flag, the nearest obstacle (only where Eq. 6 acts)
        offset = pos[:, None] - np.asarray(obstacles.centers)[None]
        surface = np.hypot(offset[..., 0], offset[..., 1]) - np.asarray(obstacles.radii)
        order = np.argsort(surface, axis=1)
        d = surface[rows, order[:, 0]]
        away = offset[rows, order[:, 0]] / (d + np.asarray(obstacles.radii)[order[:, 0]])[:, None]
        ref = st.theta if av.ahead_reference == "heading" else st.theta + st.alpha + np.pi * (st.gear < 0)
        cos = -(away[:, 0] * np.cos(ref) + away[:, 1] * np.sin(ref))
        out["Eq. 6 active"] = ((d < av.d_mino) & (cos > 0), np.minimum(abs(d - av.d_mino), abs(cos)))
        near = np.where((d < av.d_mino) & (cos > 0), order[:, 0], -1)
        out["nearest obstacle"] = (near, surface[rows, order[:, 1 % len(obstacles)]] - d)
        out["exempt (obstacle)"] = (d <= av.d_mino / 4, abs(d - av.d_mino / 4))
    gaps = np.hypot(*(pos[:, None, j] - pos[None, :, j] for j in (0, 1))) + np.diag(np.full(n, np.inf))
    order = np.argsort(gaps, axis=1)
    d = gaps[rows, order[:, 0]]
    out["Eq. 7 active"] = (d < av.d_minr, abs(d - av.d_minr))
    out["nearest unit"] = (np.where(d < av.d_minr, order[:, 0], -1), gaps[rows, order[:, 1]] - d)
    out["exempt (unit)"] = (d <= av.d_minr / 8, abs(d - av.d_minr / 8))
    out["exempt"], out["nominal gear"] = (
        (problem.exempt, np.full(n, np.nan)),
        (problem.gear, np.full(n, np.nan)),
    )
    for name, value in (("iterations", allocation.iterations), ("fell back", allocation.fell_back)):
        out[name] = (np.full(1, value), np.full(1, np.nan))
    m = spec.config.iteration_count
    if m:  # the paper's iteration replayed: each sweep's gear side per unit and its convergence test
        sets = AchievableSets.for_gear(st, np.ones(n), lim)
        base, correction, q = problem.jacobian.pinv_apply(problem.task_velocity), 0.0, problem.nominal
        middle = np.stack((np.cos(st.theta), np.sin(st.theta)), axis=1)  # C_i is symmetric about its axis
        for sweep in range(1, m + 1):
            gap = np.where(~problem.exempt[:, None], sets.project_either_gear(q) - q, 0.0)
            along, largest = np.einsum("ij,ij->i", q, middle), np.full(1, np.abs(gap).max())
            out[f"side, sweep {sweep}"] = (np.sign(along) + (along == 0), abs(along))
            out[f"converged, sweep {sweep}"] = (largest <= 1e-9, abs(largest - 1e-9))
            if largest[0] <= 1e-9:
                break
            correction = correction + gap
            q = base + problem.jacobian.null_project(problem.secondary + correction)
    elif m is None:  # a convex program: the answer on its set's edges
        rel, speed = (
            _wrap(np.arctan2(v[:, 1], v[:, 0]) - st.theta - np.pi * (problem.gear < 0)),
            np.hypot(*v.T),
        )
        out["at steering edge"] = (abs(rel) > lim.max_steering - 1e-7, abs(abs(rel) - lim.max_steering))
        out["at speed limit"] = (speed > lim.max_speed - 1e-7, abs(speed - lim.max_speed))
    # The unit controller (Eq. 2) and the step (Eq. 1).
    speed = np.hypot(v[:, 0], v[:, 1])
    error = _wrap(np.arctan2(v[:, 1], v[:, 0]) - _wrap(st.theta + np.pi * (st.gear < 0)))
    switch = (speed > 1e-12) & (abs(error) > np.pi / 2 + lim.gear_hysteresis)
    out["gear switch"] = (switch, abs(abs(error) - np.pi / 2 - lim.gear_hysteresis))
    relative = np.where(switch, error - np.copysign(np.pi, error), error)
    clipped = np.sign(relative) * (abs(relative) > lim.max_steering)
    out["steering target clipped"] = (clipped, abs(abs(relative) - lim.max_steering))
    target = np.where(speed > 0, np.clip(relative, -lim.max_steering, lim.max_steering), st.alpha)
    raw = lim.steering_gain * (target - st.alpha)
    low = np.maximum(-lim.max_steering_rate, (-lim.max_steering - st.alpha) / sc.dt)
    high = np.minimum(lim.max_steering_rate, (lim.max_steering - st.alpha) / sc.dt)
    out["steering rate clipped"] = (
        (raw > high) * 1 - (raw < low),
        np.minimum(abs(raw - low), abs(raw - high)),
    )
    after = st.alpha + np.clip(raw, low, high) * sc.dt
    out["steering clipped in the step"] = (abs(after) > lim.max_steering, abs(abs(after) - lim.max_steering))
    out["speed clipped"] = (speed > lim.max_speed, abs(speed - lim.max_speed))
    return {k: [np.asarray(x, dtype=float).tolist() for x in pair] for k, pair in out.items()}


def old_worker(task_file):
    """Under the old tree: the Clarabel rows' results, trajectories, or decisions (``task["mode"]``)."""
    task = json.loads(Path(task_file).read_text())
    if task["mode"] == "results":
        from platoon_opt.solvers import get_allocator
        from platoon_opt.study.runs import run_specs

        specs = [_spec(run) for run in task["runs"]]
        result = run_specs(specs, get_allocator, runs_dir=task["runs_dir"], workers=2)
    elif task["mode"] == "trajectories":
        done = tracks([(tuple(run), None, perturb) for run, perturb in task["runs"]])
        arrays = {f"{i}|{k}": a for i, (track, _) in enumerate(done) for k, a in track.items()}
        np.savez_compressed(task["npz"], **arrays)
        result = [scores for _, scores in done]
    else:
        with np.load(task["npz"]) as states:
            result = [
                decisions(tuple(r), k, {f: states[f"{i}|{f}"] for f in STATE}) for r, k, i in task["items"]
            ]
    Path(task["out"]).write_text(json.dumps(result))


def _old(args, mode, **task):
    path, order = args.out / f"old-{mode}.json", args.out / f"old-{mode}-task.json"
    order.write_text(json.dumps({"mode": mode, "out": str(path), **task}))
    env = {**os.environ, "PYTHONPATH": str(args.old_tree.resolve())}
    subprocess.run([sys.executable, __file__, "--old-worker", str(order)], env=env, check=True, cwd="/tmp")
    return json.loads(path.read_text())


def relative(new, old):
    new, old = float(new), float(old)
    return 0.0 if new == old else abs(new - old) / max(abs(old), 1e-300)


def difference(a, b):
    """Largest difference of positions, headings and steering per instant (T + 1,), and where the
    gears differ (T + 1,) bool."""
    d = [abs(_wrap(a[k] - b[k])) if k == "theta" else abs(a[k] - b[k]) for k in ("x", "y", "theta", "alpha")]
    return np.max(np.max(d, axis=0), axis=1), (a["gear"] != b["gear"]).any(axis=1)


def parting(d):
    """First instant above 1e-12, the step of the largest one-step jump beyond it, and the growth of
    the difference's envelope between them (steps per factor of 10)."""
    first = int(np.argmax(d > 1e-12)) if (d > 1e-12).any() else None
    ratio = np.where(d[:-1] > 1e-12, d[1:] / np.maximum(d[:-1], 1e-300), 0.0)
    jump = int(np.argmax(ratio))
    envelope = np.log10(np.maximum.accumulate(np.maximum(d, 1e-17)))
    span = np.arange(first, jump + 1) if first is not None and jump - first >= 50 else None
    slope = np.polyfit(span, envelope[span], 1)[0] if span is not None else math.nan
    return dict(first_1e12=first, jump_step=jump, before=float(d[jump]), after=float(d[jump + 1]),
                steps_per_decade=1 / slope if slope > 0 else math.nan, final=float(d[-1]))  # fmt: skip


def differing(a, b):
    """Decisions that differ between two ``decisions`` answers: [(name, unit, a, b, margins)]."""
    found = []
    for name in sorted(set(a) | set(b)):
        (va, ma), (vb, mb) = a.get(name, ([], [])), b.get(name, ([], []))
        for unit in range(max(len(va), len(vb))):
            x, y = (va[unit] if unit < len(va) else None), (vb[unit] if unit < len(vb) else None)
            if x != y and not (x != x and y != y):
                found.append((name, unit, x, y, [m[unit] if unit < len(m) else None for m in (ma, mb)]))
    return found


def verdicts(runs):
    """Every verdict of the report ({name: verdict}), and the numbers it prints beside them."""
    from platoon_opt.metrics import ERROR_METRICS
    from platoon_opt.study.config import parse_config
    from platoon_opt.study.markdown import change_text
    from platoon_opt.study.paper import PAPER_ITERATIONS, PAPER_RESULTS, verdict
    from platoon_opt.study.statistics import RunTable, paired_statistics, roles, summarize

    configs = [parse_config(c) for c in (*ITERATION, *CLARABEL)]
    scenarios = [SimpleNamespace(name=s) for s in SCENARIOS]
    study = SimpleNamespace(baseline=configs[0], configs=configs, scenarios=scenarios, variants=(),
                            seeds=SEEDS, paper_iterations=PAPER_ITERATIONS)  # fmt: skip
    rows = {(r["scenario"], r["config"], r["metric"]): r for r in summarize(study, runs)}
    table, out, printed = RunTable(runs), {}, {}

    def side(low, high):
        return "below 0" if high < 0 else ("above 0" if low > 0 else "contains 0")

    for s in SCENARIOS:
        role = roles(table, study, s)
        best = out[f"{s}: best m"] = role["best_m"].label
        out[f"{s}: best other"] = role["best_other"].label
        for c in (*ITERATION, *CLARABEL):
            for key in ERROR_METRICS:
                row = rows[(s, c, key)]
                out[f"{s}: {c} vs m=0, {key}"] = side(row["change_low"], row["change_high"])
                pair = paired_statistics(*(table.values(s, "base", x, key, SEEDS) for x in (c, best)), None)
                out[f"{s}: {c} vs best m, {key}"] = side(pair["change_low"], pair["change_high"])
                printed[f"{s}: {c} vs m=0, {key}"] = change_text(row)
                printed[f"{s}: {c} wins, {key}"] = f"{row['win_vs_baseline']:.0%}, {row['win_vs_best_m']:.0%}"
        for key, value in PAPER_RESULTS[s]["changes"].items():
            for name, label in (("paper's m", f"m={PAPER_ITERATIONS[s]}"), ("best m", best)):
                row = rows[(s, label, key)]
                text = verdict(row["change"], row["change_low"], row["change_high"], value)
                out[f"{s}: paper, {key} at the {name}"], printed[f"{s}: paper, {key} at the {name}"] = (
                    text.split(" (x")[0],
                    text,
                )
    return out, printed


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--old-tree", type=Path, help="a checkout of 0f05fd0")
    parser.add_argument("--out", type=Path, default=Path("/tmp/equivalence"))
    parser.add_argument("--seeds", type=int, nargs="+", default=SEEDS, help="fewer seeds, for a trial")
    parser.add_argument("--old-worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    SEEDS[:] = args.seeds
    if args.old_worker:
        return old_worker(args.old_worker)
    from platoon_opt.solvers import get_allocator
    from platoon_opt.study.dispatch import run_specs

    args.out.mkdir(parents=True, exist_ok=True)
    clock, report = time.perf_counter(), {}
    runs = [(s, c, seed) for s in SCENARIOS for c in (*ITERATION, *CLARABEL, *DUAL) for seed in SEEDS]
    finished = run_specs([_spec(run) for run in runs], get_allocator, runs_dir=args.out / "runs", workers=2)
    new = {(r["scenario"], r["config"], r["seed"]): r for r in finished}
    report["new_study_s"] = time.perf_counter() - clock
    committed = json.loads((Path(__file__).parents[1] / "results/seeds20/results.json").read_text())["runs"]
    committed = [r for r in committed if r["seed"] in SEEDS]
    reference = {(r["scenario"], r["config"], r["seed"]): r for r in committed if r["config"] in ITERATION}
    clarabel = [run for run in runs if run[1] in CLARABEL]
    reference.update(zip(clarabel, _old(args, "results", runs=clarabel, runs_dir=str(args.out / "old-runs"))))
    report["old_study_s"] = time.perf_counter() - clock - report["new_study_s"]
    # Agreement to 1e-6 relative per run and metric (the dual rows: against today's Clarabel rows).
    counts, diverging = {}, {}
    for run in runs:
        against = reference.get(run) or new[(run[0], run[1].split(":")[0], run[2])]
        rel = {k: relative(new[run][k], against[k]) for k in METRICS}
        count = counts.setdefault(f"{run[0]} {run[1]}", {"agree": 0, "diverge": 0, "worst agreeing": 0.0})
        count["diverge" if max(rel.values()) > 1e-6 else "agree"] += 1
        if max(rel.values()) <= 1e-6:
            count["worst agreeing"] = max(count["worst agreeing"], max(rel.values()))
        elif run[1] not in DUAL:
            diverging[run] = rel
    report["counts"] = counts
    # Each diverging run (and a few agreeing ones) under both models; the old model's twin runs.
    contrast = [(s, c, SEEDS[0]) for s in SCENARIOS for c in ("m=0", "m=4", "qp-projection")]
    studied = list(dict.fromkeys([*diverging, *contrast]))
    jobs = [(run, 0.0) for run in studied] + [(run, PERTURBATION) for run in diverging]
    old_scores = _old(args, "trajectories", runs=jobs, npz=str(args.out / "old.npz"))
    with np.load(args.out / "old.npz") as stored:
        old = [{k: stored[f"{i}|{k}"] for k in STATE} for i in range(len(jobs))]
    states, items, found = {}, [], []
    for i, (run, (mine, scores)) in enumerate(
        zip(studied, tracks([(r, r[1] in ITERATION, 0.0) for r in studied]))
    ):
        d, gear = difference(mine, old[i])
        entry = {
            "run": run,
            "parting": parting(d),
            "gear_differs_at": int(np.argmax(gear)) if gear.any() else None,
        }
        entry["old_vs_reference"] = max(relative(old_scores[i][k], reference[run][k]) for k in METRICS)
        entry["new_vs_study"] = max(relative(scores[k], new[run][k]) for k in METRICS)
        if run in diverging:
            j = len(studied) + list(diverging).index(run)
            entry["twin"] = parting(difference(old[j], old[i])[0])
            entry["twin_change"] = {k: relative(old_scores[j][k], old_scores[i][k]) for k in METRICS}
            entry["change"], entry["first_item"] = diverging[run], len(items)
            k, tw = entry["parting"]["jump_step"], entry["twin"]["jump_step"]
            for step, track in ((k, old[i]), (k, mine), (tw, old[j]), (tw, old[i])):
                states.update({f"{len(items)}|{f}": track[f][step] for f in STATE})
                items.append((run, step, len(items)))
        found.append(entry)
    np.savez(args.out / "states.npz", **states)
    before = _old(args, "decisions", items=items, npz=str(args.out / "states.npz"))
    after = [decisions(run, step, {f: states[f"{i}|{f}"] for f in STATE}) for run, step, i in items]
    pairs = {
        "old model at its state vs new model at its state": lambda i: (before[i], after[i + 1]),
        "both models at the old state": lambda i: (before[i], after[i]),
        "both models at the new state": lambda i: (before[i + 1], after[i + 1]),
        "old model at the twin's state vs at its own": lambda i: (before[i + 2], before[i + 3]),
    }
    for entry in (e for e in found if "twin" in e):
        first = entry.pop("first_item")
        entry["decisions"] = {name: differing(*pair(first)) for name, pair in pairs.items()}
    report["trajectories"] = found
    report["trajectory_s"] = time.perf_counter() - clock - report["new_study_s"] - report["old_study_s"]
    # Verdicts: the committed file; the old model (committed iteration rows, Clarabel at 0f05fd0); today.
    today = [r for r in new.values() if r["config"] not in DUAL]
    dual = [{**r, "config": r["config"].split(":")[0]} for r in new.values() if r["config"] not in CLARABEL]
    sets = {
        "committed": committed,
        "old model": list(reference.values()),
        "today": today,
        "today, dual": dual,
    }
    judged = {name: verdicts(rs) for name, rs in sets.items()}
    report["verdicts"] = {}
    for a, b in (("committed", "today"), ("old model", "today"), ("today", "today, dual")):
        (va, pa), (vb, pb) = judged[a], judged[b]
        report["verdicts"][f"{a} -> {b}"] = {
            "verdicts": len(va),
            "changed": [(k, va[k], vb[k]) for k in va if va[k] != vb[k]],
            "printed changed": [(k, pa[k], pb[k]) for k in pa if pa[k] != pb[k]],
        }
    report["wall_s"] = time.perf_counter() - clock
    (args.out / "equivalence.json").write_text(json.dumps(report, indent=1, default=str))
    print(json.dumps({k: report[k] for k in ("new_study_s", "old_study_s", "trajectory_s", "wall_s")}))


if __name__ == "__main__":
    main()
