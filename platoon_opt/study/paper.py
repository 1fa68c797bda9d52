"""The paper's numbers (Sec. 4 and Fig. 5) and the reproduction study that sets ours beside them."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

from platoon_opt.scenarios import PAPER_SCENARIOS, load_scenario
from platoon_opt.study.config import AllocatorConfig, default_configs
from platoon_opt.study.harness import Study, seeds_range
from platoon_opt.study.variants import ABLATION_VARIANTS, Variant

# The paper's percent changes against m = 0 (Sec. 4 and Fig. 5).
PAPER_RESULTS: dict[str, dict[str, Any]] = {
    "paper_no_obstacles": {
        "m": 4,
        "label": "Sec. 4, no obstacles",
        "changes": {
            "mean_position": -5.3,
            "mean_position_after_transient": -21.0,
            "var_x": -78.5,
            "var_y": -68.4,
        },
    },
    "paper_obstacles": {
        "m": 3,
        "label": "Fig. 5, obstacles, random headings",
        "changes": {"mean_position": -53.6, "var_x": -71.7, "var_y": -46.0},
    },
}


# The paper's best m per scenario (Sec. 4): the ablation runs it and the report compares at it.
PAPER_ITERATIONS = {"paper_no_obstacles": 4, "paper_obstacles": 3}


class StudySize(NamedTuple):
    """How much ``reproduce`` runs: seeds of the main comparison and of the ablation, the
    simulated time per run (s; None for each scenario's own), and the seeds of the cross-check of
    the compiled dual against Clarabel (``crosscheck``)."""

    seeds: int
    ablation_seeds: int
    duration: float | None = None
    check_seeds: int = 2


# ``reproduce`` defaults: the runs go through the compiled engine in batches, so seeds are cheap.
DEFAULT = StudySize(seeds=20, ablation_seeds=10)
# ``reproduce --quick``: a check of the whole pipeline, not a result.
QUICK = StudySize(seeds=2, ablation_seeds=1, duration=8.0, check_seeds=1)


# The ablation asks whether the modelling choices explain the paper's magnitudes, which it
# states at its m: it runs m = 0 and the paper's m (``compare`` and ``--solvers`` studies can
# add the best m and the best other allocator).
REPRODUCE_ABLATION_ROLES = ("paper_m",)


# Registered allocators ``reproduce`` leaves out unless named with --solvers (``compare``
# runs them): too slow for the time budget, or a cross-check of another allocator.
REPRODUCE_EXCLUDED = {
    "nmpc": "receding horizon, 15-75 ms per step (a 45 s run takes minutes)",
    "casadi-qp": "cross-check of qp: the same QP through CasADi's qpOASES",
    "dual": "it runs the convex programs' rows already (backend=dual)",
}
# The convex programs, which ``reproduce`` runs through the dual in the compiled engine.
CONVEX = ("qp", "qp-projection", "cone", "cone-projection")


def reproduce_configs(available: Sequence[str]) -> list[AllocatorConfig]:
    """``default_configs`` without the allocators of ``REPRODUCE_EXCLUDED``, the convex programs
    solved by the dual (``backend="dual"``: compiled, a batch of seeds per call)."""
    configs = default_configs([name for name in available if name not in REPRODUCE_EXCLUDED])
    return [AllocatorConfig.make(c.name, backend="dual") if c.name in CONVEX else c for c in configs]


def paper_study(
    available: Sequence[str],
    *,
    seeds: int = DEFAULT.seeds,
    ablation_seeds: int | None = DEFAULT.ablation_seeds,
    duration: float | None = None,
    configs: Sequence[AllocatorConfig] | None = None,
    variants: Sequence[Variant] = ABLATION_VARIANTS,
    strict: bool = False,
    check_seeds: int = DEFAULT.check_seeds,
) -> Study:
    """The reproduction: both paper scenarios; m = 0..8 and every other registered allocator
    (``available``: ``solvers.available_allocators()``) but ``REPRODUCE_EXCLUDED``, unless
    ``configs`` are given; seeds 0..seeds-1; the ablation over ``variants`` of m = 0, the
    paper's m and the best other allocator on the first ``ablation_seeds`` seeds (None: all);
    ``strict``: see ``Study.strict``; the configurations run through the dual cross-checked
    against Clarabel on the first ``check_seeds`` seeds (``Study.check_seeds``)."""

    main_seeds = seeds_range(seeds)
    ablation = main_seeds if ablation_seeds is None else main_seeds[: max(int(ablation_seeds), 1)]
    return Study(
        scenarios=tuple(load_scenario(name) for name in PAPER_SCENARIOS),
        configs=tuple(configs if configs is not None else reproduce_configs(available)),
        seeds=main_seeds,
        duration=duration,
        variants=tuple(variants),
        ablation_seeds=ablation,
        ablation_roles=REPRODUCE_ABLATION_ROLES,
        paper_iterations=PAPER_ITERATIONS,
        strict=strict,
        check_seeds=main_seeds[: max(int(check_seeds), 0)],
    )


def verdict(ours: float, low: float, high: float, paper: float) -> str:
    """Whether our percent change matches the paper's in direction and order of size.

    Direction: "yes" when the 95 % interval lies on the paper's side of 0, "no" when on the
    other side, "unclear" when it contains 0. Size: "same order" within a factor of 3 of
    the paper's change, else "smaller" / "larger" (with the ratio).
    """
    if not math.isfinite(ours):
        return "n/a"
    sign = math.copysign(1.0, paper)
    if sign * low > 0 and sign * high > 0:
        direction = "yes"
    elif sign * low < 0 and sign * high < 0:
        direction = "no"
    else:
        direction = "unclear"
    ratio = ours / paper
    if ratio <= 0:
        size = "opposite sign"
    else:
        size = "same order" if 1 / 3 <= ratio <= 3 else ("smaller" if ratio < 1 / 3 else "larger")
    return f"direction {direction}; {size} (x{ratio:.2f})"


def paper_sized(ours: float, low: float, high: float, paper: float) -> bool:
    """A reduction of the paper's size: significant, same direction, within a factor of 3."""
    return verdict(ours, low, high, paper).startswith("direction yes; same order")
