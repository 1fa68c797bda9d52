"""The scenario battery: every shipped scenario under the reproduction's configurations, paired by
seed (``platoon-opt reproduce --battery``)."""

from __future__ import annotations

from collections.abc import Sequence

from platoon_opt.scenarios import load_scenario
from platoon_opt.study.config import AllocatorConfig
from platoon_opt.study.harness import Study, seeds_range
from platoon_opt.study.paper import DEFAULT, reproduce_configs

# The shipped scenarios, the paper's first; each file's header says what it tests.
BATTERY = (
    "paper_no_obstacles",
    "paper_obstacles",
    "paper_no_obstacles_offset",
    "paper_obstacles_offset",
    "paper_covariance",
    "three_units",
    "curved_field_16",
    "units_50",
    "units_200",
    "field_sparse",
    "field_dense",
    "narrow_passage",
    "figure_eight",
    "sharp_turns",
)

# Beside the reproduction's configurations: the task-exact programs that know the steering's reach
# (rate-aware sectors, the nominal velocities as the units drive them), in the gear rule's gear and
# in the nearer gear, and in the nearer gear only while the platoon catches up (docs/programs.md,
# section 3).
RATE_AWARE_PROGRAMS = ("qp-projection", "cone-projection")
# The gear rule's gear (the default, so no option: those labels stay what they were), then the
# nearer gear, then the nearer gear while catching up.
GEAR_CHOICES: tuple[dict[str, str], ...] = ({}, {"gears": "either"}, {"gears": "catching-up"})
# And the achievable-first programs in the nearer gear while catching up: their units then drive
# that gear without the gear rule's hysteresis, which loses the paths and wins the platoons that
# start far from their target (experiments/battery.md).
ACHIEVABLE_FIRST_PROGRAMS = ("qp", "cone")


def battery_configs(available: Sequence[str]) -> list[AllocatorConfig]:
    """``reproduce_configs``, ``RATE_AWARE_PROGRAMS`` with ``rate_aware=True`` in each of
    ``GEAR_CHOICES``, and ``ACHIEVABLE_FIRST_PROGRAMS`` with ``gears="catching-up"``, all through
    the dual."""
    extra = [
        AllocatorConfig.make(name, backend="dual", rate_aware=True, **gears)
        for gears in GEAR_CHOICES
        for name in RATE_AWARE_PROGRAMS
    ]
    extra += [
        AllocatorConfig.make(name, backend="dual", gears="catching-up") for name in ACHIEVABLE_FIRST_PROGRAMS
    ]
    return reproduce_configs(available) + [c for c in extra if c.name in available]


def battery_study(
    available: Sequence[str],
    *,
    seeds: int = DEFAULT.seeds,
    duration: float | None = None,
    configs: Sequence[AllocatorConfig] | None = None,
    strict: bool = False,
    check_seeds: int = DEFAULT.check_seeds,
) -> Study:
    """Every scenario of ``BATTERY`` under ``configs`` (default: ``battery_configs``, m = 0..8
    and the convex programs through the dual, the task-exact ones also rate-aware in the three
    gear choices, the achievable-first ones also in the nearer gear while catching up) on seeds
    0..seeds-1, no ablation; the dual cross-checked against Clarabel on the first ``check_seeds``
    seeds."""
    main_seeds = seeds_range(seeds)
    return Study(
        scenarios=tuple(load_scenario(name) for name in BATTERY),
        configs=tuple(configs if configs is not None else battery_configs(available)),
        seeds=main_seeds,
        duration=duration,
        strict=strict,
        check_seeds=main_seeds[: max(int(check_seeds), 0)],
    )
