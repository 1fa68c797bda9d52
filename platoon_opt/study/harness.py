"""The comparison harness: every allocator configuration on identical scenarios, over many seeds.

A ``Study`` names scenarios, configurations (the first is the baseline), seeds and an ablation;
``run_study`` runs the main comparison, then the ablation of the configurations the statistics
single out (``statistics.roles``), then the figure runs, and returns a ``StudyResult`` (the
command line writes its report, ``report.write_report``). The allocators are passed in as a
factory (``platoon_opt.solvers.get_allocator``), which must be picklable (a module-level
function) to reach worker processes.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from platoon_opt.allocation import check_allocator
from platoon_opt.errors import OptionError
from platoon_opt.scenarios import Scenario, check_seed
from platoon_opt.solvers.convex.allocator import DUAL
from platoon_opt.study.config import AllocatorConfig, AllocatorFactory
from platoon_opt.study.crosscheck import CrossCheck, cross_check
from platoon_opt.study.dispatch import run_specs, trajectories_of
from platoon_opt.study.executor import Progress
from platoon_opt.study.fallbacks import study_counts
from platoon_opt.study.runs import RunSpec
from platoon_opt.study.statistics import roles
from platoon_opt.study.tracks import load_track
from platoon_opt.study.variants import BASE, Variant
from platoon_opt.trajectory import Trajectory


@dataclass(frozen=True)
class Study:
    """A comparison: every configuration on every scenario and seed, plus an ablation.

    Attributes:
        scenarios: the scenarios.
        configs: allocator configurations; the first is the baseline of every comparison
            (the paper's m = 0 by default).
        seeds: scenario seeds of the main comparison.
        duration: simulated time per run (s); None for each scenario's.
        variants: ablation variants (none for a plain comparison).
        ablation_seeds: seeds of the ablation runs (defaults to ``seeds``).
        ablation_roles: which configurations the ablation runs besides the baseline:
            "paper_m" (the paper's best m), "best_m" (ours), "best_other" (the best
            allocator other than the paper's iteration), as found by ``report.roles``.
        paper_iterations: scenario name -> the paper's best m.
        strict: every run ends with ``AllocationError`` at its first failed allocation
            (``RunSpec.strict``).
        check_seeds: the seeds on which every configuration run through the dual in the engine
            (``backend="dual"``) is cross-checked against Clarabel (``crosscheck``); none: no check.
    """

    scenarios: tuple[Scenario, ...]
    configs: tuple[AllocatorConfig, ...]
    seeds: tuple[int, ...]
    duration: float | None = None
    variants: tuple[Variant, ...] = ()
    ablation_seeds: tuple[int, ...] = ()
    ablation_roles: tuple[str, ...] = ("paper_m", "best_m", "best_other")
    paper_iterations: Mapping[str, int] = field(default_factory=dict)
    strict: bool = False
    check_seeds: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not self.scenarios or not self.configs or not self.seeds:
            raise ValueError("a study needs at least one scenario, configuration and seed")
        labels = [c.label for c in self.configs]
        if len(set(labels)) != len(labels):
            raise ValueError(f"configuration labels must be unique, got {labels}")
        names = [s.name for s in self.scenarios]
        if len(set(names)) != len(names):
            raise ValueError(f"scenario names must be unique, got {names}")
        if not self.ablation_seeds:
            object.__setattr__(self, "ablation_seeds", self.seeds)
        unknown = set(self.ablation_roles) - {"paper_m", "best_m", "best_other"}
        if unknown:
            raise ValueError(f"ablation_roles must be paper_m, best_m or best_other, got {sorted(unknown)}")
        for scenario in self.scenarios:
            scenario.run_steps(self.duration)  # ValueError naming the duration: no run of it
        for seed in (*self.seeds, *self.ablation_seeds):
            check_seed(seed)

    @property
    def baseline(self) -> AllocatorConfig:
        """The configuration every other one is compared with."""
        return self.configs[0]

    def checked(self, config: AllocatorConfig) -> bool:
        """Whether ``config``'s runs on the check seeds are cross-checked against Clarabel."""
        return bool(self.check_seeds) and dict(config.options).get("backend") == DUAL

    def main_specs(self) -> list[RunSpec]:
        """Every scenario x configuration x seed, unchanged scenarios; the first seed's runs
        keep their tracks for the figures, and the cross-checked runs theirs for the check."""
        return [
            RunSpec(
                scenario,
                BASE,
                config,
                seed,
                self.duration,
                keep_track=seed == self.seeds[0] or (seed in self.check_seeds and self.checked(config)),
                strict=self.strict,
            )
            for scenario in self.scenarios
            for config in self.configs
            for seed in self.seeds
        ]

    def ablation_specs(self, configs: Mapping[str, Sequence[AllocatorConfig]]) -> list[RunSpec]:
        """Every affecting variant x ``configs[scenario name]`` x ablation seed."""
        return [
            RunSpec(scenario, variant, config, seed, self.duration, strict=self.strict)
            for scenario in self.scenarios
            for variant in self.variants
            if variant.affects(scenario)
            for config in configs[scenario.name]
            for seed in self.ablation_seeds
        ]


@dataclass
class StudyResult:
    """Results of a study: per-run result dicts and the figure trajectories.

    Attributes:
        study: what was run.
        runs: one result dict per run (main and ablation), in a fixed order.
        ablation_configs: scenario name -> configurations the ablation ran.
        figures: scenario name -> (panel title, trajectory) of the first seed's figure runs
            (thinned: every ``TRACK_STRIDE``-th instant).
        wall_time: seconds the study took (reused runs cost nothing).
        computed: runs computed now (the rest were reused).
        checks: the cross-checks of the compiled dual against Clarabel (``Study.check_seeds``).
    """

    study: Study
    runs: list[dict[str, Any]]
    ablation_configs: dict[str, list[AllocatorConfig]]
    figures: dict[str, list[tuple[str, Trajectory]]]
    wall_time: float
    computed: int
    checks: list[CrossCheck] = field(default_factory=list)


def run_study(
    study: Study,
    factory: AllocatorFactory,
    out: str | Path,
    *,
    workers: int | None = None,
    scheduler: Any = None,
    fresh: bool = False,
    stream: TextIO | None = None,
    label: str = "runs",
) -> StudyResult:
    """Run a study into ``out/runs/`` (resumable: finished runs are kept and reused).

    Order: the main comparison; then, per scenario, the ablation of the baseline and of
    ``study.ablation_roles`` (found from the main comparison); then the figures of the
    first seed (baseline, best m, best other allocator) from the tracks the main runs kept.
    Before any run every configuration is built and checked against each scenario's task
    (``check_configs``); after the last, one warning line per configuration and scenario that fell
    back on more than 1 % of its steps goes to ``stream`` (``fallbacks.study_counts``).

    Args:
        factory: ``platoon_opt.solvers.get_allocator``.
        workers, scheduler, fresh: as in ``run_specs``.
        stream: where the progress bars and the fallback warnings go (default stderr).
        label: the progress bars' prefix.

    Returns:
        The study's results (``report.write_report`` writes them out).
    """
    start = time.perf_counter()
    check_configs(study, factory)
    runs_dir = Path(out) / "runs"
    options = {"runs_dir": runs_dir, "workers": workers, "scheduler": scheduler, "fresh": fresh}
    main = study.main_specs()
    with Progress(len(main), f"{label}: main", stream=stream) as progress:
        main_runs = run_specs(main, factory, progress=progress, **options)
    computed = progress.computed
    found = {scenario.name: roles(main_runs, study, scenario.name) for scenario in study.scenarios}
    ablation_configs = {
        name: _unique([study.baseline, *(role[k] for k in study.ablation_roles)])
        for name, role in found.items()
    }
    ablation_runs: list[dict[str, Any]] = []
    ablation = study.ablation_specs(ablation_configs) if study.variants else []
    if ablation:
        with Progress(len(ablation), f"{label}: ablation", stream=stream) as progress:
            ablation_runs = run_specs(ablation, factory, progress=progress, **options)
        computed += progress.computed
    titled = [
        (scenario, title, config)
        for scenario in study.scenarios
        for title, config in _figure_configs(study, found[scenario.name])
    ]
    specs = [
        RunSpec(scenario, BASE, config, study.seeds[0], study.duration, strict=study.strict)
        for scenario, _, config in titled
    ]
    tracks = [_kept_track(runs_dir, spec) for spec in specs]
    # A track is missing when its run was reused from a study that kept none (other seeds).
    missing = [i for i, track in enumerate(tracks) if track is None]
    simulated = trajectories_of([specs[i] for i in missing], factory, workers=workers, scheduler=scheduler)
    for i, trajectory in zip(missing, simulated):
        tracks[i] = trajectory
    figures: dict[str, list[tuple[str, Trajectory]]] = {scenario.name: [] for scenario in study.scenarios}
    for (scenario, title, _), track in zip(titled, tracks):
        assert track is not None  # kept, or simulated just above
        figures[scenario.name].append((title, track))
    runs = main_runs + ablation_runs
    for count in study_counts(runs):
        if count.too_many:
            print(count.warning(), file=stream if stream is not None else sys.stderr)
    checks = [
        cross_check(
            scenario,
            config,
            factory,
            study.check_seeds,
            duration=study.duration,
            tracks=[
                _kept_track(runs_dir, RunSpec(scenario, BASE, config, seed, study.duration))
                for seed in study.check_seeds
            ],
        )
        for scenario in study.scenarios
        for config in study.configs
        if study.checked(config)
    ]
    return StudyResult(
        study=study,
        runs=runs,
        checks=checks,
        ablation_configs=ablation_configs,
        figures=figures,
        wall_time=time.perf_counter() - start,
        computed=computed,
    )


def check_configs(study: Study, factory: AllocatorFactory) -> None:
    """Build every configuration once and let it check each scenario's task
    (``allocation.check_allocator``), here, before any run starts in any worker.

    Raises:
        ConfigurationError: a bad option (``OptionError``), naming the configuration and the option.
    """
    tasks = {scenario.task_kind: tuple(scenario.task().names) for scenario in study.scenarios}
    for config in study.configs:
        allocator = config.build(factory)
        for names in tasks.values():
            try:
                check_allocator(allocator, names)
            except OptionError as error:
                raise OptionError(f"{config.label}: {error}") from None


def _kept_track(runs_dir: Path, spec: RunSpec) -> Trajectory | None:
    """The thinned trajectory ``spec``'s run kept in ``runs_dir``, or None (a run reused from a
    study that kept none)."""
    path = runs_dir / f"{spec.key}.npz"
    return load_track(path) if path.exists() else None


def _figure_configs(
    study: Study, roles: Mapping[str, AllocatorConfig | None]
) -> list[tuple[str, AllocatorConfig]]:
    """(panel title, configuration) of a scenario's figures: the baseline, the best m and the
    best other allocator."""
    panels = [("baseline", study.baseline), ("best m", roles["best_m"]), ("best other", roles["best_other"])]
    seen: set[str] = set()
    titled = []
    for title, config in panels:
        if config is not None and config.label not in seen:
            seen.add(config.label)
            titled.append((f"{title}: {config.label}", config))
    return titled


def _unique(configs: Sequence[AllocatorConfig | None]) -> list[AllocatorConfig]:
    seen: dict[str, AllocatorConfig] = {}
    for config in configs:
        if config is not None and config.label not in seen:
            seen[config.label] = config
    return list(seen.values())


def seeds_range(count: int, first: int = 0) -> tuple[int, ...]:
    """Seeds ``first .. first + count - 1`` (a later first seed checks a choice on fresh seeds).

    Raises:
        ValueError: ``count < 1`` or ``first < 0``.
    """
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"seeds must be an integer >= 1, got {count!r}")
    if isinstance(first, bool) or not isinstance(first, (int, np.integer)) or first < 0:
        raise ValueError(f"the first seed must be an integer >= 0, got {first!r}")
    return tuple(range(int(first), int(first) + int(count)))
