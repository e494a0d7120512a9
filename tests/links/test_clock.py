"""The federation's clock: a link series always covers the time it is asked from; poses follow the track."""

import math

import numpy as np
import pytest

from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.clock import Relay, ScriptedClock, Segment, SumoClock, edge_download, wireless_transfer
from crchfl_sumo.links.residence import Pose
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


def test_scripted_pose_drives_straight_on_from_its_start_sample_by_sample():
    clock = ScriptedClock({"v": [Segment(0.0, 0, 8e6)]}, step_s=0.5, motion={"v": Pose(10.0, 0.0, 4.0, math.pi / 2)})
    pose = clock.pose("v", 1.7)  # the sample at 1.5 s
    assert (pose.x_m, pose.y_m, pose.speed_mps) == (pytest.approx(10.0), pytest.approx(6.0), 4.0)
    assert ScriptedClock.constant({"v": 0}, rate_bps=8e6).pose("v", 3.0) is None  # no mobility, no pose


def test_sumo_pose_moves_along_its_heading_at_its_speed():
    scenario = load_scenario("town02")
    with SumoClock(scenario, ["t02_data_0"], seed=0) as clock:
        t_s = 10.0  # on a straight road at 15 m/s (it stands at a light at 30 s)
        before, after = clock.pose("t02_data_0", t_s), clock.pose("t02_data_0", t_s + clock.step_s)
        assert after.speed_mps > 1.0  # driving
        moved = np.array([after.x_m - before.x_m, after.y_m - before.y_m])
        # SUMO moves a vehicle by its new speed over the step
        assert np.linalg.norm(moved) == pytest.approx(after.speed_mps * clock.step_s, abs=0.05)
        along = np.dot(moved, [math.cos(after.heading_rad), math.sin(after.heading_rad)])
        assert along == pytest.approx(np.linalg.norm(moved), rel=0.05)


# A vehicle served by site 0 at 1 MB/s until t = 4 s, then by site 1 at 0.5 MB/s.
CROSSING = {"v": [Segment(0.0, 0, 8e6), Segment(4.0, 1, 4e6)]}
WIRE = WirelineConfig(rate_bps=1e9, latency_s=0.01)


def test_a_download_across_a_handover_is_relayed_restarted_or_dropped():
    clock = ScriptedClock(CROSSING, step_s=0.5)
    # 10 MB from t = 1 s: 3 MB by the handover at 4 s; the other 7 MB cross the wireline
    # in 0.01 + 8 * 7e6 / 1e9 = 0.066 s and site 1 sends them in 14 s.
    out, relays = edge_download(clock, "v", 0, 1.0, 10e6, TransferConfig(), WIRE, "relay")
    assert out.ok and out.site == 1 and out.sent_bytes == pytest.approx(10e6)
    assert out.end_s == pytest.approx(4.066 + 14.0)
    assert relays == (Relay(0, 1, 4.0, pytest.approx(4.066), pytest.approx(7e6)),)
    # restart: the whole model is relayed (0.09 s) and sent again (20 s); 3 MB were sent for nothing
    out, relays = edge_download(clock, "v", 0, 1.0, 10e6, TransferConfig(), WIRE, "restart")
    assert out.ok and out.end_s == pytest.approx(4.09 + 20.0) and out.sent_bytes == pytest.approx(13e6)
    assert [r.size_bytes for r in relays] == [10e6]
    # drop: site 0 never serves the vehicle again
    out, relays = edge_download(clock, "v", 0, 1.0, 10e6, TransferConfig(on_outage="fail"), WIRE, "drop")
    assert not out.ok and out.reason == "outage" and out.end_s == pytest.approx(4.0) and relays == ()
    assert out.sent_bytes == pytest.approx(3e6)
    # a download that ends before the handover needs no relay
    out, relays = edge_download(clock, "v", 0, 1.0, 2e6, TransferConfig(), WIRE, "relay")
    assert out.ok and out.end_s == pytest.approx(3.0) and relays == ()


def test_a_relay_waits_out_a_coverage_gap_and_follows_every_handover():
    gap = ScriptedClock({"v": [Segment(0.0, 0, 8e6), Segment(4.0, -1, 0.0), Segment(6.0, 1, 8e6),
                               Segment(8.0, 0, 8e6)]}, step_s=0.5)
    out, relays = edge_download(gap, "v", 0, 1.0, 10e6, TransferConfig(), WIRE, "relay")
    # 3 MB by 4 s; stalled 4-6 s; 7 MB relayed at 6 s (0.066 s); 1.934 MB by 8 s from site 1;
    # the last 5.066 MB relayed back to site 0 (0.01 + 0.0405 s) and sent in 5.066 s
    assert [(r.from_site, r.to_site, r.start_s) for r in relays] == [(0, 1, 6.0), (1, 0, 8.0)]
    assert relays[1].size_bytes == pytest.approx(7e6 - 1.934e6)
    assert out.ok and out.end_s == pytest.approx(8.0 + 0.01 + 8 * 5.066e6 / 1e9 + 5.066)
    # under the fail policy the gap ends it, relay or not
    out, _ = edge_download(gap, "v", 0, 1.0, 10e6, TransferConfig(on_outage="fail"), WIRE, "relay")
    assert not out.ok and out.end_s == pytest.approx(4.0)
    # the deadline counts from the first byte, over all legs
    out, _ = edge_download(gap, "v", 0, 1.0, 10e6, TransferConfig(deadline_s=6.0), WIRE, "relay")
    assert not out.ok and out.reason == "deadline" and out.end_s == pytest.approx(7.0)
