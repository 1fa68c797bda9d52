"""The soak (platoon-opt soak) runs end to end on a few problems, writes soak.json and
soak.md, keeps finished chunks on a rerun (also after an interruption, and across worker
processes), and counts what goes wrong."""

from __future__ import annotations

import io
import json

import numpy as np

from platoon_opt import Allocation
from platoon_opt.solvers import get_allocator
from platoon_opt.study import problems, soak, soak_report
from platoon_opt.study.cli import main

PROBLEMS = 50


def test_soak_runs_and_writes_both_files(tmp_path, capsys):
    out = tmp_path / "soak"
    args = ["--problems", str(PROBLEMS), "--allocators", "iterative,dual", "--out", str(out), "--seed", "3"]
    assert main(["soak", *args]) == 0
    assert "no failures" in capsys.readouterr().out
    result = json.loads((out / "soak.json").read_text())
    assert list(result["allocators"]) == ["iterative", "dual"]
    for name, entry in result["allocators"].items():
        assert entry["problems"] == PROBLEMS and sum(entry["statuses"].values()) == PROBLEMS
        assert entry["exceptions"] == entry["non_finite"] == entry["limit_violations"] == 0, name
        assert entry["time_us"]["median"] > 0 and entry["problems_per_second"] > 0
        assert sum(kind["problems"] for kind in entry["by_kind"].values()) == PROBLEMS
    assert result["allocators"]["dual"]["statuses"] == {"optimal": PROBLEMS}
    assert {"cpu", "cores", "python", "numpy", "platform"} <= set(result["machine"])
    assert (
        result["date"]
        and result["seed"] == 3
        and result["counts"] == {"iterative": PROBLEMS, "dual": PROBLEMS}
    )
    table = (out / "soak.md").read_text()
    assert "| iterative | 50 | 0 | 0 | 0 |" in table and "| dual | 50 |" in table
    # A rerun with the same settings keeps what is finished and adds what is asked for.
    assert main(["soak", *args[:3], "iterative,dual,qp", *args[4:]]) == 0
    assert "soak iterative: kept 50 problems (1 chunks) from an earlier run" in capsys.readouterr().err
    again = json.loads((out / "soak.json").read_text())
    assert again["allocators"]["iterative"] == result["allocators"]["iterative"]
    assert list(again["allocators"]) == ["iterative", "dual", "qp"]


# What a chunk's outcome is, without its timings.
OUTCOME = (
    "problems",
    "complete",
    "build_errors",
    "exceptions",
    "exception_types",
    "non_finite",
    "limit_violations",
    "worst_excess",
    "worst_excess_index",
    "fallbacks",
    "statuses",
    "by_kind",
    "examples",
)


def outcome(entry):
    return {key: entry[key] for key in OUTCOME}


class Interrupted:
    """The registered allocators, except that the ``stop``-th instance is interrupted (Ctrl-C)
    on its first problem."""

    def __init__(self, stop):
        self.instances, self.stop = 0, stop

    def __call__(self, name):
        self.instances += 1
        allocator = get_allocator(name)
        if self.instances == self.stop:

            def interrupt(problem):
                raise KeyboardInterrupt

            allocator = Broken()
            allocator.allocate = interrupt
        return allocator


def test_an_interrupted_soak_resumes_where_it_stopped(tmp_path, monkeypatch):
    monkeypatch.setattr(problems, "CHUNK", 40)  # problems differ from the real family's: fine here
    whole = soak.run(tmp_path / "whole", problems=150, allocators=["iterative", "dual"], stream=io.StringIO())
    out = tmp_path / "resumed"
    stream = io.StringIO()
    try:
        soak.run(out, problems=150, allocators=["iterative", "dual"], factory=Interrupted(6), stream=stream)
    except KeyboardInterrupt:
        pass
    else:
        raise AssertionError("the injected Ctrl-C did not interrupt the soak")
    # Iterative's four chunks and dual's first are on disk; the summary holds iterative, complete.
    assert sorted(path.name for path in (out / "soak-chunks" / "iterative").iterdir()) == [
        "00000.json",
        "00001.json",
        "00002.json",
        "00003.json",
    ]
    assert [path.name for path in (out / "soak-chunks" / "dual").iterdir()] == ["00000.json"]
    assert list(json.loads((out / "soak.json").read_text())["allocators"]) == ["iterative"]
    calls = Interrupted(0)
    resumed = soak.run(out, problems=150, allocators=["iterative", "dual"], factory=calls, stream=stream)
    assert calls.instances == 3  # only dual's last three chunks were solved again
    assert "soak dual: kept 40 problems (1 chunks) from an earlier run" in stream.getvalue()
    for name in ("iterative", "dual"):
        assert outcome(resumed["allocators"][name]) == outcome(whole["allocators"][name]), name
        assert resumed["allocators"][name]["problems"] == 150
    # Chunks of other settings are not reused.
    assert soak.run(out, problems=150, allocators=["dual"], seed=1, factory=calls, stream=stream)
    assert calls.instances == 7


def test_worker_processes_give_the_same_outcome(tmp_path):
    count = problems.CHUNK + 200
    alone = soak.run(tmp_path / "one", problems=count, allocators=["iterative"], stream=io.StringIO())
    shared = soak.run(
        tmp_path / "two", problems=count, allocators=["iterative"], jobs=2, stream=io.StringIO()
    )
    assert outcome(shared["allocators"]["iterative"]) == outcome(alone["allocators"]["iterative"])
    assert shared["jobs"] == 2 and shared["allocators"]["iterative"]["chunks"] == 2


def test_a_partial_allocator_is_marked_in_the_table():
    records = [soak.soak_chunk("iterative", get_allocator, 0, 0, 30)]
    entry = soak_report.merge(records, target=100)
    assert entry["problems"] == 30 and not entry["complete"]
    result = {
        "seed": 0,
        "degenerate_rate": 0.2,
        "date": "d",
        "jobs": 1,
        "allocators": {"iterative": entry},
        "machine": {"cpu": "c", "cores": 2, "platform": "p", "python": "3", "numpy": "2"},
    }
    table = soak_report.markdown(result)
    assert "| iterative | 30 of 100 (partial) |" in table and "Partial (rerun the command" in table


def test_problems_are_reproducible_and_mix_the_degenerate_kinds():
    first = list(problems.specs(5, 1200))
    assert len(first) == 1200
    again = problems.spec_at(5, 1100)
    np.testing.assert_array_equal(again.x, first[1100].x)
    assert again.kind == first[1100].kind and again.gain_exponent == first[1100].gain_exponent
    kinds = {spec.kind for spec in first}
    assert kinds == set(problems.KINDS)
    assert 0.1 < np.mean([spec.kind != "random" for spec in first]) < 0.3
    assert {spec.n for spec in first} == set(range(problems.MIN_UNITS, problems.MAX_UNITS + 1))
    for kind in problems.DEGENERATE_KINDS:  # every kind builds
        problem = next(spec for spec in first if spec.kind == kind).build()
        assert np.all(np.isfinite(problem.nominal))
    zero = next(spec for spec in first if spec.kind == "zero_nominal").build()
    np.testing.assert_allclose(zero.nominal, 0.0, atol=1e-12)


class Broken:
    """Raises, returns NaN or leaves the sets, by turns; the soak must count each."""

    name = "broken"
    promise = "every unit in its gear's sector"

    def __init__(self) -> None:
        self.calls = 0

    def promised_excess(self, problem, allocation):
        return float(np.max(problem.achievable().distance(allocation.velocities)))

    def allocate(self, problem):
        self.calls += 1
        if self.calls % 3 == 1:
            raise RuntimeError("injected")
        velocities = np.full((problem.n, 2), np.nan if self.calls % 3 == 2 else 0.0)
        changed = self.calls % 3 == 0  # the finite answers: "another program"
        return Allocation(
            velocities,
            self.name,
            "fallback:injected",
            0,
            0.0,
            0.0,
            0.0,
            fell_back=True,
            program_changed=changed,
        )


def test_soak_counts_exceptions_non_finite_and_fallbacks(tmp_path):
    result = soak.run(
        tmp_path,
        problems=30,
        allocators=["iterative"],
        factory=lambda name: Broken(),
        stream=io.StringIO(),
    )
    entry = result["allocators"]["iterative"]
    assert entry["exceptions"] == 10 and entry["exception_types"] == {"RuntimeError": 10}
    assert entry["non_finite"] == 10 and entry["fallbacks"] == 20
    assert entry["program_changes"] == 10 and entry["examples"]["program_change"]
    assert entry["limit_violations"] == 0  # an allocator of unknown kind promises nothing
    assert len(entry["examples"]["exception"]) == soak_report.EXAMPLES
    assert entry["statuses"] == {"fallback:injected": 20}
    assert "| iterative | 30 | 10 | 10 | 0 |" in (tmp_path / "soak.md").read_text()
    assert "| 20 | 10 |" in (tmp_path / "soak.md").read_text()  # fallbacks, program changes


def test_show_rebuilds_a_problem():
    text = soak.show(7, seed=1, allocators=["dual"])
    assert text.startswith("problem 7 of seed 1: kind ") and "dual: status 'optimal'" in text


def test_the_command_line_records_the_command_as_typed_and_checks_its_options(tmp_path, capsys):
    out = tmp_path / "soak"
    assert main(["soak", "--problems", "5", "--allocators", "iterative", "--out", str(out)]) == 0
    result = json.loads((out / "soak.json").read_text())
    assert result["command"] == f"platoon-opt soak --problems 5 --allocators iterative --out {out}"
    assert {"seed", "degenerate_rate", "code", "family", "checks"} <= set(result)
    capsys.readouterr()
    for arguments, complaint in (
        (["--jobs", "0"], "--jobs"),
        (["--problems", "0"], "--problems"),
        (["--allocators", "nope"], "--allocators"),
        (["--degenerate-rate", "2"], "--degenerate-rate"),
    ):
        assert main(["soak", *arguments]) == 2
        assert complaint in capsys.readouterr().err


def test_a_chunk_of_fewer_problems_is_not_reused(tmp_path):
    calls = Interrupted(0)
    soak.run(tmp_path, problems=30, allocators=["iterative"], factory=calls, stream=io.StringIO())
    longer = soak.run(tmp_path, problems=50, allocators=["iterative"], factory=calls, stream=io.StringIO())
    assert calls.instances == 2 and longer["allocators"]["iterative"]["problems"] == 50
    stream = io.StringIO()
    soak.run(tmp_path, problems=50, allocators=["iterative"], factory=calls, stream=stream)
    assert calls.instances == 2 and "kept 50 problems (1 chunks)" in stream.getvalue()
    assert [path.name for path in (tmp_path / "soak-chunks" / "iterative").iterdir()] == ["00000.json"]


def test_the_problem_family_has_a_version_that_follows_its_constants(monkeypatch):
    version = problems.family_version()
    assert version == problems.family_version()
    monkeypatch.setattr(problems, "CHUNK", 40)
    assert problems.family_version() != version
