"""A configuration against a reference (the best m), paired by seed, as a ratio of means.

The change of a nonnegative error is ``100 (mean_c / mean_r - 1)`` percent. Its 95 % interval is
the percentile interval of that ratio over paired bootstrap resamples of the seeds (the same
resampled seeds for both configurations), so it can never leave the possible range (-100 %, +inf)
as a t-interval of the differences divided by the reference's mean can. Where the reference's
mean is negligible (below ``NEGLIGIBLE`` in the metric's units: a rigid 3-unit formation whose
variance error is 1e-10 m^2 s) a ratio says nothing; the change is then the mean of the paired
differences, in the metric's units, with its t-interval. Counts (gear flips, time inside
obstacles) are compared as differences always.

The resamples come from a fixed seed, so a report is the same number for number when rerun.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from platoon_opt.study.statistics import interval

# Bootstrap resamples of the seeds.
RESAMPLES = 10_000
# A reference mean below this (in the metric's units) is compared by differences, not ratios.
NEGLIGIBLE = 1e-6
_SEED = 20_061_206


class Change(NamedTuple):
    """A paired comparison: ``kind`` "ratio" (``value``, ``low``, ``high`` in percent) or
    "difference" (in the metric's units); ``n`` seeds; ``wins`` the fraction of seeds on which the
    configuration is better (ties count one half); all nan where undefined."""

    kind: str
    value: float
    low: float
    high: float
    n: int
    wins: float


def paired_change(
    values: np.ndarray, reference: np.ndarray, *, lower_is_better: bool = True, ratio: bool = True
) -> Change:
    """``values`` (k,) against ``reference`` (k,), the same seeds in the same order: the ratio of
    means as a percent change with its paired bootstrap interval, or (``ratio`` False, or a
    negligible reference) the mean paired difference with its t-interval."""
    values, reference = np.asarray(values, dtype=float), np.asarray(reference, dtype=float)
    k = values.shape[0]
    if k == 0 or not (np.all(np.isfinite(values)) and np.all(np.isfinite(reference))):
        return Change("ratio" if ratio else "difference", math.nan, math.nan, math.nan, k, math.nan)
    better = values < reference if lower_is_better else values > reference
    wins = float((np.count_nonzero(better) + 0.5 * np.count_nonzero(values == reference)) / k)
    base = float(reference.mean())
    if not ratio or base < NEGLIGIBLE or np.any(values < 0) or np.any(reference < 0):
        difference = values - reference
        low, high = interval(difference)
        return Change("difference", float(difference.mean()), low, high, k, wins)
    value = 100 * (float(values.mean()) / base - 1)
    if k < 2:
        return Change("ratio", value, math.nan, math.nan, k, wins)
    picks = np.random.default_rng(_SEED).integers(0, k, size=(RESAMPLES, k))
    numerators, denominators = values[picks].mean(axis=1), reference[picks].mean(axis=1)
    # A resample whose reference mean is 0 has an infinite ratio: it counts as the largest.
    ratios = np.divide(numerators, denominators, out=np.full(RESAMPLES, np.inf), where=denominators > 0)
    low, high = np.percentile(ratios, [2.5, 97.5])
    return Change("ratio", value, 100 * (float(low) - 1), 100 * (float(high) - 1), k, wins)


def change_text(change: Change, unit: str) -> str:
    """``-51 % [-60, -42]`` for a ratio, ``+0.0012 m^2 s [-0.0003, +0.0027]`` for a difference."""
    if math.isnan(change.value):
        return "—"
    if change.kind == "ratio":
        if math.isnan(change.low):
            return f"{change.value:+.0f} %"
        # Whole percent, unless the interval and the change are both below 1 %: then the decimals
        # that show the larger of the two (at most 3).
        scale = max(change.high - change.low, min(abs(change.value), 1.0))
        digits = 0 if not 0 < scale < 1 else min(3, -math.floor(math.log10(scale)))
        return f"{change.value:+.{digits}f} % [{change.low:+.{digits}f}, {_upper(change.high, digits)}]"
    unit = f" {unit}" if unit else ""
    if math.isnan(change.low):
        return f"{change.value:+.3g}{unit}"
    return f"{change.value:+.3g}{unit} [{change.low:+.3g}, {change.high:+.3g}]"


def _upper(high: float, digits: int) -> str:
    return "+inf" if math.isinf(high) else f"{high:+.{digits}f}"
