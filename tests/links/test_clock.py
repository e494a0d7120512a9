"""The federation's clock: a link series always covers the time it is asked from."""

import pytest

from crchfl_sumo.links.clock import ScriptedClock, SumoClock, wireless_transfer
from crchfl_sumo.links.transfer import TransferConfig
from crchfl_sumo.sumo.scenario import load_scenario

# Two epochs of 2928 samples at 120 s per 2928 samples, from t = 0.25 s, end at
# 240.24999999999997 s in floating point: one rounding short of the 240.25 s sample.
START_S = 0.25 + 2 * 2928 * (120 / 2928)


def test_rounding_case_is_what_a_real_run_produces():
    assert START_S < 240.25 and START_S == pytest.approx(240.25, abs=1e-9)


def test_scripted_series_starts_at_or_before_the_start_and_transfer_runs():
    clock = ScriptedClock.constant({"v": 0}, rate_bps=8e6, step_s=0.25)
    link = clock.series("v", "edge", START_S, START_S + 10.0)
    assert link.t_s[0] <= START_S
    outcome = wireless_transfer(clock, "v", "edge", START_S, 1e6, TransferConfig())
    assert outcome.ok and outcome.end_s == pytest.approx(START_S + 1.0)  # 8 Mbit at 8 Mbit/s


def test_sumo_series_starts_at_or_before_the_start():
    scenario = load_scenario("town02")
    with SumoClock(scenario, ["t02_data_0"], seed=0) as clock:
        link = clock.series("t02_data_0", "edge", START_S, START_S + 5.0)
        assert link.t_s[0] <= START_S < link.t_s[1]
        outcome = wireless_transfer(clock, "t02_data_0", "edge", START_S, 1e5, TransferConfig())
        assert outcome.end_s > START_S
