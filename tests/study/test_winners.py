"""The report's "Who wins where": the best other allocator against the best m of each error, with
the verdict its paired interval gives, on runs whose answer is known."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from platoon_opt.study.config import AllocatorConfig
from platoon_opt.study.statistics import RunTable
from platoon_opt.study.winners import winners_section

CONFIGS = tuple(
    AllocatorConfig.make(n, **o)
    for n, o in [
        ("iterative", {"max_iterations": 0}),
        ("iterative", {"max_iterations": 4}),
        ("qp", {}),
        ("cone", {}),
    ]
)


def _runs(scenario: str, factors: dict[str, float]) -> list[dict]:
    """20 seeds; every error of a configuration is its factor times a seed's noisy level."""
    rng = np.random.default_rng(0)
    level = rng.uniform(1.0, 2.0, 20)
    runs = []
    for config in CONFIGS:
        for seed in range(20):
            value = factors[config.label] * level[seed] * (1 + 0.01 * rng.normal())
            errors = {k: value for k in ("mean_position", "mean_position_after_transient", "var_x", "var_y")}
            runs.append(
                {
                    "scenario": scenario,
                    "variant": "base",
                    "config": config.label,
                    "seed": seed,
                    **errors,
                    "time_inside_obstacles": 0.0,
                }
            )
    return runs


def test_the_best_other_allocator_meets_the_best_m_of_each_error():
    labels = [c.label for c in CONFIGS]
    runs = _runs("easy", dict(zip(labels, (1.0, 0.8, 0.5, 0.6))))  # qp beats m = 4 by ~37 %
    runs += _runs("hard", dict(zip(labels, (1.0, 0.5, 0.7, 0.9))))  # m = 4 beats qp
    study = SimpleNamespace(
        configs=CONFIGS, scenarios=(SimpleNamespace(name="easy"), SimpleNamespace(name="hard"))
    )
    text = winners_section(study, RunTable(runs))
    easy, hard = (line for line in text.splitlines() if line.startswith(("| easy", "| hard")))
    assert easy.count("**win**") == 4 and f"`{labels[2]}` vs `{labels[1]}`" in easy
    assert hard.count(" loss") == 4 and "**win**" not in hard
    assert "4 wins, 0 cells whose interval holds 0, 4 losses, of 8" in text
    # Time inside obstacles 0 on every seed of both: a difference of 0 with no mark.
    assert easy.endswith("+0 unit s [+0, +0] |") and hard.endswith("+0 unit s [+0, +0] |")
    # Each allocator on both: qp wins easy (4) and loses hard (4) by 0.7 / 0.5 - 1 = +40 %;
    # cone wins easy and loses hard by 0.9 / 0.5 - 1 = +80 %, its worst cell.
    rows = {line.split(" | ")[0]: line for line in text.splitlines() if line.startswith("| `")}
    qp, cone = rows[f"| `{labels[2]}`"], rows[f"| `{labels[3]}`"]
    for row, label, worst in ((qp, labels[2], 40), (cone, labels[3], 80)):
        assert row.startswith(f"| `{label}` | 4 | 0 | 4 | hard, ")
        assert abs(float(row.split(": ")[-1].split(" %")[0]) - worst) <= 3, row
