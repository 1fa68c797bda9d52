"""Each input the issue "Trustworthy failures" (sections 1 and 2) names, by name, through the
command line's entry point in this process: exit 2 and one stderr line naming the file or flag,
the key and the value, no traceback; or, where the issue asks for a run, a run that says what it
could not do."""

from __future__ import annotations

import json

import pytest

from platoon_opt.solvers import available_allocators
from platoon_opt.solvers.registry import registered
from platoon_opt.study.cli import main
from tests.conftest import scenario_text

SHORT = ["--duration", "0.02", "--no-figures"]


def _refused(capsys, argv: list[str], *parts: str) -> str:
    """Run ``argv``: exit 2, one stderr line ``platoon-opt: error: ...`` holding every one of
    ``parts``, no traceback; returns the line."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("platoon-opt: error: ") and "Traceback" not in err, err
    for part in parts:
        assert part in err, (part, err)
    return err.strip()


def _file(tmp_path, old: str, new: str, name: str = "paper_obstacles") -> str:
    text = scenario_text(name)
    assert old in text
    path = tmp_path / "edited.toml"
    path.write_text(text.replace(old, new, 1))
    return str(path)


# --- section 1: flags ----------------------------------------------------------------------------


def test_duration_minus_one_is_exit_2_one_line(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--duration", "-1", "--out", str(tmp_path / "out")]
    _refused(capsys, argv, "argument --duration", "got '-1'")
    assert not (tmp_path / "out").exists()


def test_duration_nan_is_exit_2_one_line(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--duration", "nan", "--out", str(tmp_path)]
    _refused(capsys, argv, "argument --duration", "finite", "got 'nan'")


def test_duration_inf_is_exit_2_one_line(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--duration", "inf", "--out", str(tmp_path)]
    _refused(capsys, argv, "argument --duration", "finite", "got 'inf'")


def test_duration_zero_is_exit_2_not_an_all_zero_run(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--duration", "0", "--out", str(tmp_path)]
    _refused(capsys, argv, "argument --duration", "got '0'")
    assert not (tmp_path / "metrics.json").exists()


def test_duration_shorter_than_one_step_is_exit_2(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--duration", "0.004", "--out", str(tmp_path)]
    _refused(capsys, argv, "--duration must be at least one step (dt = 0.01 s", "got 0.004")


@pytest.mark.parametrize("command", ["simulate", "compare"])
def test_simulate_checks_duration_as_compare_does(command, tmp_path, capsys):
    argv = [command, "paper_obstacles", "--duration", "-1", "--out", str(tmp_path)]
    _refused(capsys, argv, "argument --duration: must be a finite number of seconds > 0, got '-1'")


def test_seed_minus_one_is_exit_2_one_line(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--seed", "-1", *SHORT, "--out", str(tmp_path)]
    _refused(capsys, argv, "argument --seed", "integer >= 0", "got '-1'")


def test_out_naming_an_existing_file_is_exit_2(tmp_path, capsys):
    existing = tmp_path / "file.txt"
    existing.write_text("x")
    argv = ["simulate", "paper_obstacles", *SHORT, "--out", str(existing)]
    _refused(capsys, argv, f"--out must be a folder, got '{existing}', an existing file")
    assert existing.read_text() == "x"


# --- section 1: scenario files -------------------------------------------------------------------


def test_scenario_path_that_is_a_folder_is_exit_2(tmp_path, capsys):
    _refused(capsys, ["simulate", str(tmp_path), *SHORT], f"{tmp_path}: is a folder, not a scenario file")


def test_non_utf8_scenario_is_exit_2(tmp_path, capsys):
    path = tmp_path / "latin1.toml"
    text = scenario_text("paper_obstacles").replace('description = "Sec. 4', 'description = "Sec. \xa74')
    path.write_bytes(text.encode("latin-1"))
    _refused(capsys, ["simulate", str(path), *SHORT], f"{path}: not UTF-8 text: bytes b'\\xa7' at line")


def test_negative_desired_variance_is_exit_2(tmp_path, capsys):
    path = _file(tmp_path, "var_x = 0.6384\n", "var_x = -0.5\n")
    _refused(capsys, ["simulate", path, *SHORT], f"{path}: task.desired.var_x must be > 0", "got -0.5")


def test_transient_longer_than_the_run_is_exit_2(tmp_path, capsys):
    path = _file(tmp_path, "transient = 4.0", "transient = 50.0")
    _refused(
        capsys,
        ["simulate", path, *SHORT],
        f"{path}: simulation.transient must be shorter than simulation.duration = 45.0",
        "got 50.0",
    )


def test_duration_within_the_transient_runs_and_warns_on_one_line(tmp_path, capsys):
    # A run shorter than the transient is a run (the fuzzer's are), but its after-transient
    # errors would read 0 silently: one warning line says so.
    assert main(["simulate", "paper_obstacles", *SHORT, "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert err == (
        "platoon-opt: warning: a run of 0.02 s ends within the 4 s transient of paper_obstacles: "
        "its after-transient errors are 0\n"
    )
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 2


def test_max_steering_deg_error_names_the_key_and_value_in_degrees(tmp_path, capsys):
    path = tmp_path / "steering.toml"
    path.write_text(scenario_text("paper_obstacles") + "\n[vehicle]\nmax_steering_deg = -30\n")
    line = _refused(
        capsys,
        ["simulate", str(path), *SHORT],
        f"{path}: vehicle.max_steering_deg must be in (0, 90) degrees",
    )
    assert line.endswith("got -30") and "max_steering " not in line and "0.5236" not in line


def test_unknown_key_lists_the_valid_keys_of_its_table(tmp_path, capsys):
    path = _file(tmp_path, "[avoidance]", "[avoidance]\nd_min = 1.0")
    _refused(
        capsys,
        ["simulate", path, *SHORT],
        f"{path}: unknown key avoidance.d_min = 1.0; valid: d_minr, d_mino, ahead_reference",
    )


# --- section 2: options --------------------------------------------------------------------------


def test_nmpc_task_weights_wrong_length_is_exit_2(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--solver", "nmpc", "--option", "task_weights=4,1"]
    _refused(
        capsys,
        [*argv, "--duration", "1", "--out", str(tmp_path)],
        "--solver nmpc: option task_weights of nmpc must be a tuple of 4 numbers",
        "got (4.0, 1.0)",
    )
    assert not (tmp_path / "metrics.json").exists()


def test_nmpc_task_weights_wrong_length_in_compare_is_exit_2_before_any_run(tmp_path, capsys):
    argv = ["compare", "paper_obstacles", "--solvers", "m=0", "nmpc:task_weights=(4,1)", "--seeds", "1"]
    _refused(capsys, [*argv, *SHORT, "--out", str(tmp_path)], "option task_weights of nmpc", "got (4.0, 1.0)")
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "name, option",
    [(name, option.name) for name in available_allocators() for option in registered(name).options],
)
def test_every_option_of_every_allocator_is_checked_when_it_is_built(name, option, tmp_path, capsys):
    # "@@" is text, which is no value of any rule (a number, a flag, a choice, a tuple, a table).
    argv = ["simulate", "paper_obstacles", "--solver", name, "--option", f"{option}=@@", *SHORT]
    _refused(capsys, [*argv, "--out", str(tmp_path)], f"option {option} of {name}", "'@@'")
    assert not tmp_path.joinpath("metrics.json").exists()


# --- found by the fuzzer -------------------------------------------------------------------------


def test_subnormal_max_steering_deg_is_exit_2_not_a_traceback(tmp_path, capsys):
    # 5e-324 degrees is > 0 but 0.0 rad once converted: VehicleLimits raised a ValueError.
    path = tmp_path / "steering.toml"
    path.write_text(scenario_text("paper_obstacles") + "\n[vehicle]\nmax_steering_deg = 5e-324\n")
    _refused(
        capsys, ["simulate", str(path), *SHORT], f"{path}: vehicle.max_steering_deg must be >= 1e-09 degrees"
    )


def test_an_option_given_twice_in_a_configuration_is_exit_2(tmp_path, capsys):
    # "iterative:gears=(,gears=model" ran under gears=model: the bad first value went unchecked.
    argv = ["compare", "paper_no_obstacles", "--solvers", "iterative:gears=(,gears=model", "--seeds", "1"]
    _refused(capsys, [*argv, *SHORT, "--out", str(tmp_path)], "option gears must be given once", "'gears=('")


def test_an_option_given_twice_to_simulate_is_exit_2(tmp_path, capsys):
    argv = ["simulate", "paper_obstacles", "--solver", "qp", "--option", "rho=-1", "--option", "rho=100"]
    _refused(capsys, [*argv, *SHORT, "--out", str(tmp_path)], "--option: option rho must be given once")
