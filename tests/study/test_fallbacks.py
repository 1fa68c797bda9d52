"""A configuration error is an error, not a fallback on every step; a run that fell back on more
than 1 % of its steps says so on one stderr line, and the report shows every configuration's
fallbacks (issue "Trustworthy failures")."""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import pytest

from platoon_opt import OptionError, load_scenario, simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.study.cli import main
from platoon_opt.study.config import AllocatorConfig
from platoon_opt.study.harness import Study, run_study
from platoon_opt.study.report import write_report
from tests.conftest import random_problem
from tests.study.test_strict import Failing, _controller, factory, registered  # noqa: F401


@dataclass(frozen=True)
class Misconfigured:
    """Raises the configuration error it is given at every step."""

    name: str = "misconfigured"

    def allocate(self, problem):
        raise OptionError("option k of misconfigured must be 2, got 3")


@pytest.mark.parametrize("strict", [False, True])
def test_the_controller_lets_a_configuration_error_through(strict):
    problem = random_problem(np.random.default_rng(0), 6)
    with pytest.raises(OptionError, match="option k of misconfigured"):
        _controller(Misconfigured(), strict=strict).allocate(problem)


def test_a_fallback_status_carries_the_exceptions_message():
    problem = random_problem(np.random.default_rng(0), 6)
    allocation = _controller(Failing(after=0.0), strict=False).allocate(problem)
    assert allocation.fell_back and allocation.status == "fallback:RuntimeError: injected failure"


def test_nmpc_task_weights_that_do_not_fit_the_task_fail_before_the_first_step():
    allocator = get_allocator("nmpc", task_weights=(4, 1))
    with pytest.raises(OptionError, match=r"task_weights of nmpc must be a tuple of 4 numbers.*\(4.0, 1.0\)"):
        simulate(load_scenario("paper_obstacles"), allocator, duration=1.0)
    covariance = load_scenario("paper_covariance")
    with pytest.raises(OptionError, match="tuple of 5 numbers >= 0, one per task component .*cov_xy"):
        simulate(covariance, get_allocator("nmpc", task_weights=(4, 1, 4, 1)), duration=0.1)


def test_cli_simulate_nmpc_with_two_task_weights_is_one_line_and_exit_2(tmp_path, capsys):
    args = ["simulate", "paper_obstacles", "--solver", "nmpc", "--option", "task_weights=4,1"]
    assert main([*args, "--duration", "1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(
        "platoon-opt: error: --solver nmpc: option task_weights of nmpc must be a tuple of 4"
    )
    assert "got (4.0, 1.0)" in err and not (tmp_path / "metrics.json").exists()


def test_cli_compare_checks_every_configuration_before_any_run(tmp_path, capsys):
    args = ["compare", "paper_obstacles", "--solvers", "m=0", "nmpc:task_weights=(4,1)", "--seeds", "1"]
    assert main([*args, "--duration", "0.1", "--workers", "1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("platoon-opt: error: nmpc:task_weights=(4, 1): option task_weights of nmpc")
    assert err.count("\n") == 1 and not (tmp_path / "runs").exists()


@pytest.mark.usefixtures("registered")
def test_cli_simulate_warns_when_more_than_one_percent_of_the_steps_fell_back(tmp_path, capsys):
    args = ["simulate", "paper_obstacles", "--solver", "failing", "--seed", "4", "--duration", "0.1"]
    assert main([*args, "--no-figures", "--out", str(tmp_path)]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "fell back" in line]
    assert warnings == [
        "platoon-opt: warning: failing(raise) fell back on 5 of 10 steps (50 %) on paper_obstacles (seed 4); "
        "first at t = 0.05 s: fallback:RuntimeError: injected failure"
    ]


def test_a_run_that_never_fell_back_prints_no_warning(tmp_path, capsys):
    args = ["simulate", "paper_obstacles", "--duration", "0.1", "--no-figures", "--out", str(tmp_path)]
    assert main(args) == 0
    assert "fell back" not in capsys.readouterr().err


def _study() -> Study:
    configs = (AllocatorConfig.make("iterative", "m=0", max_iterations=0), AllocatorConfig.make("failing"))
    return Study((load_scenario("paper_no_obstacles"),), configs, (0, 1), 0.1)


def test_the_harness_warns_once_per_configuration_and_the_report_shows_it(tmp_path):
    stream = io.StringIO()
    result = run_study(_study(), factory, tmp_path, workers=1, stream=stream)
    lines = [line for line in stream.getvalue().splitlines() if "warning" in line]
    assert lines == [
        "platoon-opt: warning: failing fell back on 10 of 20 steps (50 %) on paper_no_obstacles over 2 runs; "
        "first in seed 0 at t = 0.05 s: fallback:RuntimeError: injected failure"
    ]
    assert [run["first_fallback"] for run in result.runs] == [
        "",
        "",
        *["fallback:RuntimeError: injected failure"] * 2,
    ]
    report = write_report(result, tmp_path, figures=False).read_text()
    assert "**Fallbacks on more than 1 % of the steps**" in report
    assert "- `failing` on paper_no_obstacles: 10 of 20 steps (50 %) over 2 runs" in report
    timing = report[report.index("## Compute time per step") :]
    assert "| `failing` |" in timing and "**50 %, above 1 %**" in timing and "| 0 % |" in timing
