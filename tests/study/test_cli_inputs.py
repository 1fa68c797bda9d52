"""Every input of the command line gets one clear line and exit 2, never a traceback (issue
"Trustworthy failures"): each case the issue names, and one check for every command's numbers."""

from __future__ import annotations

import io
import json

import pytest

from platoon_opt.study.cli import main
from platoon_opt.study.config import parse_config, parse_value
from tests.conftest import scenario_text


def _error(capsys) -> str:
    """The one stderr line of a refused command (nothing else on stderr)."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("platoon-opt: error: ") and "Traceback" not in err, err
    return err.strip()


@pytest.mark.parametrize(
    "value, shown",
    [
        ("-1", "got '-1'"),
        ("nan", "got 'nan'"),
        ("inf", "got 'inf'"),
        ("0", "got '0'"),
        ("abc", "got 'abc'"),
        ("0.001", "at least one step (dt = 0.01 s of paper_"),
        ("1e308", "at most 10,000,000 steps"),
    ],
)
@pytest.mark.parametrize("command", ["simulate", "compare", "reproduce"])
def test_every_command_refuses_a_bad_duration(command, value, shown, tmp_path, capsys):
    args = {"simulate": ["simulate", "paper_obstacles"], "compare": ["compare", "paper_obstacles"]}
    args["reproduce"] = ["reproduce", "--seeds", "1", "--ablation-seeds", "0"]
    assert main([*args[command], "--duration", value, "--out", str(tmp_path / "out")]) == 2
    err = _error(capsys)
    assert "--duration" in err and shown in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "args, flag, value",
    [
        (["simulate", "paper_obstacles", "--seed", "-1"], "--seed", "'-1'"),
        (["simulate", "paper_obstacles", "--seed", "1.5"], "--seed", "'1.5'"),
        (["simulate", "paper_obstacles", "--iterations", "-2"], "--iterations", "'-2'"),
        (["compare", "paper_obstacles", "--workers", "0"], "--workers", "'0'"),
        (["compare", "paper_obstacles", "--seeds", "0"], "--seeds", "'0'"),
        (["compare", "paper_obstacles", "--seeds", "2000000"], "--seeds", "'2000000'"),
        (["compare", "paper_obstacles", "--first-seed", "-3"], "--first-seed", "'-3'"),
        (["reproduce", "--seeds", "x"], "--seeds", "'x'"),
        (["reproduce", "--ablation-seeds", "-1"], "--ablation-seeds", "'-1'"),
        (["reproduce", "--workers", "1.0"], "--workers", "'1.0'"),
        (["bench", "--sizes", "8", "1"], "--sizes", "'1'"),
        (["bench", "--sizes", "10000000"], "--sizes", "'10000000'"),
        (["soak", "--problems", "-5"], "--problems", "'-5'"),
        (["soak", "--jobs", "0"], "--jobs", "'0'"),
        (["soak", "--seed", "-1"], "--seed", "'-1'"),
        (["soak", "--degenerate-rate", "nan"], "--degenerate-rate", "'nan'"),
        (["soak", "--show", "-1"], "--show", "'-1'"),
        (["fuzz", "--cases", "0"], "--cases", "'0'"),
        (["fuzz", "--seed", "-1"], "--seed", "'-1'"),
        (["fuzz", "--show", "x"], "--show", "'x'"),
    ],
)
def test_every_number_is_checked_where_it_enters(args, flag, value, tmp_path, capsys):
    assert main([*args, "--out", str(tmp_path / "out")]) == 2
    err = _error(capsys)
    assert flag in err and value in err


def test_out_naming_an_existing_file_is_one_line(tmp_path, capsys):
    existing = tmp_path / "file"
    existing.write_text("x")
    assert main(["simulate", "paper_obstacles", "--duration", "0.1", "--out", str(existing)]) == 2
    assert f"--out must be a folder, got '{existing}', an existing file" in _error(capsys)
    assert main(["simulate", "paper_obstacles", "--duration", "0.1", "--out", str(existing / "sub")]) == 2
    assert "under the file" in _error(capsys)
    assert main(["compare", "paper_obstacles", "--duration", "0.1", "--out", ""]) == 2
    assert "--out must name a folder, got ''" in _error(capsys)


def test_a_scenario_path_that_is_a_folder_is_one_line(tmp_path, capsys):
    assert main(["simulate", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert f"{tmp_path}: is a folder, not a scenario file" in _error(capsys)


def test_a_scenario_file_that_is_not_utf8_is_one_line(tmp_path, capsys):
    path = tmp_path / "latin.toml"
    text = scenario_text("paper_obstacles").replace('description = "Sec. 4', 'description = "Sec. \xa74')
    path.write_bytes(text.encode("latin-1"))
    assert main(["simulate", str(path), "--out", str(tmp_path / "out")]) == 2
    assert f"{path}: not UTF-8 text: bytes b'\\xa7' at line 10" in _error(capsys)


def test_a_zero_duration_is_an_error_not_an_empty_run(tmp_path, capsys):
    assert main(["simulate", "paper_obstacles", "--duration", "0", "--out", str(tmp_path)]) == 2
    _error(capsys)
    assert not (tmp_path / "metrics.json").exists()


@pytest.mark.parametrize(
    "args, part",
    [
        (["nope"], "argument command: invalid choice: 'nope'"),
        ([], "the following arguments are required: command"),
        (["simulate"], "the following arguments are required: scenario"),
        (["simulate", "paper_obstacles", "--seed"], "argument --seed: expected one argument"),
        (["simulate", "paper_obstacles", "--bogus"], "unrecognized arguments: --bogus"),
        (["allocators", "nope", "--markdown"], "unknown allocator 'nope'"),
        (["compare", "paper_obstacles", "--solvers", "qp:"], "--solvers: solver must look like NAME"),
        (["compare", "paper_obstacles", "--solvers", "qp:rho=1,,eps=2"], "got 'qp:rho=1,,eps=2'"),
        (
            ["simulate", "paper_obstacles", "--solver", "qp", "--option", "rho=" + "-" * 5000 + "1"],
            "rho of qp",
        ),
    ],
)
def test_usage_errors_are_one_line(args, part, capsys, tmp_path):
    assert main([*args, *(["--out", str(tmp_path)] if args[:1] in (["compare"],) else [])]) == 2
    assert part in _error(capsys)


def test_help_and_version_return_0(capsys):
    assert main(["--version"]) == 0 and capsys.readouterr().out.startswith("platoon-opt ")
    assert main(["simulate", "--help"]) == 0 and "--no-figures" in capsys.readouterr().out


def test_option_values_that_would_exhaust_the_parser_stay_text():
    assert parse_value("-" * 10_000 + "1") == "-" * 10_000 + "1"
    assert parse_value("~" * 999 + "1") == "~" * 999 + "1"
    assert parse_value("(4, 1, 4, 1)") == (4, 1, 4, 1)
    with pytest.raises(ValueError, match="NAME:key=value"):
        parse_config("qp:")


def test_no_figures_writes_metrics_and_timeseries_only(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["simulate", "paper_obstacles", "--duration", "0.05", "--no-figures", "--out", str(out)]
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "timeseries.csv"]
    assert json.loads((out / "metrics.json").read_text())["steps"] == 5
    # A run within the 4 s transient says that its after-transient errors are 0.
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("platoon-opt: warning: a run of 0.05 s ends within")


class _ClosedPipe:
    """A stdout whose reader has gone (``platoon-opt ... | head`` after head exits)."""

    def write(self, text):
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self):
        pass

    def fileno(self):
        raise io.UnsupportedOperation("fileno")  # as io.StringIO: no descriptor to redirect


def test_output_cut_off_by_its_reader_is_exit_141_without_a_traceback(monkeypatch, capsys):
    monkeypatch.setattr("sys.stdout", _ClosedPipe())
    assert main(["allocators", "--markdown"]) == 141
    assert capsys.readouterr().err == ""
