"""The soak script (benchmarks/soak.py) runs end to end on a few problems, writes soak.json and
soak.md, keeps finished allocators on a rerun, and counts what goes wrong."""

from __future__ import annotations

import io
import json

import numpy as np

from benchmarks import soak
from platoon_opt import Allocation

PROBLEMS = 50


def test_soak_runs_and_writes_both_files(tmp_path, capsys):
    out = tmp_path / "soak"
    args = ["--problems", str(PROBLEMS), "--allocators", "iterative,dual", "--out", str(out), "--seed", "3"]
    assert soak.main(args) == 0
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
    assert soak.main([*args[:3], "iterative,dual,qp", *args[4:]]) == 0
    assert "kept from the earlier run" in capsys.readouterr().err
    again = json.loads((out / "soak.json").read_text())
    assert again["allocators"]["iterative"] == result["allocators"]["iterative"]
    assert list(again["allocators"]) == ["iterative", "dual", "qp"]


def test_problems_are_reproducible_and_mix_the_degenerate_kinds():
    first = list(soak.specs(5, 1200))
    assert len(first) == 1200
    again = soak.spec_at(5, 1100)
    np.testing.assert_array_equal(again.x, first[1100].x)
    assert again.kind == first[1100].kind and again.gain_exponent == first[1100].gain_exponent
    kinds = {spec.kind for spec in first}
    assert kinds == set(soak.KINDS)
    assert 0.1 < np.mean([spec.kind != "random" for spec in first]) < 0.3
    assert {spec.n for spec in first} == set(range(soak.MIN_UNITS, soak.MAX_UNITS + 1))
    for kind in soak.DEGENERATE_KINDS:  # every kind builds
        problem = next(spec for spec in first if spec.kind == kind).build()
        assert np.all(np.isfinite(problem.nominal))
    zero = next(spec for spec in first if spec.kind == "zero_nominal").build()
    np.testing.assert_allclose(zero.nominal, 0.0, atol=1e-12)


class Broken:
    """Raises, returns NaN or leaves the sets, by turns; the soak must count each."""

    name = "broken"

    def __init__(self) -> None:
        self.calls = 0

    def allocate(self, problem):
        self.calls += 1
        if self.calls % 3 == 1:
            raise RuntimeError("injected")
        velocities = np.full((problem.n, 2), np.nan if self.calls % 3 == 2 else 0.0)
        return Allocation(velocities, self.name, "fallback:injected", 0, 0.0, 0.0, 0.0, fell_back=True)


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
    assert entry["limit_violations"] == 0  # an allocator of unknown kind promises nothing
    assert len(entry["examples"]["exception"]) == soak.EXAMPLES
    assert entry["statuses"] == {"fallback:injected": 20}
    assert "| iterative | 30 | 10 | 10 | 0 |" in (tmp_path / "soak.md").read_text()


def test_show_rebuilds_a_problem():
    text = soak.show(7, seed=1, allocators=["dual"])
    assert text.startswith("problem 7 of seed 1: kind ") and "dual: status 'optimal'" in text
