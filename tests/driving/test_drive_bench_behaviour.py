"""Leaderboard 2.0 and Bench2Drive figures of one drive (driving.drive_bench_behaviour), by hand."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from crchfl_sumo.driving.drive_bench_behaviour import (
    abilities,
    comfort_signals,
    min_speed_penalty,
    smoothness,
    traffic_speed_ratios,
)
from crchfl_sumo.sumo.route import Crossing, LaneChange

STEP_S = 0.25


def test_the_minimum_speed_penalty_by_hand():
    # one checkpoint at half the traffic's speed: 1 - 0.3 * 0.5; at or above the traffic's: no factor
    assert min_speed_penalty([50.0, 100.0, 120.0]) == pytest.approx(0.85)
    assert min_speed_penalty([0.0, 0.0]) == pytest.approx(0.49)
    assert min_speed_penalty([]) == 1.0


def test_speed_ratios_per_checkpoint_reached():
    progress = np.linspace(0.0, 100.0, 101)
    speed = np.where(progress < 50.0, 5.0, 10.0)
    log = SimpleNamespace(progress_m=progress, speed_mps=speed, traffic_speed_mps=np.full(101, 10.0))
    assert traffic_speed_ratios(log, 0.0, 100.0, 4) == pytest.approx([50.0, 50.0, 100.0, 100.0])
    # stopped at 60 m: two checkpoints passed; no traffic in the first stretch: it gives none
    stopped = SimpleNamespace(progress_m=progress[:61], speed_mps=speed[:61],
                              traffic_speed_mps=np.where(progress[:61] < 25.0, np.nan, 10.0))
    assert traffic_speed_ratios(stopped, 0.0, 100.0, 4) == pytest.approx([50.0])
    # past 95 % of the route the last checkpoint counts too
    almost = SimpleNamespace(progress_m=progress[:97], speed_mps=speed[:97], traffic_speed_mps=np.full(97, 10.0))
    assert len(traffic_speed_ratios(almost, 0.0, 100.0, 4)) == 4
    # traffic that stands (0.01 m/s) gives no ratio in its stretch; traffic at 0.5 m/s does
    queue = SimpleNamespace(progress_m=progress, speed_mps=speed,
                            traffic_speed_mps=np.where(progress < 25.0, 0.01, np.where(progress < 50.0, 0.5, 10.0)))
    assert traffic_speed_ratios(queue, 0.0, 100.0, 4) == pytest.approx([1000.0, 100.0, 100.0])


def test_comfort_signals_of_polynomial_motions_are_exact():
    t = np.arange(32) * STEP_S
    # braking at 6 m/s^2 on a straight: the filter fits the ramp exactly
    ramp = comfort_signals(20.0 - 6.0 * t, np.zeros(32), STEP_S)
    assert ramp["lon_accel_mps2"] == pytest.approx(np.full(32, -6.0))
    assert ramp["lon_jerk_mps3"] == pytest.approx(np.zeros(32), abs=1e-9)
    # turning at 0.5 rad/s at 5 m/s: lateral acceleration 2.5 m/s^2, no yaw acceleration
    turn = comfort_signals(np.full(32, 5.0), 0.5 * t, STEP_S)
    assert turn["yaw_rate_radps"] == pytest.approx(np.full(32, 0.5))
    assert turn["lat_accel_mps2"] == pytest.approx(np.full(32, 2.5))
    assert turn["yaw_accel_radps2"] == pytest.approx(np.zeros(32), abs=1e-9)


def test_smoothness_is_the_share_of_comfortable_two_second_windows():
    t = np.arange(32) * STEP_S  # four windows of 8 steps
    assert smoothness(np.full(32, 5.0), 0.5 * t, STEP_S) == 1.0
    assert smoothness(np.full(32, 5.0), 1.2 * t, STEP_S) == 0.0  # yaw rate over 0.95 rad/s throughout
    assert smoothness(20.0 - 6.0 * t, np.zeros(32), STEP_S) == 0.0  # braking harder than 4.05 m/s^2
    # the heading wraps at pi: unwrapped, it is the same smooth turn
    wrapped = np.arctan2(np.sin(3.0 + 0.5 * t), np.cos(3.0 + 0.5 * t))
    assert smoothness(np.full(32, 5.0), wrapped, STEP_S) == 1.0
    assert smoothness(np.full(4, 5.0), np.zeros(4), STEP_S) is None  # shorter than the filter


def _approach(letters, speeds, red_at=None, colliding_at=None, gap=math.inf):
    """A drive through one right-turn junction (stop line at 50 m, leaves it at 60 m), 1 m a step
    until the line, as scripted: ``letters`` and ``speeds`` per step while approaching."""
    n = len(letters)
    progress = np.concatenate([np.linspace(20.0, 49.0, n), [55.0, 65.0]])
    log = SimpleNamespace(
        progress_m=progress,
        crossing_ahead=np.array([0] * n + [-1, -1]),
        signal_dist_m=np.concatenate([50.0 - np.linspace(20.0, 49.0, n), [math.inf, math.inf]]),
        signal_letter=np.array(list(letters) + ["", ""]),
        speed_mps=np.concatenate([speeds, [5.0, 5.0]]),
        red_light=np.zeros(n + 2, bool),
        colliding=np.zeros(n + 2, bool),
        leader_gap_m=np.full(n + 2, gap),
    )
    if red_at is not None:
        log.red_light[red_at] = True
    if colliding_at is not None:
        log.colliding[colliding_at] = True
    return log


CROSSINGS = [Crossing(50.0, 60.0, "tls", 0, "r")]


def test_abilities_of_a_stop_at_red_then_a_turn_on_green():
    log = _approach("rrrrrrrrGGGG", [5, 3, 1, 0, 0, 0, 0, 0, 0.2, 2, 4, 5])
    tally = abilities(log, CROSSINGS, STEP_S)
    assert tally["turn_at_junction"] == [1, 1] and tally["stop_at_red"] == [1, 1]
    # standing at the green for one step (0.25 s) only: it went
    assert tally["go_at_green"] == [1, 1]
    assert tally["yield_on_minor_green"] == [0, 0] and tally["follow_a_leader"] == [0, 0]


def test_abilities_failed_running_the_red_hesitating_and_colliding():
    ran = abilities(_approach("rrrr", [5, 5, 5, 5], red_at=4), CROSSINGS, STEP_S)
    assert ran["stop_at_red"] == [1, 0]
    # 9 steps standing at a free green: 2.25 s, beyond the 2 s allowed (7 steps, 1.75 s, would pass)
    hesitated = abilities(_approach("GGGGGGGGGGGG", [5, 1] + [0] * 9 + [3]), CROSSINGS, STEP_S)
    assert hesitated["go_at_green"] == [1, 0] and hesitated["stop_at_red"] == [0, 0]
    # a leader 10 m ahead all along: the green is not free, and the drive is a follow attempt
    queued = abilities(_approach("GGGGGGGGGGGGGGGGGGGGGG", [0.0] * 22, gap=10.0), CROSSINGS, STEP_S)
    assert queued["go_at_green"] == [0, 0] and queued["follow_a_leader"] == [1, 1]
    crashed = abilities(_approach("gggg", [5, 5, 5, 5], colliding_at=5), CROSSINGS, STEP_S)
    assert crashed["yield_on_minor_green"] == [1, 0] and crashed["turn_at_junction"] == [1, 0]


def _lane_change_drive(offset_at_end: float, colliding_at=None, stop_at=None):
    """A straight drive 0 .. 100 m, 1 m a step, through a planned lane change moving from 40 to 70 m; the ego's
    offset from the route's centre line (the new lane's, after the move) is ``offset_at_end`` from 70 m on."""
    progress = np.arange(0.0, 101.0) if stop_at is None else np.arange(0.0, stop_at + 1.0)
    n = len(progress)
    log = SimpleNamespace(
        progress_m=progress, crossing_ahead=np.full(n, -1), signal_dist_m=np.full(n, math.inf),
        signal_letter=np.full(n, ""), speed_mps=np.full(n, 8.0), red_light=np.zeros(n, bool),
        colliding=np.zeros(n, bool), leader_gap_m=np.full(n, math.inf),
        offset_m=np.where(progress >= 70.0, offset_at_end, 0.0), lane_width_m=np.full(n, 3.2),
    )
    if colliding_at is not None:
        log.colliding[colliding_at] = True
    return log


def test_change_lane_counts_a_planned_change_reached_and_succeeds_on_the_planned_lane():
    change = [LaneChange(40.0, 70.0, 1)]
    assert abilities(_lane_change_drive(0.3), [], STEP_S, change)["change_lane"] == [1, 1]
    # 5 m past the move it is still 1.7 m off the planned lane's centre, past the half width of 1.6 m: failed
    assert abilities(_lane_change_drive(-1.7), [], STEP_S, change)["change_lane"] == [1, 0]
    assert abilities(_lane_change_drive(1.5), [], STEP_S, change)["change_lane"] == [1, 1]
    assert abilities(_lane_change_drive(0.0, colliding_at=60), [], STEP_S, change)["change_lane"] == [1, 0]
    # a collision before the move began does not count against it
    assert abilities(_lane_change_drive(0.0, colliding_at=30), [], STEP_S, change)["change_lane"] == [1, 1]
    # the drive ended during the move: attempted, not done; before it: not attempted
    assert abilities(_lane_change_drive(0.0, stop_at=60), [], STEP_S, change)["change_lane"] == [1, 0]
    assert abilities(_lane_change_drive(0.0, stop_at=35), [], STEP_S, change)["change_lane"] == [0, 0]
    assert abilities(_lane_change_drive(0.0), [], STEP_S)["change_lane"] == [0, 0]  # none planned
