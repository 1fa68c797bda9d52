"""The command line: simulate writes its files; bad input is one line and exit status 2."""

import json

import pytest

from platoon_opt.study import cli
from platoon_opt.study.cli import main
from tests.conftest import scenario_text


def test_cli_simulate_writes_metrics_timeseries_and_figure(tmp_path):
    out = tmp_path / "run"
    code = main(
        [
            "simulate",
            "paper_obstacles",
            "--solver",
            "iterative",
            "--iterations",
            "3",
            "--duration",
            "1.0",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    for key in (
        "mean_position",
        "var_x",
        "var_y",
        "mean_position_after_transient",
        "gear_flips",
        "min_clearance",
        "scenario",
        "solver",
        "options",
        "dt",
        "steps",
        "wall_time",
    ):
        assert key in metrics
    assert metrics["steps"] == 100 and metrics["options"] == {"max_iterations": 3}
    lines = (out / "timeseries.csv").read_text().splitlines()
    assert len(lines) == 102
    assert (out / "trajectory.png").stat().st_size > 10_000


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(scenario_text("paper_no_obstacles").replace("dt = 0.01", "dt = -0.01"))
    assert main(["simulate", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "simulation.dt" in err and "-0.01" in err
    assert main(["simulate", "paper_obstacles", "--solver", "nope", "--out", str(tmp_path / "y")]) == 2
    assert "unknown allocator" in capsys.readouterr().err


def test_cli_takes_the_options(tmp_path):
    out = tmp_path / "run"
    args = [
        "simulate",
        "paper_obstacles",
        "--solver",
        "qp",
        "--option",
        "priority='strict'",
        "--option",
        "rho=10",
    ]
    assert main([*args, "--duration", "0.2", "--out", str(out)]) == 0
    assert json.loads((out / "metrics.json").read_text())["allocator"] == "qp(strict, clarabel)"


@pytest.mark.parametrize(
    "arguments, checked",
    [
        ([], (0, 1)),
        (["--check-seeds", "0"], ()),
        (["--quick"], (0,)),
        (["--battery", "--check-seeds", "3"], (0, 1, 2)),
    ],
)
def test_reproduce_cross_checks_the_seeds_it_is_asked_to(monkeypatch, arguments, checked):
    studies = []
    monkeypatch.setattr(cli, "_run_study", lambda args, study, out, label: studies.append(study) or 0)
    assert main(["reproduce", *arguments]) == 0
    assert studies[0].check_seeds == checked
