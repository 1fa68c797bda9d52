"""The cross-check of the compiled dual against Clarabel replays the same problems from a study's
thinned track as from a run made again."""

from __future__ import annotations

import io

import pytest

from platoon_opt import load_scenario, simulate
from platoon_opt.solvers import get_allocator
from platoon_opt.study import crosscheck
from platoon_opt.study.config import AllocatorConfig, parse_config
from platoon_opt.study.crosscheck import cross_check
from platoon_opt.study.harness import Study, run_study
from platoon_opt.study.tracks import TRACK_STRIDE, thin


def test_a_kept_track_gives_the_check_of_a_run_made_again():
    scenario = load_scenario("paper_obstacles")
    config = parse_config("qp-projection:backend=dual")
    run = simulate(scenario, config.build(get_allocator), seed=3, duration=1.0, compiled=True)
    again = cross_check(scenario, config, get_allocator, (3,), every=10, duration=1.0)
    kept = cross_check(scenario, config, get_allocator, (3,), every=10, tracks=[thin(run, TRACK_STRIDE)])
    assert again.problems == kept.problems == 10 and again.agree and kept.agree
    assert kept == again
    with pytest.raises(ValueError, match="thinned by 5"):
        cross_check(scenario, config, get_allocator, (3,), every=12, tracks=[thin(run, TRACK_STRIDE)])


def test_a_study_checks_the_runs_it_kept_without_running_them_again(tmp_path, monkeypatch):
    scenario = load_scenario("paper_no_obstacles")
    config = parse_config("qp-projection:backend=dual")
    study = Study((scenario,), (parse_config("m=0"), config), (0, 1, 2), duration=1.0, check_seeds=(0, 1))
    assert [spec.keep_track for spec in study.main_specs()] == [True, False, False, True, True, False]

    def refuse(*args, **kwargs):
        raise AssertionError("the cross-check ran a kept run again")

    monkeypatch.setattr(crosscheck, "simulate", refuse)
    result = run_study(study, get_allocator, tmp_path, workers=1, stream=io.StringIO())
    (check,) = result.checks
    assert check.seeds == (0, 1) and check.problems == 4 and check.agree


def test_the_clarabel_reference_keeps_every_option_but_the_backend_and_says_so():
    config = AllocatorConfig.make("qp-projection", backend="dual", rate_aware=True)
    reference = crosscheck.clarabel_of(config)
    assert dict(reference.options) == {"backend": "clarabel", "rate_aware": True}
    assert reference.label == "qp-projection:clarabel,rate_aware=True"
    assert crosscheck.clarabel_of(AllocatorConfig.make("cone", backend="dual")).label == "cone:clarabel"
