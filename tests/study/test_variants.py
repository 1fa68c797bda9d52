"""The ablation variants' fields: each changes exactly what it says on a scenario, and a bad value
is refused in one line naming the field."""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import numpy as np
import pytest

from platoon_opt import load_scenario, simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.study.config import parse_config
from platoon_opt.study.runs import RunSpec, scenario_definition
from platoon_opt.study.variants import Variant


def _flat(scenario):
    """Every field a run depends on, flattened to (key path, value)."""
    definition = scenario_definition(scenario)
    definition.update(limits=asdict(scenario.limits))
    out = {}

    def walk(prefix, value):
        if isinstance(value, dict):
            for key, item in value.items():
                walk(f"{prefix}.{key}" if prefix else key, item)
        else:
            out[prefix] = value

    walk("", definition)
    return out


def _changed(variant, name="paper_obstacles"):
    scenario = load_scenario(name)
    before, after = _flat(scenario), _flat(variant.apply(scenario))
    return {key: after[key] for key in before if before[key] != after[key]}


@pytest.mark.parametrize(
    "variant, expected",
    [
        (Variant("x", start_offset=2.0), {"center": [-2.0, 0.0]}),
        (Variant("x", steering_gain=20.0), {"vehicle.steering_gain": 20.0, "limits.steering_gain": 20.0}),
        (Variant("x", integration="euler"), {"limits.integration": "euler"}),
        (
            Variant("x", gear_hysteresis_deg=0.0),
            {"vehicle.gear_hysteresis_deg": 0.0, "limits.gear_hysteresis": 0.0},
        ),
        (Variant("x", dt_scale=0.5), {"dt": 0.005}),
    ],
)
def test_each_field_changes_exactly_what_it_says(variant, expected):
    assert _changed(variant) == expected


def test_start_offset_places_the_platoon_west_of_the_target_start_with_the_same_spread():
    scenario = load_scenario("paper_no_obstacles")
    state, _ = Variant("x", start_offset=1.0).apply(scenario).initial(3)
    plain, _ = scenario.initial(3)
    np.testing.assert_allclose(state.x, plain.x - 1.0, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(state.y, plain.y)
    # Like the shipped file's target.start_offset = [1, 0]; 0 moves that platoon back onto the target.
    shipped = load_scenario("paper_no_obstacles_offset")
    np.testing.assert_array_equal(Variant("x", start_offset=1.0).apply(scenario).center, shipped.center)
    np.testing.assert_array_equal(Variant("x", start_offset=0.0).apply(shipped).center, [0.0, 0.0])


def test_euler_and_gain_change_the_run_and_its_fingerprint():
    scenario = load_scenario("paper_no_obstacles")
    config = parse_config("m=0")
    allocator = config.build(get_allocator)
    tracks = {}
    for variant in (Variant("base"), Variant("x", integration="euler"), Variant("y", steering_gain=20.0)):
        tracks[variant.name] = simulate(variant.apply(scenario), allocator, seed=0, duration=0.1)
    arc, euler, slow = tracks["base"], tracks["x"], tracks["y"]
    # Same steering (the controller sees the same first state), other positions: the Euler step
    # cuts each arc's half turn.
    np.testing.assert_array_equal(euler.alpha[1], arc.alpha[1])
    assert np.max(np.abs(np.asarray(euler.x) - np.asarray(arc.x))) > 0
    # The first step steers toward the steering limit: at the rate limit (40 rad/s) with K_alpha =
    # 100, a fifth of the way with K_alpha dt = 0.2.
    np.testing.assert_allclose(np.abs(arc.alpha[1]), 40.0 * scenario.dt, rtol=1e-12)
    np.testing.assert_allclose(np.abs(slow.alpha[1]), 0.2 * scenario.limits.max_steering, rtol=1e-12)
    fingerprints = {
        RunSpec(scenario, Variant(name, **fields), config, 0).fingerprint()
        for name, fields in (("a", {}), ("b", {"integration": "euler"}), ("c", {"steering_gain": 20.0}))
    }
    assert len(fingerprints) == 3


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"start_offset": -1.0}, "Variant.start_offset must be finite and >= 0, got -1.0"),
        ({"start_offset": math.inf}, "Variant.start_offset must be finite and >= 0, got inf"),
        ({"steering_gain": 0.0}, "Variant.steering_gain must be finite and > 0, got 0.0"),
        ({"integration": "rk4"}, "Variant.integration must be 'arc' or 'euler', got 'rk4'"),
        ({"dt_scale": math.nan}, "Variant.dt_scale must be finite and > 0, got nan"),
    ],
)
def test_bad_values_are_refused_in_one_line(fields, message):
    with pytest.raises(ValueError) as error:
        Variant("x", **fields)
    assert str(error.value) == message


def test_start_offset_of_an_explicit_formation_is_refused_in_one_line():
    scenario = load_scenario("paper_no_obstacles")
    explicit = replace(scenario, positions=scenario.initial(0)[0].positions)
    with pytest.raises(ValueError) as error:
        Variant("x", start_offset=1.0).apply(explicit)
    assert "\n" not in str(error.value)
    assert str(error.value).startswith("Variant.start_offset must be left out for paper_no_obstacles")
