"""Transfer time over piecewise-constant rates: hand-computed cases, outage policies, wireline."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.transfer import TransferConfig, transfer, wireline_transfer_time_s

MBIT = 1e6 / 8  # bytes in one megabit


def test_rate_is_integrated_not_taken_at_the_start():
    # 10 Mbit: 1 Mbit/s for 4 s carries 4 Mbit; the other 6 Mbit at 2 Mbit/s take 3 s -> 7 s
    # ("size / rate at start" would say 10 s)
    result = transfer([0.0, 4.0], [1e6, 2e6], 0.0, 10 * MBIT)
    assert result.ok and result.reason == "done"
    assert result.end_t_s == pytest.approx(7.0)
    assert result.sent_bytes == pytest.approx(10 * MBIT) and result.stalled_s == 0.0


def test_start_in_the_middle_of_a_segment():
    # from 1 s: 3 Mbit by 4 s, then 7 Mbit at 2 Mbit/s = 3.5 s -> 7.5 s
    assert transfer([0.0, 4.0], [1e6, 2e6], 1.0, 10 * MBIT).end_t_s == pytest.approx(7.5)
    # and from exactly a sample time: from 4 s, 10 Mbit at 2 Mbit/s -> 9 s
    assert transfer([0.0, 4.0], [1e6, 2e6], 4.0, 10 * MBIT).end_t_s == pytest.approx(9.0)


def test_last_sample_holds():
    # 8 Mbit/s from t = 0 onwards; 1 MB = 8 Mbit -> 1 s
    assert transfer([0.0], [8e6], 0.0, 1e6).end_t_s == pytest.approx(1.0)


def test_finish_exactly_at_a_rate_change():
    # 4 Mbit at 1 Mbit/s is done at 4.0 s, just as the rate changes
    assert transfer([0.0, 4.0], [1e6, 0.0], 0.0, 4 * MBIT).end_t_s == pytest.approx(4.0)


RATES_T = [0.0, 2.0, 5.0]
RATES = [1e6, 0.0, 1e6]  # coverage lost from 2 s to 5 s


def test_stall_waits_for_coverage():
    # 4 Mbit: 2 Mbit by 2 s, stall 3 s, the other 2 Mbit from 5 s to 7 s
    result = transfer(RATES_T, RATES, 0.0, 4 * MBIT, TransferConfig(on_outage="stall"))
    assert result.ok and result.end_t_s == pytest.approx(7.0) and result.stalled_s == pytest.approx(3.0)


def test_fail_policy_gives_up_when_coverage_is_lost():
    result = transfer(RATES_T, RATES, 0.0, 4 * MBIT, TransferConfig(on_outage="fail"))
    assert not result.ok and result.reason == "outage"
    assert result.end_t_s == pytest.approx(2.0) and result.sent_bytes == pytest.approx(2 * MBIT)
    # a transfer that ends before the outage is unaffected by the policy
    assert transfer(RATES_T, RATES, 0.0, 1 * MBIT, TransferConfig(on_outage="fail")).end_t_s == pytest.approx(1.0)


def test_stall_gives_up_after_max_outage():
    # the 3 s outage exceeds 2 s: give up at 2 + 2 = 4 s with 2 Mbit sent
    result = transfer(RATES_T, RATES, 0.0, 4 * MBIT, TransferConfig(max_outage_s=2.0))
    assert (result.ok, result.reason) == (False, "outage")
    assert result.end_t_s == pytest.approx(4.0) and result.stalled_s == pytest.approx(2.0)
    assert result.sent_bytes == pytest.approx(2 * MBIT)


def test_coverage_that_never_returns():
    result = transfer([0.0, 2.0], [1e6, 0.0], 0.0, 4 * MBIT, TransferConfig(max_outage_s=30.0))
    assert (result.ok, result.reason, result.end_t_s) == (False, "outage", pytest.approx(32.0))


def test_deadline_bounds_the_whole_transfer():
    # deadline 6 s: by then 2 Mbit + 1 Mbit (5 s to 6 s) were sent, 3 s stalled
    result = transfer(RATES_T, RATES, 0.0, 4 * MBIT, TransferConfig(deadline_s=6.0))
    assert (result.ok, result.reason) == (False, "deadline")
    assert result.end_t_s == pytest.approx(6.0) and result.sent_bytes == pytest.approx(3 * MBIT)
    assert result.stalled_s == pytest.approx(3.0)
    # deadline reached during the outage: 4 s, 2 Mbit sent, 2 s stalled
    result = transfer(RATES_T, RATES, 0.0, 4 * MBIT, TransferConfig(deadline_s=4.0))
    assert (result.reason, result.end_t_s, result.stalled_s) == ("deadline", 4.0, 2.0)


def test_start_during_an_outage():
    # starts at 1 s without coverage, coverage from 3 s at 1 Mbit/s: 1 Mbit done at 4 s
    result = transfer([0.0, 3.0], [0.0, 1e6], 1.0, 1 * MBIT)
    assert result.end_t_s == pytest.approx(4.0) and result.stalled_s == pytest.approx(2.0)
    assert transfer([0.0, 3.0], [0.0, 1e6], 1.0, 1 * MBIT, TransferConfig(on_outage="fail")).end_t_s == 1.0


def test_consecutive_zero_samples_are_one_outage():
    # outage from 2 s to 5 s reported as three zero samples; max_outage 2.5 s must see one 3 s outage
    result = transfer([0.0, 2.0, 3.0, 4.0, 5.0], [1e6, 0.0, 0.0, 0.0, 1e6], 0.0, 4 * MBIT,
                      TransferConfig(max_outage_s=2.5))  # fmt: skip
    assert (result.reason, result.end_t_s) == ("outage", pytest.approx(4.5))


def test_zero_size_finishes_at_once():
    assert transfer([0.0], [0.0], 3.0, 0).end_t_s == 3.0


def test_matches_closed_form_on_random_series():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.1, 1.0, 50))
    rate = rng.uniform(1e5, 1e7, 50)
    for size in (1e5, 1e6, 5e6):
        end = transfer(t, rate, t[0], size).end_t_s
        # bits sent by `end`, integrated sample by sample, equal the size
        span = np.clip(np.minimum(np.append(t[1:], np.inf), end) - t, 0, None)
        assert np.sum(rate * span) == pytest.approx(8 * size, rel=1e-9)


def test_wireline_time_is_latency_plus_serialisation():
    # 150 MB at 1 Gbit/s: 150e6 * 8 / 1e9 = 1.2 s, plus 10 ms latency -> 1.21 s
    assert wireline_transfer_time_s(150e6, WirelineConfig(1e9, 0.010)) == pytest.approx(1.21)


def test_bad_inputs():
    with pytest.raises(ValueError, match="precedes"):
        transfer([1.0, 2.0], [1e6, 1e6], 0.0, 10)
    with pytest.raises(ValueError, match="increasing"):
        transfer([0.0, 0.0], [1e6, 1e6], 0.0, 10)
    with pytest.raises(CrchflError, match="max_outage_s"):
        TransferConfig(max_outage_s=-1.0)
    with pytest.raises(CrchflError, match="on_outage"):
        from_mapping(TransferConfig, {"on_outage": "retry"}, "transfer")
    assert from_mapping(TransferConfig, {"deadline_s": 60}, "transfer").deadline_s == 60.0
    assert math.isinf(TransferConfig().deadline_s)
