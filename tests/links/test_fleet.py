"""Heterogeneous and intermittent vehicles (links/fleet.py): on-time arithmetic by hand, the dead link
while off, the seeded draws, and the trace file's refusals."""

from __future__ import annotations

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.links.clock import ScriptedClock, wireless_transfer
from crchfl_sumo.links.fleet import AvailableClock, Fleet, FleetConfig, draw_fleet, read_availability_trace
from crchfl_sumo.links.mobility import NO_SITE
from crchfl_sumo.links.transfer import TransferConfig

OFF = Fleet(off_s={"a": np.array([[2.0, 4.0], [6.0, 7.0]])})


@pytest.mark.parametrize(
    "start_s, work_s, end_s",
    [
        (0.0, 1.5, 1.5),  # done before the first off period
        (0.0, 3.0, 5.0),  # 2 s, off 2..4, 1 s
        (0.0, 5.0, 8.0),  # 2 s, off, 2 s (4..6), off 6..7, 1 s
        (3.0, 1.0, 5.0),  # starts while off: waits until 4
        (7.0, 2.0, 9.0),  # after the last period
        (0.0, 0.0, 0.0),
    ],
)
def test_work_pauses_while_the_vehicle_is_off(start_s, work_s, end_s):
    assert OFF.work_end_s("a", start_s, work_s) == pytest.approx(end_s)
    assert OFF.work_end_s("b", start_s, work_s) == pytest.approx(start_s + work_s)  # b is never off


def test_on_and_off_at_the_period_ends():
    assert [OFF.is_on("a", t) for t in (1.9, 2.0, 3.9, 4.0, 6.5, 7.0)] == [True, False, False, True, False, True]
    assert list(OFF.on_mask("a", np.array([1.9, 2.0, 3.9, 4.0, 6.5, 7.0]))) == [True, False, False, True, False, True]
    assert OFF.off_between("a", 0.0, 2.0) and OFF.off_between("a", 3.0, 3.5) and not OFF.off_between("a", 4.0, 5.9)
    assert not OFF.off_between("b", 0.0, 100.0)
    assert list(OFF.boundaries("a", 1.0, 6.5)) == [2.0, 4.0, 6.0]
    assert OFF.off_s_within("a", 0.0, 10.0) == 3.0 and OFF.off_s_within("a", 3.0, 6.5) == 1.5
    assert OFF.off_s_within("b", 0.0, 10.0) == 0.0


def test_the_link_is_dead_exactly_while_the_vehicle_is_off():
    clock = AvailableClock(ScriptedClock.constant({"a": 0, "b": 1}, 8e6), OFF)
    link = clock.series("a", "edge", 0.0, 8.0)
    assert list(link.t_s) == [0, 1, 2, 3, 4, 5, 6, 7, 8]  # the boundaries fall on samples here
    assert list(link.rate_bps) == [8e6, 8e6, 0, 0, 8e6, 8e6, 0, 8e6, 8e6]
    assert list(link.site) == [0, 0, NO_SITE, NO_SITE, 0, 0, NO_SITE, 0, 0]
    half = AvailableClock(ScriptedClock.constant({"a": 0}, 8e6), Fleet(off_s={"a": np.array([[1.5, 2.25]])}))
    link = half.series("a", "edge", 0.0, 3.0)
    assert list(link.t_s) == [0, 1, 1.5, 2, 2.25, 3]
    assert list(link.rate_bps) == [8e6, 8e6, 0, 0, 8e6, 8e6]
    assert half.start_s == 0.0 and half.step_s == 1.0  # the rest is the wrapped clock's


def test_a_transfer_stalls_or_fails_while_the_vehicle_is_off():
    clock = AvailableClock(ScriptedClock.constant({"a": 0}, 8e6), Fleet(off_s={"a": np.array([[1.5, 3.0]])}))
    size = 1_000_000  # 1 s at 8 Mbit/s
    stalled = wireless_transfer(clock, "a", "edge", 1.0, size, TransferConfig())
    assert stalled.ok and stalled.end_s == pytest.approx(3.5)  # 0.5 s, off 1.5 s, 0.5 s
    failed = wireless_transfer(clock, "a", "edge", 1.0, size, TransferConfig(on_outage="fail"))
    assert not failed.ok and failed.reason == "outage" and failed.end_s == pytest.approx(1.5)


def test_draws_are_seeded_and_have_their_documented_shape():
    vehicles = [f"v{i}" for i in range(400)]
    lognormal = draw_fleet(FleetConfig(compute_profile="lognormal", compute_sigma=0.5), vehicles, seed=3)
    factors = np.array([lognormal.factor(v) for v in vehicles])
    assert 0.9 < np.median(factors) < 1.1  # median 1
    assert np.std(np.log(factors)) == pytest.approx(0.5, abs=0.05)
    assert draw_fleet(FleetConfig(compute_profile="lognormal"), vehicles, seed=3) == lognormal
    assert draw_fleet(FleetConfig(compute_profile="lognormal"), vehicles, seed=4) != lognormal
    tiers = draw_fleet(FleetConfig(compute_profile="tiers", compute_tiers=(1.0, 3.0)), vehicles, seed=0)
    assert {tiers.factor(v) for v in vehicles} == {1.0, 3.0}
    assert draw_fleet(FleetConfig(), vehicles, seed=0) == Fleet()  # the paper's: equal and always on


def test_on_off_periods_have_the_configured_off_share():
    config = FleetConfig(availability="onoff", mean_on_s=600.0, mean_off_s=120.0)
    fleet = draw_fleet(config, ["a", "b", "c"], seed=0, start_s=100.0)
    for periods in fleet.off_s.values():
        assert np.all(periods[:, 0] < periods[:, 1]) and np.all(periods[1:, 0] > periods[:-1, 1])  # disjoint
        assert periods[0, 0] >= 100.0
    off = sum(float(np.sum(p[:, 1] - p[:, 0])) for p in fleet.off_s.values()) / (3 * 86400.0)
    assert off == pytest.approx(120 / 720, abs=0.03)  # mean_off / (mean_on + mean_off)
    again = draw_fleet(config, ["a", "b", "c"], seed=0, start_s=100.0)
    assert all(np.array_equal(again.off_s[v], fleet.off_s[v]) for v in "abc")


def test_a_trace_is_read_merged_and_refused_by_line(tmp_path):
    trace = tmp_path / "off.csv"
    trace.write_text("vehicle,off_start_s,off_end_s\na,10,20\na,15,30\nb,5,6\n\na,40,41\n")
    periods = read_availability_trace(trace, ["a", "b", "c"])
    assert periods["a"].tolist() == [[10, 30], [40, 41]] and periods["b"].tolist() == [[5, 6]] and "c" not in periods
    bad = {
        "vehicle,start,end\na,1,2\n": "first line must be the header",
        "vehicle,off_start_s,off_end_s\nz,1,2\n": "line 2: vehicle 'z' is not federated",
        "vehicle,off_start_s,off_end_s\na,nan,2\n": "line 2: need finite times",
        "vehicle,off_start_s,off_end_s\na,3,2\n": "line 2: need finite times",
        "vehicle,off_start_s,off_end_s\na,1,2\na,x,2\n": "line 3: off_start_s and off_end_s must be numbers",
        "vehicle,off_start_s,off_end_s\na,1\n": "line 2: expected 3 values",
    }
    for text, match in bad.items():
        trace.write_text(text)
        with pytest.raises(CrchflError, match=match):
            read_availability_trace(trace, ["a", "b"])
    with pytest.raises(CrchflError, match="cannot read .*missing.csv"):
        read_availability_trace(tmp_path / "missing.csv", ["a"])


@pytest.mark.parametrize(
    "clock, match",
    [
        ({"compute_profile": "fast"}, "clock.compute_profile: 'fast' is not one of"),
        ({"compute_sigma": -1.0}, "clock.compute_sigma"),
        ({"compute_tiers": []}, "clock.compute_tiers: give at least one"),
        ({"compute_tiers": [1.0, 0.0]}, r"clock.compute_tiers\[1\]"),
        ({"availability": "sometimes"}, "clock.availability: 'sometimes' is not one of"),
        ({"mean_off_s": 0.0}, "clock.mean_off_s"),
        ({"availability": "trace"}, "clock.availability_trace: give the CSV file exactly when"),
        ({"availability_trace": "off.csv"}, "clock.availability_trace: give the CSV file exactly when"),
    ],
)
def test_bad_device_settings_are_refused_naming_the_key(clock, match):
    with pytest.raises(CrchflError, match=match):
        from_mapping(RunConfig, {"clock": clock}, "run.toml")
