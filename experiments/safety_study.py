"""The cost of hard safety in closed loop: tables from ``platoon-opt compare`` folders.

Run the study (20 seeds per scenario), e.g. on every shipped scenario with the two task-exact
programs through the dual (the m's and the programs without barriers come from the battery's
runs of the same seeds, results/battery50):

    platoon-opt compare paper_no_obstacles paper_obstacles ... --seeds 20 --out OUT \
        --no-figures --solvers qp-projection:backend=dual,safety=barrier \
        cone-projection:backend=dual,safety=barrier

then ``python experiments/safety_study.py results/battery50 OUT [OUT ...]`` prints, per scenario
and configuration with barriers, each task error's mean over the seeds, its ratio to the same
configuration without barriers and to the best m (the m with the least mean of that error, picked
on these seeds: the competitor's best case), each ratio of means with a 95 % paired bootstrap
interval over the seeds (and to the best m with the safety filter, where the folders hold
``iterative:max_iterations=M,safety=barrier`` runs), the seeds whose mean ran away
(``RUNAWAY``), the safety metrics (worst over the seeds; time inside, slack and fallback steps
summed over the seeds), the median allocation time per step and the median wall time of a
whole control step (problem, allocation, units; the runs' medians' median).
"""

from __future__ import annotations

import csv
import json
import re
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ERRORS = ("mean_position", "var_x", "var_y")
# A run whose integrated mean-position error exceeds this many times the best m's on the same seed
# has lost the target for a while.
RUNAWAY = 5.0
RESAMPLES = 10_000
# What the tables read from a results.csv.
METRICS = (
    *ERRORS,
    "time_inside_obstacles",
    "min_clearance",
    "min_unit_distance",
    "fallback_steps",
    "solve_time_median",
    "step_time",
)


def load(folders: list[str]) -> dict[str, dict[str, dict[int, dict]]]:
    """scenario -> configuration label -> seed -> metrics, from the runs of ``folders`` (a study's
    ``runs/`` records, or else its ``results.csv``); a later folder's runs replace an earlier's."""
    table: dict[str, dict[str, dict[int, dict]]] = defaultdict(lambda: defaultdict(dict))
    for folder in folders:
        paths = sorted(Path(folder, "runs").glob("*/base/*/seed-*.json"))
        for path in paths:
            record = json.loads(path.read_text())
            metrics = {key: _number(value) for key, value in record.get("metrics", record).items()}
            seed = int(re.search(r"seed-(\d+)", path.name).group(1))
            table[path.parts[-4]][path.parts[-2]][seed] = metrics
        if not paths and Path(folder, "results.csv").exists():
            with open(Path(folder, "results.csv"), newline="") as file:
                for row in csv.DictReader(file):
                    if row["variant"] == "base":
                        metrics = {key: float(row[key]) for key in METRICS if key in row}
                        label = row["config"].replace(":", "_")
                        table[row["scenario"]][label][int(row["seed"])] = metrics
    return table


def _number(value):
    """A record's value, with the JSON text of a non-finite one ("inf": no obstacle; "nan": a
    compiled run, which does not time its allocation apart) as a float."""
    return float(value) if value in ("inf", "-inf", "nan") else value


def ratio(values: np.ndarray, reference: np.ndarray, rng: np.random.Generator) -> tuple[float, float, float]:
    """mean(values) / mean(reference) and its 95 % paired bootstrap interval over the seeds."""
    picks = rng.integers(0, values.size, (RESAMPLES, values.size))
    resampled = values[picks].mean(axis=1) / np.maximum(reference[picks].mean(axis=1), 1e-300)
    low, high = np.percentile(resampled, [2.5, 97.5])
    return float(values.mean() / reference.mean()), float(low), float(high)


def unsafe_label(label: str) -> str | None:
    """The configuration without barriers (its label less the safety option), or None. Labels are
    folder names: the study writes ``name:options`` as ``name_options``."""
    if "safety=barrier" not in label:
        return None
    plain = re.sub(r",?safety=barrier", "", label).replace("_,", "_").rstrip("_")
    return re.sub(r"^iterative_max_iterations=(\d)$", r"m=\1", plain)


def report(table: dict[str, dict[str, dict[int, dict]]]) -> str:
    rng = np.random.default_rng(0)
    lines = []
    for scenario, configs in sorted(table.items()):
        # Scenarios with barrier runs, on the seeds every configuration with barriers has; a
        # configuration that lacks one of them (an interrupted study) is left out.
        guarded = [set(runs) for label, runs in configs.items() if unsafe_label(label)]
        if not guarded:
            continue
        seeds = sorted(set.intersection(*guarded))
        configs = {label: runs for label, runs in configs.items() if set(seeds) <= set(runs)}
        values = {
            label: {key: np.array([runs[seed][key] for seed in seeds]) for key in runs[seeds[0]]}
            for label, runs in configs.items()
        }
        best = _best(values, r"m=\d")
        # The iteration with the safety filter, where the study ran it: the competitor under the
        # same guarantee.
        guarded_best = _best(values, r"iterative_max_iterations=\d,safety=barrier")
        against = "x no barrier, x best m" + (", x best m with barriers" if guarded_best else "")
        lines += [
            f"## {scenario} ({len(seeds)} seeds)",
            "",
            "Best m per error: " + ", ".join(f"{error} {best[error]}" for error in ERRORS) + ".",
            "",
            "| configuration | "
            + " | ".join(f"{e}: mean, {against}" for e in ERRORS)
            + " | runaway seeds | inside (unit-s) | min clearance (m) | min unit distance (m) | slack steps"
            " | fallback steps | allocation ms/step | control step ms |",
            "|---" * 12 + "|",
        ]
        reference_mean = values[best["mean_position"]]["mean_position"]
        for label in sorted(values, key=lambda text: (unsafe_label(text) is None, text)):
            v = values[label]
            plain = unsafe_label(label)
            cells = []
            for error in ERRORS:
                text = f"{v[error].mean():.4f}"
                for reference in (plain, best[error], *([guarded_best[error]] if guarded_best else [])):
                    if reference is None or reference not in values:
                        text += ", -"
                        continue
                    r, low, high = ratio(v[error], values[reference][error], rng)
                    text += f", {r:.2f} [{low:.2f}, {high:.2f}]"
                cells.append(text)
            slack = int(v["slack_steps"].sum()) if "slack_steps" in v else 0
            cells += [
                str(int(np.count_nonzero(v["mean_position"] > RUNAWAY * reference_mean))),
                f"{v['time_inside_obstacles'].sum():.2f}",
                f"{v['min_clearance'].min():.3f}",
                f"{v['min_unit_distance'].min():.3f}",
                str(slack),
                str(int(v["fallback_steps"].sum())),
                _milliseconds(v["solve_time_median"]),
                _milliseconds(v.get("step_time")),
            ]
            lines.append(f"| `{label}` | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _best(values: dict[str, dict[str, np.ndarray]], pattern: str) -> dict[str, str]:
    """Per error, the label matching ``pattern`` with the least mean of it ({} if none matches)."""
    labels = [label for label in values if re.fullmatch(pattern, label)]
    if not labels:
        return {}
    return {error: min(labels, key=lambda label: values[label][error].mean()) for error in ERRORS}


def _milliseconds(seconds: np.ndarray | None) -> str:
    """The median of per-run times (s) in ms, or "-" where none was measured (compiled runs)."""
    if seconds is None or not np.isfinite(seconds).any():
        return "-"
    return f"{1e3 * np.nanmedian(seconds):.2f}"


if __name__ == "__main__":
    print(report(load(sys.argv[1:])))
