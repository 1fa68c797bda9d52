"""The comparison harness: statistics, identical results serial / parallel / Dask, resuming
after a kill, and a short-horizon smoke run of the whole report."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from platoon_opt import integrated_errors, load_scenario, simulate, simulate_batch
from platoon_opt.scenarios import SCENARIO_DIR
from platoon_opt.solvers import available_allocators, get_allocator
from platoon_opt.study import battery
from platoon_opt.study.batches import plan_batches
from platoon_opt.study.battery import battery_study
from platoon_opt.study.cli import main
from platoon_opt.study.config import AllocatorConfig, iterative_configs, parse_config
from platoon_opt.study.dispatch import run_specs
from platoon_opt.study.paper import reproduce_configs, verdict
from platoon_opt.study.runs import TIMING_FIELDS, RunSpec
from platoon_opt.study.statistics import paired_statistics
from platoon_opt.study.tracks import load_track, thin
from platoon_opt.study.variants import BASE, Variant

ROOT = Path(__file__).resolve().parents[2]


def _specs(configs, seeds, duration=1.0, scenario="paper_obstacles"):
    loaded = load_scenario(scenario)
    return [RunSpec(loaded, BASE, c, s, duration) for c in configs for s in seeds]


def _deterministic(result):
    return {k: v for k, v in result.items() if k not in TIMING_FIELDS}


def _refuse(name, **options):
    raise AssertionError(f"run {name} {options} was recomputed")


def test_parse_config_reads_m_names_and_options():
    assert parse_config("m=3") == AllocatorConfig.make("iterative", "m=3", max_iterations=3)
    config = parse_config("qp:rho=100,backend=osqp")
    assert config.name == "qp" and dict(config.options) == {"rho": 100, "backend": "osqp"}
    assert config.label == "qp:backend=osqp,rho=100"
    config = parse_config("nmpc:task_weights=(4,1,4,1),shadow_weight=0.1")
    assert dict(config.options) == {"task_weights": (4, 1, 4, 1), "shadow_weight": 0.1}
    for bad in ("qp:rho", "q p", "qp:1x=2"):
        with pytest.raises(ValueError, match="must look like"):
            parse_config(bad)


def test_variants_change_only_their_choice():
    scenario = load_scenario("paper_obstacles")
    plain = Variant("x", gear_hysteresis_deg=0.0).apply(scenario)
    assert plain.limits.gear_hysteresis == 0.0 and plain.dt == scenario.dt
    assert plain.avoidance == scenario.avoidance
    assert Variant("x", dt_scale=0.5).apply(scenario).dt == scenario.dt / 2
    assert Variant("x", ahead_reference="travel").apply(scenario).avoidance.ahead_reference == "travel"
    assert not Variant("x", ahead_reference="travel").affects(load_scenario("paper_no_obstacles"))
    assert (
        RunSpec(scenario, BASE, parse_config("m=0"), 0).fingerprint()
        != RunSpec(scenario, Variant("x", dt_scale=0.5), parse_config("m=0"), 0).fingerprint()
    )


def test_paired_statistics_by_hand():
    values, baseline, best = np.array([1.0, 2.0, 3.0]), np.array([2.0, 2.0, 4.0]), np.array([1.0, 1.0, 1.0])
    result = paired_statistics(values, baseline, best)
    mean_0 = 8 / 3
    assert result["mean"] == pytest.approx(2.0)
    assert result["change"] == pytest.approx(100 * (2.0 - mean_0) / mean_0)  # -25 %
    half = 4.302652729911275 * np.std([-1.0, 0.0, -1.0], ddof=1) / math.sqrt(3)  # t(0.975, 2)
    assert result["change_low"] == pytest.approx(100 * (-2 / 3 - half) / mean_0)
    assert result["change_high"] == pytest.approx(100 * (-2 / 3 + half) / mean_0)
    assert result["median_change"] == pytest.approx(-25.0)  # of -50, 0, -25
    assert result["win_vs_baseline"] == pytest.approx(2.5 / 3)  # a tie counts one half
    assert result["win_vs_best_m"] == pytest.approx(0.5 / 3)
    clearance = paired_statistics(values, baseline, None, lower_is_better=False)
    assert clearance["win_vs_baseline"] == pytest.approx(0.5 / 3) and math.isnan(clearance["win_vs_best_m"])
    assert verdict(-50.0, -60.0, -40.0, -53.6).startswith("direction yes; same order")
    assert verdict(-5.0, -9.0, 2.0, -53.6).startswith("direction unclear; smaller")
    assert verdict(20.0, 10.0, 30.0, -50.0).startswith("direction no; opposite sign")


def test_parallel_runs_equal_a_serial_run():
    specs = _specs(iterative_configs([0, 3]), [0, 1])
    serial = run_specs(specs, get_allocator, workers=1)
    parallel = run_specs(specs, get_allocator, workers=2)
    assert [r["key"] for r in parallel] == [s.key for s in specs]
    assert [_deterministic(r) for r in parallel] == [_deterministic(r) for r in serial]


def test_every_batch_has_one_size_and_the_first_batches_come_first():
    iteration = _specs(iterative_configs([0, 3]), [0, 1, 2, 3, 4])  # one group of 10 runs
    dual = _specs([AllocatorConfig("dual")], [0, 1, 2])  # another of 3
    qp = _specs([AllocatorConfig("qp")], [0])  # the host's
    specs = [dataclasses.replace(spec, keep_track=spec.seed == 0) for spec in iteration + dual + qp]
    batches, host = plan_batches(specs, get_allocator, size=4)
    assert host == [13]
    # Seed 0 of m = 0 and m = 3 (runs 0 and 5) keeps its trajectory: one tracked run at most in
    # each of the iteration's batches.
    assert batches == [((0, 1, 2, 3), 4, 1), ((10, 11, 12), 4, 1), ((4, 5, 6), 4, 1), ((7, 8, 9), 4, 1)]


def test_a_runs_numbers_do_not_depend_on_the_study_around_it():
    # XLA rounds differently in programs compiled for different batch sizes, and paper_obstacles
    # under the cone dual grows that into other trajectories: a run must not depend on how many
    # seeds or workers its study has.
    config = [parse_config("cone-projection:backend=dual")]
    few = run_specs(_specs(config, range(8), duration=2.0), get_allocator, workers=1)
    many = run_specs(_specs(config, range(40), duration=2.0), get_allocator, workers=1)
    assert {r["path"] for r in few + many} == {"compiled"}
    assert [_deterministic(r) for r in few] == [_deterministic(r) for r in many[:8]]
    # The library's batch call runs its seeds as a study does.
    scores = simulate_batch(
        load_scenario("paper_obstacles"), config[0].build(get_allocator), range(8), duration=2.0
    )
    for result, score in zip(few, scores):
        assert all(result[key] == score[key] for key in ("mean_position", "var_x", "var_y", "gear_flips"))


def test_batched_runs_equal_their_platoons_in_the_host_loop():
    specs = _specs(iterative_configs([0, 3]), [0, 1, 2], duration=1.5)
    qp = _specs([AllocatorConfig("qp")], [0], duration=0.3)
    results = run_specs(specs + qp, get_allocator, workers=1)
    assert [r["path"] for r in results] == ["compiled"] * len(specs) + ["host"]
    for spec, result in zip(specs, results):
        alone = integrated_errors(
            simulate(
                spec.scenario, spec.config.build(get_allocator), seed=spec.seed, duration=1.5, compiled=False
            )
        )
        for key in ("mean_position", "var_x", "var_y", "min_unit_distance", "min_clearance"):
            assert result[key] == pytest.approx(alone[key], rel=1e-12), key
        assert result["gear_flips"] == alone["gear_flips"]


def test_dask_cluster_runs_equal_a_serial_run():
    distributed = pytest.importorskip("distributed")
    specs = _specs(iterative_configs([0, 2]), [0, 1], duration=0.5)
    serial = run_specs(specs, get_allocator, workers=1)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        on_cluster = run_specs(specs, get_allocator, scheduler=cluster.scheduler_address)
    assert [_deterministic(r) for r in on_cluster] == [_deterministic(r) for r in serial]


def test_finished_runs_are_reused_and_changed_runs_recomputed(tmp_path):
    specs = _specs(iterative_configs([0, 1]), [0], duration=0.3)
    first = run_specs(specs, get_allocator, runs_dir=tmp_path, workers=1)
    # As JSON: a compiled run's allocation time is nan (not timed apart from its step).
    assert json.dumps(run_specs(specs, _refuse, runs_dir=tmp_path, workers=1)) == json.dumps(first)
    longer = _specs(iterative_configs([0]), [0], duration=0.4)
    assert run_specs(longer, get_allocator, runs_dir=tmp_path, workers=1)[0]["steps"] == 40


def test_thinned_track_round_trips(tmp_path):
    scenario = load_scenario("paper_obstacles")
    # Seed 1 keeps its track within the batch of the three seeds (recorded in the batch's call).
    specs = [
        RunSpec(scenario, BASE, parse_config("m=2"), seed, 0.5, keep_track=seed == 1) for seed in (0, 1, 2)
    ]
    run_specs(specs, get_allocator, runs_dir=tmp_path, workers=1)
    assert [(tmp_path / f"{spec.key}.npz").exists() for spec in specs] == [False, True, False]
    track = load_track(tmp_path / f"{specs[1].key}.npz")
    full = thin(simulate(scenario, get_allocator("iterative", max_iterations=2), seed=1, duration=0.5), 5)
    assert track.steps == full.steps == 10 and track.dt == pytest.approx(0.05)
    np.testing.assert_array_equal(track.x, full.x)
    np.testing.assert_array_equal(track.obstacles.centers, full.obstacles.centers)
    assert list(track.status) == list(full.status) and track.task_names == full.task_names
    np.testing.assert_array_equal(track.solved, full.solved)
    # A track kept before steps recorded whether they solved: every step did.
    with np.load(tmp_path / f"{specs[1].key}.npz") as data:
        older = {name: data[name] for name in data.files if name != "solved"}
    np.savez_compressed(tmp_path / "older.npz", **older)
    assert load_track(tmp_path / "older.npz").solved.all()


def test_a_killed_study_resumes_without_losing_finished_runs(tmp_path):
    out = tmp_path / "study"
    # Two batches of the iteration (each written at its end), then the host's runs one by one.
    solvers = ["m=0", "m=3", "qp"]
    # 18 runs of 4 s: enough that a busy machine does not finish them all between two looks (with 3
    # seeds, all 9 runs of a CI run on a loaded machine were on disk at the first look that saw 3).
    args = ["compare", "paper_no_obstacles", "--solvers", *solvers, "--seeds", "6", "--duration", "4"]
    args += ["--workers", "2", "--out", str(out)]
    process = subprocess.Popen(
        [sys.executable, "-m", "platoon_opt.study.cli", *args],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # its own process group: the kill takes the workers too
    )
    runs = out / "runs"
    # The loop ends at the third finished run; the deadline only bounds a study that never starts
    # (a loaded 2-core machine took over 60 s to import, compile and finish three runs).
    deadline = time.monotonic() + 300
    try:
        while len(list(runs.rglob("*.json"))) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    finished = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in runs.rglob("*.json")}
    assert 3 <= len(finished) < 18, "the kill must come part-way"
    assert not (out / "report.md").exists()

    assert main(args) == 0
    for path, (content, mtime) in finished.items():
        assert path.read_bytes() == content and path.stat().st_mtime_ns == mtime
    specs = _specs([parse_config(s) for s in solvers], range(6), duration=4.0, scenario="paper_no_obstacles")
    resumed = run_specs(specs, _refuse, runs_dir=out / "runs", workers=1)  # every run is on disk
    uninterrupted = run_specs(specs, get_allocator, workers=1)
    assert [_deterministic(r) for r in resumed] == [_deterministic(r) for r in uninterrupted]
    assert len(json.loads((out / "results.json").read_text())["runs"]) == 18


def test_smoke_reproduce_short_horizon_two_seeds(tmp_path, capsys):
    out = tmp_path / "results"
    # In this process: the worker pool has tests of its own (test_parallel_runs_equal_a_serial_run,
    # and the killed study above); spawning it here cost half of this test's time in imports.
    args = ["reproduce", "--seeds", "2", "--ablation-seeds", "1", "--duration", "1.0", "--out", str(out)]
    args += ["--workers", "1"]
    assert main([*args, "--solvers", "m=0", "m=3", "m=4", "dual"]) == 0
    printed = capsys.readouterr().out
    assert "**paper**, m = 4" in printed and "**paper**, m = 3" in printed
    report = (out / "report.md").read_text()
    for section in (
        "The paper's table beside ours",
        "Sweep over m",
        "Against the best m",
        "Compute time per step",
        "Ablation",
        "Scenarios",
    ):
        assert f"## {section}" in report
    for name in ("paper_no_obstacles", "paper_obstacles"):
        for figure in ("trajectories", "errors", "sweep"):
            assert (out / "figures" / f"{figure}_{name}.png").stat().st_size > 10_000
            assert f"figures/{figure}_{name}.png" in report
    assert (out / "figures" / "ablation.png").exists()
    data = json.loads((out / "results.json").read_text())
    main_runs = [r for r in data["runs"] if r["variant"] == "base"]
    assert len(main_runs) == 2 * 4 * 2
    # The ablation: m = 0 and the paper's m of each scenario, one seed.
    assert {r["config"] for r in data["runs"] if r["variant"] == "half-dt"} == {"m=0", "m=3", "m=4"}
    assert {r["variant"] for r in data["runs"]} == {
        "base",
        "no-hysteresis",
        "travel-ahead",
        "no-hysteresis-travel",
        "half-dt",
    }
    csv_lines = (out / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + len(data["runs"])


def test_the_battery_is_every_shipped_scenario_and_reproduce_runs_it(tmp_path, monkeypatch):
    study = battery_study(available_allocators(), seeds=3)
    assert {s.name for s in study.scenarios} == {p.stem for p in SCENARIO_DIR.glob("*.toml")}
    assert study.variants == () and study.seeds == (0, 1, 2)
    # The reproduction's configurations, the rate-aware task-exact programs in the three gear
    # choices and the achievable-first ones while catching up, through the dual.
    labels = [c.label for c in study.configs]
    assert labels[: len(reproduce_configs(available_allocators()))] == [
        c.label for c in reproduce_configs(available_allocators())
    ]
    rate_aware = [c for c in study.configs if dict(c.options).get("rate_aware")]
    assert [c.name for c in rate_aware] == ["qp-projection", "cone-projection"] * 3
    gears = [dict(c.options).get("gears", "model") for c in rate_aware]
    assert gears == ["model"] * 2 + ["either"] * 2 + ["catching-up"] * 2
    assert all(dict(c.options)["backend"] == "dual" for c in rate_aware)
    # And the achievable-first programs in the nearer gear while catching up.
    extra = study.configs[len(reproduce_configs(available_allocators())) + len(rate_aware) :]
    assert [(c.name, dict(c.options)) for c in extra] == [
        (name, {"backend": "dual", "gears": "catching-up"}) for name in ("qp", "cone")
    ]
    # The command on two of them (every shipped file runs in tests/model/test_scenario_files.py).
    monkeypatch.setattr(battery, "BATTERY", ("three_units", "field_sparse"))
    out = tmp_path / "battery"
    args = ["reproduce", "--battery", "--seeds", "1", "--duration", "0.3", "--solvers", "m=0", "dual"]
    assert main([*args, "--out", str(out), "--no-figures", "--workers", "1"]) == 0
    runs = json.loads((out / "results.json").read_text())["runs"]
    assert sorted((r["scenario"], r["config"]) for r in runs) == [
        ("field_sparse", "dual"),
        ("field_sparse", "m=0"),
        ("three_units", "dual"),
        ("three_units", "m=0"),
    ]
    report = (out / "report.md").read_text()
    assert "### three_units" in report and "## Against the best m" in report


def test_a_baseline_other_than_m0_puts_no_paper_change_beside_its_own(tmp_path, capsys):
    out = tmp_path / "m1"
    args = ["compare", "paper_no_obstacles", "--solvers", "m=1", "m=0", "--seeds", "2", "--duration", "0.2"]
    assert main([*args, "--out", str(out), "--workers", "1"]) == 0
    assert "**paper**" not in capsys.readouterr().out
    report = (out / "report.md").read_text()
    assert "The paper's table beside ours" not in report and "Baseline: `m=1`" in report


def test_compare_runs_every_registered_allocator(tmp_path):
    out = tmp_path / "every"
    others = [name for name in available_allocators() if name != "iterative"]
    args = ["compare", "paper_obstacles", "--solvers", "m=0", *others, "--seeds", "2", "--duration", "0.2"]
    assert main([*args, "--out", str(out), "--workers", "1"]) == 0
    runs = json.loads((out / "results.json").read_text())["runs"]
    assert {r["allocator"] for r in runs} == {"iterative", *others}
    assert all(r["steps"] == 20 for r in runs)
    # nmpc solves every resolve_every (5) steps and hands its plan between; the others solve each step.
    assert all(r["solve_steps"] == (4 if r["allocator"] == "nmpc" else 20) for r in runs)
    nmpc = [r for r in runs if r["allocator"] == "nmpc"]
    assert all(r["solve_time_per_solve_median"] > r["solve_time_median"] for r in nmpc)
    assert "allocator per solve, median (ms)" in (out / "report.md").read_text()


@pytest.mark.parametrize(
    "args",
    [
        ["compare", "paper_obstacles", "--solvers", "no-such-allocator"],
        ["compare", "paper_obstacles", "--solvers", "m=0", "iterative:bogus=1"],
        ["compare", "paper_obstacles", "--solvers", "m=0", "m=0"],
        ["compare", "no_such_scenario"],
        ["reproduce", "--seeds", "0"],
        ["reproduce", "--workers", "0"],
    ],
)
def test_bad_study_input_is_one_line_and_exit_2(args, capsys, tmp_path):
    assert main([*args, "--out", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("platoon-opt: error:") and error.count("\n") == 1


def test_a_batched_run_that_overflowed_runs_in_the_host_loop(monkeypatch):
    """A study's batch hands a run whose barrier capacity overflowed (``simulation.overflowed``)
    to the host loop: its result says so (path "host") and holds the host loop's numbers; the
    batch's other run stays compiled. On the iteration's kernel, the run marked by hand."""
    from platoon_opt.study import batches

    monkeypatch.setattr(batches, "overflowed", lambda batch, index: index == 1)
    results = run_specs(_specs(iterative_configs([2]), [3, 1], duration=0.3), get_allocator, workers=1)
    assert [r["path"] for r in results] == ["compiled", "host"]
    scenario = load_scenario("paper_obstacles")
    allocator = get_allocator("iterative", max_iterations=2)
    run = simulate(scenario, allocator, seed=1, duration=0.3, compiled=False)
    reference = integrated_errors(run, scenario.transient)
    assert all(results[1][key] == reference[key] for key in ("mean_position", "var_x", "var_y"))
