"""Scenario files, seeds and durations are checked where they enter (issue "Trustworthy failures"):
every refusal is one line naming the file, the key as written and the value as written; the
library's own arguments (``simulate(duration=...)``, ``Scenario.initial(seed)``) are refused with a
``ValueError`` naming the argument and the value."""

from __future__ import annotations

import math

import numpy as np
import pytest

from platoon_opt import ScenarioError, load_scenario, simulate
from tests.conftest import NominalAllocator, scenario_text


def _load(tmp_path, text: str, name: str = "paper.toml"):
    path = tmp_path / name
    path.write_text(text) if isinstance(text, str) else path.write_bytes(text)
    return load_scenario(path)


def _refused(tmp_path, text, *parts: str) -> str:
    """The one-line message for ``text``, which must name the file and every one of ``parts``."""
    with pytest.raises(ScenarioError) as caught:
        _load(tmp_path, text)
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"{tmp_path / 'paper.toml'}: ")
    for part in parts:
        assert part in message, (part, message)
    return message


def _edit(name: str, old: str, new: str) -> str:
    text = scenario_text(name)
    assert old in text
    return text.replace(old, new, 1)


def test_an_unknown_key_lists_the_valid_keys_of_its_table(tmp_path):
    message = _refused(tmp_path, _edit("paper_obstacles", "[avoidance]", "[avoidance]\nbogus = 1"))
    valid = "d_minr, d_mino, ahead_reference"
    assert message == f"{tmp_path / 'paper.toml'}: unknown key avoidance.bogus = 1; valid: {valid}"


def test_an_odd_unknown_key_is_quoted(tmp_path):
    message = _refused(tmp_path, _edit("paper_obstacles", "[avoidance]", '[avoidance]\n"" = 1'))
    assert 'unknown key avoidance."" = 1; valid: d_minr' in message


def test_a_negative_desired_variance_is_refused(tmp_path):
    _refused(
        tmp_path, _edit("paper_obstacles", "var_x = 0.6384\n", "var_x = -0.5\n"), "task.desired.var_x", "-0.5"
    )


def test_a_zero_desired_variance_is_refused(tmp_path):
    _refused(
        tmp_path, _edit("paper_obstacles", "var_y = 0.5536\n", "var_y = 0\n"), "task.desired.var_y", "got 0"
    )


def test_a_desired_covariance_beyond_the_variances_is_refused(tmp_path):
    text = _edit("paper_covariance", "cov_xy = 0.55\n", "cov_xy = 0.75\n")  # sqrt(0.7 * 0.7) = 0.7
    _refused(tmp_path, text, "task.desired.cov_xy must be inside", "0.7", "got 0.75")
    _load(tmp_path, _edit("paper_covariance", "cov_xy = 0.55\n", "cov_xy = -0.69\n"))


def test_a_transient_as_long_as_the_run_is_refused_naming_both(tmp_path):
    text = _edit("paper_obstacles", "transient = 4.0", "transient = 50.0")
    _refused(
        tmp_path, text, "simulation.transient must be shorter than simulation.duration = 45.0", "got 50.0"
    )
    _refused(tmp_path, _edit("paper_obstacles", "transient = 4.0", "transient = 45.0"), "got 45.0")


def test_vehicle_errors_name_the_key_and_the_value_in_the_files_units(tmp_path):
    text = scenario_text("paper_obstacles") + "\n[vehicle]\nmax_steering_deg = -30\n"
    message = _refused(tmp_path, text, "vehicle.max_steering_deg", "-30")
    assert "VehicleLimits" not in message and "0.5236" not in message
    text = scenario_text("paper_obstacles") + "\n[vehicle]\ngear_hysteresis_deg = 90\n"
    _refused(tmp_path, text, "vehicle.gear_hysteresis_deg must be in [0, 90) degrees, got 90")
    text = scenario_text("paper_obstacles") + "\n[vehicle]\nmax_speed = 0\n"
    _refused(tmp_path, text, "vehicle.max_speed must be > 0, got 0")
    limits = _load(tmp_path, scenario_text("paper_obstacles") + "\n[vehicle]\nmax_steering_deg = 30\n").limits
    assert limits.max_steering == pytest.approx(math.radians(30))


@pytest.mark.parametrize(
    "old, new, parts",
    [
        ("dt = 0.01", "dt = nan", ("simulation.dt must be a finite number, got nan",)),
        ("dt = 0.01", "dt = -0.0", ("simulation.dt must be > 0, got -0.0",)),
        ("dt = 0.01", "dt = 1e-308", ("simulation.dt must be >= 1e-09", "got 1e-308")),
        ("dt = 0.01", "dt = 1e-6", ("simulation.duration must be at most 10,000,000 steps", "got 45.0")),
        ("n = 8", "n = 9223372036854775807", ("platoon.n must be <= 1,000,000", "9223372036854775807")),
        ("speed = 0.8", "speed = 1e308", ("target.speed must be at most 1e+09 in magnitude, got 1e+308",)),
        (
            "center = [0.0, 0.0]",
            "center = [0.0, inf]",
            ("platoon.center[1] must be a finite number, got inf",),
        ),
        ("center = [0.0, 0.0]", "center = [0.0]", ("platoon.center must be [x, y], got [0.0]",)),
        ("[10.0, 0.0], [10.0, 6.0]", "[10.0, 0.0], [10.0, 0.0]", ("target.waypoints[2] must be at least",)),
        ("[0.0, 0.0], [10.0, 0.0]", "[0.0, 0.0], [1e-308, 0.0]", ("target.waypoints[1]", "1e-308")),
        (
            "gains = [50.0, 10.0, 50.0, 10.0]",
            "gains = [50.0, -1, 50.0, 10.0]",
            ("task.gains[1] must be >= 0",),
        ),
        ("radius = 0.5", "radius = []", ("obstacles[0].radius must be a number, got []",)),
        ('name = "paper_obstacles"', 'name = ".."', ("name must be printable text", "got '..'")),
        ("ring_phase = true", "ring_phase = 1", ("seed.ring_phase must be true or false, got 1",)),
    ],
)
def test_a_bad_value_is_one_line_naming_key_and_value(tmp_path, old, new, parts):
    _refused(tmp_path, _edit("paper_obstacles", old, new), *parts)


def test_two_units_without_a_ring_phase_are_refused(tmp_path):
    text = _edit("paper_no_obstacles", "n = 8", "n = 2").replace("ring_phase = true", "ring_phase = false")
    _refused(tmp_path, text, "platoon.n must be >= 3 when seed.ring_phase = false", "got 2")


def test_a_file_that_is_not_utf8_names_where(tmp_path):
    data = scenario_text("paper_obstacles").encode().replace(b"paper_obstacles", b"paper_\xffobstacles", 1)
    _refused(tmp_path, data, "not UTF-8 text: bytes b'\\xff' at line 9")


def test_a_folder_a_missing_file_and_an_empty_path_are_one_line(tmp_path):
    with pytest.raises(ScenarioError, match="is a folder, not a scenario file"):
        load_scenario(tmp_path)
    with pytest.raises(
        ScenarioError, match="no such scenario file, nor a shipped scenario .*paper_obstacles"
    ):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ScenarioError, match="an empty path"):
        load_scenario("")


def test_a_duplicate_key_names_its_line(tmp_path):
    text = _edit("paper_obstacles", "n = 8\n", "n = 8\nn = 9\n")
    _refused(tmp_path, text, "not valid TOML: Cannot overwrite a value (at line", "'n = 9'")


def test_an_empty_file_says_so(tmp_path):
    _refused(tmp_path, "", "missing key name (the file holds no keys")


def test_a_byte_order_mark_is_allowed(tmp_path):
    assert _load(tmp_path, "\ufeff" + scenario_text("paper_obstacles")).name == "paper_obstacles"


@pytest.mark.parametrize("duration", [-1.0, 0.0, math.nan, math.inf, 0.001, 1e308, "1", True])
def test_simulate_refuses_a_bad_duration_naming_it(duration):
    with pytest.raises(ValueError, match=r"^duration must be .*got") as caught:
        simulate(load_scenario("paper_obstacles"), NominalAllocator(), duration=duration)
    assert repr(duration) in str(caught.value)


@pytest.mark.parametrize("seed", [-1, 1.5, "0", True, None])
def test_a_bad_seed_is_refused_naming_it(seed):
    scenario = load_scenario("paper_obstacles")
    with pytest.raises(ValueError, match=rf"^seed must be an integer >= 0, got {seed!r}$"):
        scenario.initial(seed)
    with pytest.raises(ValueError, match="^seed must be"):
        simulate(scenario, NominalAllocator(), seed=seed, duration=0.02)


def test_a_run_of_one_step_is_a_run():
    trajectory = simulate(
        load_scenario("paper_obstacles"), NominalAllocator(), duration=0.01, seed=np.int64(3)
    )
    assert trajectory.steps == 1 and trajectory.seed == 3
