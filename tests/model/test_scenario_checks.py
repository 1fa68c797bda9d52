"""Scenario files, seeds and durations are checked where they enter (issue "Trustworthy failures"):
every refusal is one line naming the file, the key as written and the value as written; the
library's own arguments (``simulate(duration=...)``, ``Scenario.initial(seed)``) are refused with a
``ValueError`` naming the argument and the value."""

from __future__ import annotations

import math

import numpy as np
import pytest

from platoon_opt import ScenarioError, load_scenario, simulate
from platoon_opt.study.fuzz_oracle import scenario_message
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


# --- the keys of issue 20: target kinds, formations, the start offset, obstacle fields ---------

CIRCLE = '[target]\nkind = "circle"\ncenter = [0.0, 5.0]\nradius = 5.0\nspeed = 0.8\n'
FIELD = "\n[obstacle_field]\ncount = 5\nradius_range = [0.3, 0.6]\nregion = [-2.0, -6.0, 22.0, 6.0]\n"


def _target(new: str) -> str:
    """paper_no_obstacles with its [target] table replaced by ``new``."""
    waypoints = "[[0.0, 0.0], [10.0, 0.0], [10.0, 6.0], [3.0, 6.0], [8.0, 6.0], [8.0, -2.0]]"
    return _edit("paper_no_obstacles", f"[target]\nspeed = 0.8\nwaypoints = {waypoints}\n", new)


def _platoon(new: str, n: int = 8, target: str = "") -> str:
    """paper_no_obstacles with its [platoon] table's keys but n replaced by ``new``, and without
    seed.ring_phase (a key of the ring only)."""
    old = (
        "center = [0.0, 0.0]\n"
        "variance = [0.6384, 0.5536]   # m^2, the initial sample variances, met exactly\n"
        "heading = 1.5707963267948966  # pi/2\n"
    )
    text = _edit("paper_no_obstacles", old, new).replace("n = 8", f"n = {n}", 1)
    text = text.replace("ring_phase = true   # a seed rotates the units around the ring\n", "")
    return text.replace("[target]\nspeed = 0.8\n", f"[target]\nspeed = 0.8\n{target}", 1)


@pytest.mark.parametrize(
    "text, parts",
    [
        (
            _target('[target]\nkind = "spiral"\nspeed = 1.0\n'),
            ("target.kind must be 'polyline' or 'rounded'", "got 'spiral'"),
        ),
        (_target(CIRCLE.replace("radius = 5.0\n", "")), ("missing key target.radius",)),
        (
            _target(CIRCLE + "turn_radius = 1.0\n"),
            ("target.turn_radius must be left out with target.kind = 'circle'", "got 1.0"),
        ),
        (_target(CIRCLE + "laps = 0\n"), ("target.laps must be > 0, got 0",)),
        (
            _target(CIRCLE.replace("speed = 0.8", "speeds = [0.8]")),
            ("target.speeds must be left out with target.kind = 'circle'",),
        ),
        (_target(CIRCLE.replace("speed = 0.8\n", "")), ("missing key target.speed (or target.speeds",)),
        (
            _target("[target]\nspeed = 0.8\nspeeds = [0.8]\nwaypoints = [[0.0, 0.0], [1.0, 0.0]]\n"),
            ("target.speeds must be left out when target.speed is given",),
        ),
        (
            _target("[target]\nspeeds = [0.8]\nwaypoints = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]\n"),
            ("target.speeds must be a list of 2 speeds", "got [0.8]"),
        ),
        (
            _target("[target]\nspeeds = [0.8, -1]\nwaypoints = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]\n"),
            ("target.speeds[1] must be > 0, got -1",),
        ),
        (
            _edit("paper_no_obstacles", "[target]\n", '[target]\nkind = "rounded"\nturn_radius = 1.0\n'),
            ("target.waypoints[3] must be no reversal", "got [3.0, 6.0]"),
        ),
        (
            _target(
                '[target]\nkind = "rounded"\nturn_radius = 4.0\nspeed = 1.0\n'
                "waypoints = [[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]]\n"
            ),
            (
                "target.turn_radius must be small enough for the arcs at target.waypoints[1] and [2]",
                "5 m leg (they need 8 m)",
                "got 4.0",
            ),
        ),
        (
            _target(
                '[target]\nkind = "spline"\nspeed = 1.0\nwaypoints = [[0.0, 0.0], [5.0, 0.0], [0.0, 0.0]]\n'
            ),
            ("target.waypoints[1] must be no point where", "cusp", "got [5.0, 0.0]"),
        ),
        (
            _target('[target]\nkind = "spline"\nspeed = 1.0\nwaypoints = [[0.0, 0.0]]\n'),
            ("target.waypoints must be a list of at least 2 [x, y]",),
        ),
        (
            _target(
                '[target]\nkind = "figure_eight"\ncenter = [0.0, 0.0]\nsize = [10.0, 0.0]\nspeed = 1.0\n'
            ),
            ("target.size[1] must be >= 1e-09 (m), got 0.0",),
        ),
        (
            _target(
                '[target]\nkind = "figure_eight"\ncenter = [0.0, 0.0]\nsize = [1e6, 1e-6]\nspeed = 1.0\n'
            ),
            ("target.size must be less elongated", "got [1000000.0, 1e-06]"),
        ),
        (_target(CIRCLE + "start_offset = [1.0]\n"), ("target.start_offset must be [x, y], got [1.0]",)),
        (
            _target(CIRCLE + "start_offset = [1.0, 0.0]\n"),
            ("platoon.center must be left out when target.start_offset places the platoon", "got [0.0, 0.0]"),
        ),
        (_platoon("variance = [0.6, 0.5]\n"), ("missing key platoon.center (or target.start_offset)",)),
        (
            _platoon('center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nformation = "blob"\n'),
            ("platoon.formation must be 'ring' or 'disk'", "got 'blob'"),
        ),
        (_platoon('center = [0.0, 0.0]\nformation = "grid"\n'), ("missing key platoon.variance",)),
        (
            _platoon('center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nformation = "grid"\n', n=2),
            ("platoon.n must be >= 3 with platoon.formation = 'grid'", "got 2"),
        ),
        (
            _platoon('center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nformation = "grid"\n').replace(
                "[seed]\n", "[seed]\nring_phase = false\n"
            ),
            ("seed.ring_phase must be left out with platoon.formation = 'grid'", "got False"),
        ),
        (
            _platoon("center = [0.0, 0.0]\nvariance = [0.6, 0.5]\npositions = [[0.0, 0.0]]\n"),
            ("platoon.positions must be left out with platoon.formation = 'ring'",),
        ),
        (
            _platoon('formation = "explicit"\n', n=3),
            ("missing key platoon.positions",),
        ),
        (
            _platoon(
                'formation = "explicit"\ncenter = [0.0, 0.0]\n'
                "positions = [[0.0, 0.0], [1.0, 1.0], [2.0, 0.0]]\n",
                n=3,
            ),
            ("platoon.center must be left out with platoon.formation = 'explicit'", "got [0.0, 0.0]"),
        ),
        (
            _platoon('formation = "explicit"\npositions = [[0.0, 0.0], [1.0, 1.0]]\n', n=3),
            ("platoon.positions must be a list of platoon.n = 3 [x, y]",),
        ),
        (
            _platoon('formation = "explicit"\npositions = [[0.0, 0.0], [1.0, 1.0], [0.0, 0.0]]\n', n=3),
            ("platoon.positions[", "must be at least 1e-09 m from every other unit", "got [0.0, 0.0]"),
        ),
        (
            _platoon('formation = "explicit"\npositions = [[0.0, 1.0], [1.0, 1.0], [2.0, 1.0]]\n', n=3),
            ("platoon.positions must be spread along both axes",),
        ),
        (
            _platoon(
                'formation = "explicit"\npositions = [[0.0, 0.0], [1.0, 1.0], [2.0, 0.0]]\n',
                n=3,
                target="start_offset = [1.0, 0.0]\n",
            ),
            ("target.start_offset must be left out with platoon.formation = 'explicit'", "got [1.0, 0.0]"),
        ),
        (
            _platoon('center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nheadings = "fixed"\n').replace(
                "headings = false", "headings = true"
            ),
            ("seed.headings must be false or left out with platoon.headings = 'fixed', got True",),
        ),
        (
            _platoon('center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nheadings = "north"\n'),
            ("platoon.headings must be 'fixed' or 'random' or 'toward_target', got 'north'",),
        ),
        (
            scenario_text("paper_no_obstacles") + FIELD.replace("count = 5", "count = 0"),
            ("obstacle_field.count must be in [1, 1,000], got 0",),
        ),
        (
            scenario_text("paper_no_obstacles") + FIELD.replace("region = [-2.0, -6.0, 22.0, 6.0]\n", ""),
            ("missing key obstacle_field.region",),
        ),
        (
            scenario_text("paper_no_obstacles") + FIELD.replace("[0.3, 0.6]", "[0.6, 0.3]"),
            ("obstacle_field.radius_range[1] must be radius_range[1] >= radius_range[0]", "got 0.3"),
        ),
        (
            scenario_text("paper_no_obstacles") + FIELD.replace("22.0, 6.0]", "22.0, -5.5]"),
            (
                "obstacle_field.region[3] must be at least 2 radius_range[1] = 1.2 m above region[1] = -6",
                "got -5.5",
            ),
        ),
        (
            scenario_text("paper_no_obstacles")
            + FIELD.replace("count = 5", "count = 900").replace("[0.3, 0.6]", "[0.5, 0.6]"),
            ("obstacle_field.count must be small enough for that many obstacles to fit", "got 900"),
        ),
        (
            scenario_text("paper_no_obstacles") + FIELD + "path_gap = -1.0\n",
            ("obstacle_field.path_gap must be >= 0, got -1.0",),
        ),
        (
            scenario_text("paper_no_obstacles") + FIELD + "gap = 1.0\n",
            (
                "unknown key obstacle_field.gap = 1.0; valid: count, radius_range, region, path_gap, "
                "start_gap, obstacle_gap",
            ),
        ),
    ],
)
def test_the_new_keys_are_refused_in_one_line_naming_key_and_value(tmp_path, text, parts):
    message = _refused(tmp_path, text, *parts)
    # The fuzzer's oracle reads the same message back against the file: the key as written and its
    # value, or a default key's rule.
    assert scenario_message(message.split(": ", 1)[1], text.encode()) is None, message


def test_every_target_kind_and_formation_loads(tmp_path):
    for table in (
        CIRCLE + "laps = 0.5\nstart_angle_deg = 0.0\nclockwise = true\n",
        '[target]\nkind = "figure_eight"\ncenter = [0.0, 0.0]\nsize = [8.0, 3.0]\nspeed = 0.6\nlaps = 2\n',
        '[target]\nkind = "spline"\nspeeds = [0.5, 0.8]\nwaypoints = [[0.0, 0.0], [4.0, 1.0], [6.0, 5.0]]\n',
        '[target]\nkind = "rounded"\nturn_radius = 0.5\nspeed = 0.7\n'
        "waypoints = [[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]]\n",
        "[target]\nspeed = 0.7\nwaypoints = [[0.0, 0.0]]\n",
    ):
        assert _load(tmp_path, _target(table)).target.length >= 0
    for formation in ("disk", "grid", "line"):
        text = _platoon(f'center = [0.0, 0.0]\nvariance = [0.6, 0.5]\nformation = "{formation}"\n')
        assert _load(tmp_path, text).formation == formation
