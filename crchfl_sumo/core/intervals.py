"""95 % intervals, on scipy.stats: a mean over seeds (t), a success rate (Wilson), a paired difference.

Pure functions of numbers; every layer that prints a mean over seeds or episodes takes its interval
from here, so that one report and the next compute it the same way.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy import stats

CONFIDENCE = 0.95


def wilson_interval(successes: int, trials: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of a success rate (successes of trials); (0, 1) for no trial.

    Wilson rather than the normal approximation: it stays inside [0, 1] and is not empty at 0 or
    all successes, where a benchmark cell of 10 episodes often sits.
    """
    if trials == 0:
        return (0.0, 1.0)
    if not 0 <= successes <= trials:
        raise ValueError(f"wilson_interval: {successes} successes of {trials} trials")
    ci = stats.binomtest(int(successes), int(trials)).proportion_ci(confidence_level=confidence, method="wilson")
    return (float(ci.low), float(ci.high))


def t_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float, float] | None:
    """Student-t interval of the mean of ``values`` (seeds); None with fewer than two values.

    Values that are all equal give the point (mean, mean).
    """
    x = np.asarray(values, dtype=np.float64)
    if len(x) < 2:
        return None
    mean = float(x.mean())
    sem = float(stats.sem(x))
    if sem == 0.0:
        return (mean, mean)
    lo, hi = stats.t.interval(confidence, len(x) - 1, loc=mean, scale=sem)
    return (float(lo), float(hi))


def paired_difference(a: Sequence[float], b: Sequence[float], confidence: float = CONFIDENCE) -> dict:
    """Mean of b - a over pairs (the same seed, the same episode), its paired-t interval and p-value.

    Returns {"mean", "ci95": [lo, hi] or None, "p": two-sided p of "no difference" or None, "n"}.
    Pairs that all differ by the same amount give the point interval and p 0 (1 when that is 0).
    """
    x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"paired_difference: {len(x)} against {len(y)} values")
    d = y - x
    n = len(d)
    if n == 0:
        return {"mean": None, "ci95": None, "p": None, "n": 0}
    mean = float(d.mean())
    if n < 2:
        return {"mean": mean, "ci95": None, "p": None, "n": n}
    if float(np.ptp(d)) == 0.0:
        return {"mean": mean, "ci95": [mean, mean], "p": 1.0 if mean == 0.0 else 0.0, "n": n}
    test = stats.ttest_rel(y, x)
    ci = test.confidence_interval(confidence_level=confidence)
    return {"mean": mean, "ci95": [float(ci.low), float(ci.high)], "p": float(test.pvalue), "n": n}


def distinguishable(ci95: Sequence[float] | None) -> bool:
    """Whether an interval of a difference excludes 0 (False without an interval)."""
    return ci95 is not None and not (ci95[0] <= 0.0 <= ci95[1]) and not any(map(math.isnan, ci95))
