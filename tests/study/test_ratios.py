"""The comparison against the best m: ratio-of-means changes whose intervals stay in the possible
range, differences where the reference is negligible, the best m taken over 0..8."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from platoon_opt import load_scenario
from platoon_opt.study.best_m import best_m_by_score, best_m_of, best_m_section
from platoon_opt.study.config import parse_config
from platoon_opt.study.harness import Study
from platoon_opt.study.ratios import NEGLIGIBLE, Change, change_text, paired_change
from platoon_opt.study.statistics import RunTable

errors = st.lists(st.floats(1e-3, 1e3), min_size=2, max_size=25)


@settings(max_examples=200, deadline=None)
@given(errors, st.data())
def test_a_ratio_interval_never_leaves_the_possible_range(values, data):
    reference = data.draw(st.lists(st.floats(1e-3, 1e3), min_size=len(values), max_size=len(values)))
    change = paired_change(np.array(values), np.array(reference))
    assert change.kind == "ratio"
    assert change.value == 100 * (np.mean(values) / np.mean(reference) - 1)
    assert -100 <= change.low <= change.high
    assert 0 <= change.wins <= 1
    # Scale-free: the same errors in other units give the same change.
    scaled = paired_change(np.array(values) * 7.5, np.array(reference) * 7.5)
    assert math.isclose(scaled.value, change.value, rel_tol=1e-9, abs_tol=1e-9)
    assert math.isclose(scaled.low, change.low, rel_tol=1e-9, abs_tol=1e-9)


def test_a_constant_ratio_has_a_point_interval_and_reruns_the_same():
    reference = np.array([0.1, 0.3, 0.2, 0.5])
    change = paired_change(reference / 2, reference)
    assert change.kind == "ratio" and change.wins == 1.0
    assert (
        math.isclose(change.value, -50) and math.isclose(change.low, -50) and math.isclose(change.high, -50)
    )
    noisy = paired_change(reference * np.array([0.5, 1.2, 0.9, 0.7]), reference)
    assert noisy == paired_change(reference * np.array([0.5, 1.2, 0.9, 0.7]), reference)


def test_a_negligible_reference_is_compared_by_differences():
    # A rigid 3-unit formation: the best m's variance error is 1e-10, the allocator's 1e-9.
    reference = np.full(6, 1e-10)
    change = paired_change(np.full(6, 1e-9), reference)
    assert change.kind == "difference" and math.isclose(change.value, 9e-10)
    assert NEGLIGIBLE > 1e-9
    assert change_text(change, "m^2 s").startswith("+9e-10 m^2 s")
    assert paired_change(np.array([1.0, 2.0]), np.array([0.0, 0.0])).kind == "difference"


def test_counts_are_differences_and_nan_input_gives_no_number():
    change = paired_change(np.array([3.0, 5.0]), np.array([1.0, 1.0]), ratio=False)
    assert change.kind == "difference" and change.value == 3.0
    assert change_text(paired_change(np.array([math.nan]), np.array([1.0])), "m") == "—"


def _runs(errors_by_config):
    runs = []
    for config, values in errors_by_config.items():
        for seed, value in enumerate(values):
            runs.append(
                {
                    "scenario": "paper_no_obstacles",
                    "variant": "base",
                    "config": config,
                    "seed": seed,
                    **dict.fromkeys(
                        ("mean_position", "mean_position_after_transient", "var_x", "var_y"), value
                    ),
                    "gear_flips": 0.0,
                    "time_inside_obstacles": 0.0,
                }
            )
    return runs


def test_the_best_m_may_be_the_baseline_and_the_section_compares_against_it():
    configs = tuple(parse_config(c) for c in ("m=0", "m=1", "m=2", "qp-projection"))
    study = Study((load_scenario("paper_no_obstacles"),), configs, (0, 1, 2))
    table = RunTable(
        _runs(
            {
                "m=0": [1.0, 1.1, 0.9],
                "m=1": [2.0, 2.1, 1.9],
                "m=2": [3.0, 3, 3],
                "qp-projection": [0.5, 0.55, 0.45],
            }
        )
    )
    assert best_m_by_score(table, study, "paper_no_obstacles").label == "m=0"
    assert best_m_of(table, study, "paper_no_obstacles", "var_x").label == "m=0"
    section = best_m_section(study, table)
    assert "against the best m by score, `m=0`" in section
    assert "| `qp-projection` | -50 % [-50, -50]" in section
    assert "3/3; 3/3; 3/3" in section
    # No other allocator: no section.
    assert best_m_section(Study(study.scenarios, configs[:3], (0, 1, 2)), table) == ""


def test_a_narrow_interval_shows_the_decimals_it_needs():
    text = change_text(Change("ratio", 0.04, 0.03, 0.05, 20, 0.5), "")
    assert text == "+0.04 % [+0.03, +0.05]"
    assert change_text(Change("ratio", -51.0, -60.0, -42.0, 20, 0.5), "") == "-51 % [-60, -42]"
