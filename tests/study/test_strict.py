"""Strict mode (issue 6): a run whose allocation fails or falls back ends with a typed
``AllocationError`` naming the allocator, scenario and seed, through the controller, ``simulate``,
the harness (in this process and in worker processes) and the command line (one line on stderr,
exit status 3, no traceback); without strict the run carries on with the fallback."""

from __future__ import annotations

import json
import pickle
from dataclasses import dataclass

import numpy as np
import pytest

from platoon_opt import (
    Allocation,
    AllocationError,
    AllocationProblem,
    MeanVarianceTask,
    PlatoonController,
    VehicleLimits,
    load_scenario,
    simulate,
)
from platoon_opt.solvers import get_allocator, registry
from platoon_opt.solvers.options import Choice, Number, Option
from platoon_opt.study.cli import main
from platoon_opt.study.config import AllocatorConfig
from platoon_opt.study.dispatch import run_specs
from platoon_opt.study.exits import ALLOCATION_FAILED
from platoon_opt.study.runs import TIMING_FIELDS, RunSpec
from platoon_opt.study.variants import BASE
from tests.conftest import random_problem

FAIL_AT = 0.05  # s: the injected failure's first step


@dataclass(frozen=True)
class Failing:
    """Hands out the nominal velocity (the paper's m = 0) until ``after`` seconds, then raises
    (``mode="raise"``) or answers with a fallback of its own (``mode="fallback"``)."""

    after: float = Option("after", FAIL_AT, "when it starts to fail (s)", Number(at_least=0)).field()
    mode: str = Option(
        "mode", "raise", "raise, or answer with a fallback", Choice(("raise", "fallback"))
    ).field()

    @property
    def name(self) -> str:
        return f"failing({self.mode})"

    def allocate(self, problem: AllocationProblem) -> Allocation:
        failing = problem.t >= self.after - 1e-9
        if failing and self.mode == "raise":
            raise RuntimeError("injected failure")
        return Allocation.of(
            problem,
            problem.nominal.copy(),
            allocator=self.name,
            status="fallback:injected->nominal" if failing else "nominal",
            iterations=0,
            solve_time=0.0,
            fell_back=failing,
        )


def make_failing(after: float = FAIL_AT, mode: str = "raise") -> Failing:
    return Failing(after, mode)


def factory(name: str, **options):
    """``get_allocator`` plus "failing" (module level: worker processes unpickle it)."""
    return make_failing(**options) if name == "failing" else get_allocator(name, **options)


@pytest.fixture
def registered(monkeypatch):
    """ "failing" in the registry for this test only (the CLI looks allocators up by name)."""
    monkeypatch.setitem(registry._REGISTRY, "failing", registry.Registered("failing", Failing, "", ""))


def _controller(allocator, strict: bool) -> PlatoonController:
    return PlatoonController(
        task=MeanVarianceTask(),
        gains=np.array([50.0, 10, 50, 10]),
        limits=VehicleLimits(),
        allocator=allocator,
        strict=strict,
    )


@pytest.mark.parametrize("mode", ["raise", "fallback"])
def test_controller_raises_only_when_strict(mode):
    problem = random_problem(np.random.default_rng(0), 6)  # t = 0
    failing = Failing(after=0.0, mode=mode)
    lenient = _controller(failing, strict=False).allocate(problem)
    assert lenient.fell_back and np.all(np.isfinite(lenient.velocities))
    with pytest.raises(AllocationError) as caught:
        _controller(failing, strict=True).allocate(problem)
    error = caught.value
    assert error.allocator == f"failing({mode})" and error.t == 0.0
    assert ("raised RuntimeError" if mode == "raise" else "fell back: fallback:injected") in error.reason
    # A healthy allocation passes through strict mode untouched.
    healthy = Failing(after=1.0, mode=mode)
    strict = _controller(healthy, strict=True).allocate(problem)
    np.testing.assert_array_equal(strict.velocities, problem.nominal)
    assert not strict.fell_back


def test_allocation_error_is_one_line_and_pickles():
    error = AllocationError(allocator="qp(rho=1000, clarabel)", reason="raised ValueError('a\nb')", t=0.25)
    named = error.within(scenario="paper_obstacles", seed=3)
    text = str(named)
    assert "\n" not in text
    assert text == (
        "allocator qp(rho=1000, clarabel) failed on scenario paper_obstacles, seed 3, at t = 0.25 s: "
        "raised ValueError('a b')"
    )
    copy = pickle.loads(pickle.dumps(named))  # worker processes send it back pickled
    assert type(copy) is AllocationError and str(copy) == text
    assert (copy.allocator, copy.scenario, copy.seed, copy.t) == (
        "qp(rho=1000, clarabel)",
        "paper_obstacles",
        3,
        0.25,
    )


@pytest.mark.parametrize("mode", ["raise", "fallback"])
def test_simulate_strict_stops_at_the_failing_step(mode):
    scenario = load_scenario("paper_obstacles")
    lenient = simulate(scenario, Failing(mode=mode), seed=1, duration=0.1)
    assert lenient.fell_back.sum() == 5 and not lenient.fell_back[:5].any()
    with pytest.raises(AllocationError, match=rf"failing\({mode}\) failed at t = 0.05 s"):
        simulate(scenario, Failing(mode=mode), seed=1, duration=0.1, strict=True)


def _spec(name: str, strict: bool, seed: int = 2, **options) -> RunSpec:
    config = AllocatorConfig.make(name, **options)
    return RunSpec(load_scenario("paper_no_obstacles"), BASE, config, seed, 0.1, strict=strict)


@pytest.mark.parametrize("workers", [1, 2])
def test_harness_strict_run_raises_naming_the_run(workers, tmp_path):
    specs = [_spec("iterative", True, seed=0, max_iterations=2), _spec("failing", True)]
    with pytest.raises(AllocationError) as caught:
        run_specs(specs, factory, runs_dir=tmp_path, workers=workers)
    error = caught.value
    assert (error.allocator, error.scenario, error.seed) == ("failing(raise)", "paper_no_obstacles", 2)
    assert "allocator failing(raise) failed on scenario paper_no_obstacles, seed 2, at t = 0.05 s" in str(
        error
    )
    assert not (tmp_path / f"{specs[1].key}.json").exists()
    # Without strict the same run completes on the controller's fallback.
    result = run_specs([_spec("failing", False)], factory, workers=1)[0]
    assert result["fallback_steps"] == 5


def _refuse(name, **options):
    raise AssertionError(f"run {name} {options} was recomputed")


def test_strict_is_not_in_the_fingerprint_and_changes_no_result(tmp_path):
    lenient, strict = _spec("iterative", False, max_iterations=3), _spec("iterative", True, max_iterations=3)
    assert lenient.fingerprint() == strict.fingerprint() and lenient.key == strict.key
    first = run_specs([lenient], factory, runs_dir=tmp_path, workers=1)[0]
    assert first["fallback_steps"] == 0
    # A finished run that never fell back is what a strict run gives: reused (as JSON: a compiled
    # run's allocation time is nan).
    assert json.dumps(run_specs([strict], _refuse, runs_dir=tmp_path, workers=1)[0]) == json.dumps(first)
    recomputed = run_specs([strict], factory, workers=1)[0]
    assert {k: v for k, v in recomputed.items() if k not in TIMING_FIELDS} == {
        k: v for k, v in first.items() if k not in TIMING_FIELDS
    }


def test_a_finished_run_that_fell_back_is_not_reused_by_a_strict_study(tmp_path):
    finished = run_specs([_spec("failing", False, mode="fallback")], factory, runs_dir=tmp_path, workers=1)
    assert finished[0]["fallback_steps"] == 5
    with pytest.raises(AllocationError, match="fell back"):
        run_specs([_spec("failing", True, mode="fallback")], factory, runs_dir=tmp_path, workers=1)


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_cli_simulate_strict_is_one_line_and_exit_3(registered, tmp_path, capsys):
    args = ["simulate", "paper_obstacles", "--solver", "failing", "--seed", "4", "--duration", "0.1"]
    assert main([*args, "--out", str(tmp_path / "lenient")]) == 0
    assert "fallback_steps" in (tmp_path / "lenient" / "metrics.json").read_text()
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "strict"), "--strict"]) == ALLOCATION_FAILED == 3
    err = _one_line(capsys.readouterr().err.split("\r")[-1].lstrip("\n"))
    assert err.startswith(
        "platoon-opt: error: allocator failing(raise) failed on scenario paper_obstacles, seed 4, "
        "at t = 0.05 s: raised RuntimeError('injected failure')"
    )
    assert not (tmp_path / "strict" / "metrics.json").exists()


@pytest.mark.parametrize("command", ["compare", "reproduce"])
def test_cli_study_strict_is_one_line_and_exit_3(command, registered, tmp_path, capsys):
    out = tmp_path / command
    args = [command, *(["paper_no_obstacles"] if command == "compare" else []), "--solvers", "m=0"]
    args += [
        "failing:mode=fallback",
        "--seeds",
        "1",
        "--duration",
        "0.1",
        "--workers",
        "1",
        "--out",
        str(out),
    ]
    if command == "reproduce":
        args += ["--ablation-seeds", "0"]
    assert main([*args, "--strict"]) == ALLOCATION_FAILED
    full = capsys.readouterr().err  # progress lines, then the error
    assert "Traceback" not in full
    err = _one_line(full.splitlines()[-1] + "\n")
    assert err.startswith("platoon-opt: error: allocator failing(fallback) failed on scenario paper_")
    assert ", seed 0, at t = 0.05 s: fell back: fallback:injected->nominal" in err
    assert f"finished runs are kept in {out}/runs" in err
    assert not (out / "report.md").exists()
