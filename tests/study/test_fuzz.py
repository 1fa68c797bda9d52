"""The fuzzer (``platoon-opt fuzz``): its oracle catches what it is meant to catch, 150 cases of
every family pass it here (hypothesis), and a run resumes where it stopped."""

from __future__ import annotations

import json
import random
import sys

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from platoon_opt.solvers.registry import registered
from platoon_opt.study import fuzz
from platoon_opt.study.cli import main
from platoon_opt.study.fuzz_argv import option_value
from platoon_opt.study.fuzz_oracle import CASE_FILE, Case, run_case, verdict
from tests.conftest import scenario_text


@settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(family=st.sampled_from(fuzz.FAMILIES), rng=st.randoms(use_true_random=False))
def test_every_fuzz_case_ends_in_a_sane_run_or_one_line(family, rng):
    case = fuzz.build_case(family, rng)
    outcome = run_case(case, main)
    assert not outcome.problems, (fuzz.show_case(case), outcome.problems, outcome.error)


def _case(argv, file: bytes | None = None, *, must_fail=False, command="simulate", steps=2) -> Case:
    return Case(0, "test", "test", "", tuple(argv), file, "", must_fail, True, command, "out", steps, False)


SIMULATE = ["simulate", CASE_FILE, "--duration", "0.02", "--out", "out", "--no-figures"]


def test_the_oracle_passes_a_sane_run_and_a_named_error():
    good = scenario_text("paper_obstacles").encode()
    assert verdict(run_case(_case(SIMULATE, good), main)) == "run"
    bad = scenario_text("paper_obstacles").replace("dt = 0.01", "dt = -0.01", 1).encode()
    assert verdict(run_case(_case(SIMULATE, bad, must_fail=True), main)) == "error"


def _entry(status: int, stderr: str = "", raises: BaseException | None = None):
    def entry(argv):
        print(stderr, file=sys.stderr, end="")
        if raises is not None:
            raise raises
        return status

    return entry


@pytest.mark.parametrize(
    "entry, problem",
    [
        (_entry(0, raises=ZeroDivisionError("x")), "traceback: ZeroDivisionError: x"),
        (_entry(1, "platoon-opt: error: boom\n"), "exit status 1"),
        (_entry(2, "platoon-opt: error: simulation.dt is bad\nmore\n"), "exit 2 with 2 stderr lines"),
        (_entry(2, "platoon-opt: error: case.toml: something is wrong\n"), "does not name a key"),
        (_entry(2, "platoon-opt: error: case.toml: simulation.dt must be > 0, got 5\n"), "not the file's"),
        (_entry(0), "simulate exit 0 without its files"),
    ],
)
def test_the_oracle_finds_a_traceback_a_wrong_exit_and_a_line_that_names_nothing(entry, problem):
    good = scenario_text("paper_obstacles").encode()
    outcome = run_case(_case(SIMULATE, good), entry)
    assert verdict(outcome) == "finding" and problem in outcome.problems[0], outcome.problems


def test_the_oracle_finds_a_run_of_the_wrong_length_and_a_bad_file_that_ran(tmp_path):
    good = scenario_text("paper_obstacles").encode()
    outcome = run_case(_case(SIMULATE, good, steps=3), main)
    assert outcome.problems == ("2 steps, asked for 3",)
    outcome = run_case(_case(SIMULATE, good, must_fail=True), main)
    assert outcome.problems[0].startswith("exit 0 for input that breaks a documented rule")


class _Counting:
    """An entry point that counts its calls and may stop (Ctrl-C) at call ``stop``."""

    def __init__(self, stop: int | None = None) -> None:
        self.calls, self.stop = 0, stop

    def __call__(self, argv):
        self.calls += 1
        if self.calls == self.stop:
            raise KeyboardInterrupt
        print("platoon-opt: error: argument --x: no", file=sys.stderr)
        return 2


def test_a_stopped_run_resumes_where_it_stopped_and_keeps_finished_chunks(tmp_path):
    cases = 5 * len(fuzz.FAMILIES)  # one chunk of 5 cases per family
    with pytest.raises(KeyboardInterrupt):
        fuzz.run(tmp_path, _Counting(stop=13), cases=cases)  # in the third family's chunk
    assert len(list((tmp_path / "fuzz-chunks").rglob("*.json"))) == 2
    resumed = _Counting()
    result = fuzz.run(tmp_path, resumed, cases=cases)
    assert resumed.calls == cases - 10 and result["reused"] == 10
    again = _Counting()
    fuzz.run(tmp_path, again, cases=cases)
    assert again.calls == 0
    (tmp_path / "fuzz-chunks" / fuzz.FAMILIES[0] / "00000.json").unlink()
    fuzz.run(tmp_path, again, cases=cases)
    assert again.calls == 5


def test_cli_fuzz_writes_its_figures_and_shows_a_case(tmp_path, capsys):
    cases = 2 * len(fuzz.FAMILIES)
    assert main(["fuzz", "--cases", str(cases), "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "fuzz.json").read_text())
    assert sum(chunk["cases"] for chunk in result["chunks"]) == cases
    assert {chunk["family"] for chunk in result["chunks"]} == set(fuzz.FAMILIES)
    assert f"**{cases:,} cases, 0 findings**" in (tmp_path / "fuzz.md").read_text()
    capsys.readouterr()
    assert main(["fuzz", "--show", "3"]) == 0
    assert capsys.readouterr().out.startswith(f"case 3 of seed 0: {fuzz.FAMILIES[3]}")


def test_an_empty_tuple_of_names_is_a_valid_option_value_for_the_generator_too(tmp_path, capsys):
    # The fuzzer had "()" among the broken values of every rule; a Choices option (qp's
    # fallbacks: the backends tried next) takes it: no backend after the first.
    argv = ["simulate", "paper_obstacles", "--solver", "qp-projection", "--option", "fallbacks=()"]
    assert main([*argv, "--duration", "0.02", "--no-figures", "--out", str(tmp_path)]) == 0
    option = next(o for o in registered("qp-projection").options if o.name == "fallbacks")
    values = {option_value(option, random.Random(seed), 4) for seed in range(200)}
    assert ("()", False) in values and ("()", True) not in values
