"""95 % intervals (core.intervals) against hand-computed values."""

from __future__ import annotations

import math

import pytest

from crchfl_sumo.core.intervals import distinguishable, paired_difference, t_interval, wilson_interval

Z = 1.959963984540054  # the normal quantile of 0.975


def _wilson_by_hand(k: int, n: int) -> tuple[float, float]:
    p = k / n
    centre = (p + Z * Z / (2 * n)) / (1 + Z * Z / n)
    half = Z * math.sqrt(p * (1 - p) / n + Z * Z / (4 * n * n)) / (1 + Z * Z / n)
    return centre - half, centre + half


@pytest.mark.parametrize("k", [0, 7, 10])
def test_wilson_on_0_7_and_10_of_10(k):
    lo, hi = wilson_interval(k, 10)
    assert (lo, hi) == pytest.approx(_wilson_by_hand(k, 10), abs=1e-9)
    assert 0.0 <= lo <= k / 10 <= hi <= 1.0


def test_wilson_by_the_numbers():
    # 7 of 10: centre 0.64449, half-width 0.24772
    assert wilson_interval(7, 10) == pytest.approx((0.39677, 0.89221), abs=1e-5)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.27753), abs=1e-5)
    assert wilson_interval(10, 10) == pytest.approx((0.72247, 1.0), abs=1e-5)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(11, 10)


def test_t_interval_of_three_seeds():
    # mean 2, sample sd 1, sem 1/sqrt(3); t(0.975, 2 dof) = 4.302653
    lo, hi = t_interval([1.0, 2.0, 3.0])
    half = 4.302652729911275 / math.sqrt(3)
    assert (lo, hi) == pytest.approx((2 - half, 2 + half), abs=1e-9)
    assert t_interval([5.0]) is None
    assert t_interval([0.4, 0.4]) == (0.4, 0.4)


def test_paired_difference_by_hand():
    # differences 1, 0, 0, 1: mean 0.5, sd 0.57735, sem 0.288675, t(0.975, 3) = 3.182446
    d = paired_difference([0, 1, 1, 0], [1, 1, 1, 1])
    half = 3.182446305284263 * 0.2886751345948129
    assert d["mean"] == 0.5 and d["n"] == 4
    assert d["ci95"] == pytest.approx([0.5 - half, 0.5 + half], abs=1e-9)
    # t = 0.5 / 0.288675 = 1.7321 on 3 dof: two-sided p = 0.1817
    assert d["p"] == pytest.approx(0.18169, abs=1e-4)
    assert not distinguishable(d["ci95"])
    same = paired_difference([0.2, 0.3], [0.2, 0.3])
    assert same == {"mean": 0.0, "ci95": [0.0, 0.0], "p": 1.0, "n": 2}
    shifted = paired_difference([0.2, 0.3], [0.5, 0.6])
    assert shifted["mean"] == pytest.approx(0.3) and shifted["p"] == 0.0 and distinguishable(shifted["ci95"])
    assert paired_difference([], [])["mean"] is None
    with pytest.raises(ValueError):
        paired_difference([1, 2], [1])


def test_distinguishable_needs_an_interval_that_excludes_zero():
    assert distinguishable([0.1, 0.3]) and distinguishable([-0.3, -0.1])
    assert not distinguishable([-0.1, 0.3]) and not distinguishable([0.0, 0.2]) and not distinguishable(None)
