"""Lane changes in the labels: a hand-made two-lane road whose left turn leaves only from the left lane. SUMO
moves the data vehicle over (--lanechange.duration), the track shows one lane change to the left, the commands
say change_left over it and left before the junction, and the steer label steers left, then back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from helpers import fork_network, one_car_scenario

from crchfl_sumo.data.expert import expert_labels, tracks_from_frames
from crchfl_sumo.data.generation import multi_lane
from crchfl_sumo.data.labels import CHANGE_LEFT, CHANGE_RIGHT, COMMAND_NAMES, FOLLOW, LEFT
from crchfl_sumo.data.route_commands import CommandConfig, RouteCommands, track_commands, track_lane_changes
from crchfl_sumo.sumo.route import LaneChange, lane_side, read_net, route_geometry
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation
from crchfl_sumo.sumo.turns import arc_length_m, choice_junctions

MOVE_S = 3.0  # SUMO's --lanechange.duration in the data run
STEP_S = 0.25


@pytest.fixture(scope="module")
def fork(tmp_path_factory) -> Path:
    """Z -> A -> B, 300 m straight on two lanes, then B -> C left (from the left lane only) or B -> D straight on
    (from the right lane only); one car, inserted on the right lane at Z, turns left at B."""
    net = fork_network(tmp_path_factory.mktemp("fork"), approach_lanes=2)
    return one_car_scenario(net, "ZA AB BC", STEP_S, departLane="0")


@pytest.fixture(scope="module")
def drive(fork):
    """The car's track through the fork with SUMO's lane changes taking MOVE_S seconds, its lane changes and
    the arc position of each row."""
    with Simulation(load_scenario(fork), seed=0, watch={"ego"},
                    extra_options=("--lanechange.duration", f"{MOVE_S:g}")) as sim:
        frames = [f for f in sim.run(60.0) if "ego" in f.ids]
    track = tracks_from_frames(frames)["ego"]
    s = arc_length_m(np.stack([track.x_m, track.y_m], axis=1))
    net = read_net(fork.parent / "f.net.xml")
    return track, s, track_lane_changes(track, net, MOVE_S), net


def test_a_sumo_lane_change_is_found_on_the_track_with_its_side_and_its_sideways_move(drive):
    track, s, changes, net = drive
    assert len(changes) == 1
    change = changes[0]
    assert change.side == 1  # ZA_0 -> ZA_1: to the left
    # the move lasts MOVE_S, and SUMO makes it on ZA, as soon as the car is in
    t_start, t_end = np.interp([change.s_start_m, change.s_end_m], s, track.t_s)
    assert t_end - t_start == pytest.approx(MOVE_S, abs=STEP_S + 1e-6)
    lanes = track.lane_id[(s >= change.s_start_m) & (s <= change.s_end_m)]
    assert set(lanes) == {"ZA_0", "ZA_1"}
    # sideways (ZA runs along x): halfway across when SUMO switches its lane, on ZA_1's centre at the end
    lane_y = [np.asarray(net.getLane(lane).getShape())[:, 1].mean() for lane in ("ZA_0", "ZA_1")]
    y = np.interp([(change.s_start_m + change.s_end_m) / 2.0, change.s_end_m], s, track.y_m)
    assert y[0] == pytest.approx(np.mean(lane_y), abs=0.3) and y[1] == pytest.approx(lane_y[1], abs=0.3)


def test_the_commands_say_change_left_over_the_move_then_left_for_the_junction(drive, fork):
    track, s, changes, net = drive
    config = CommandConfig()
    commands = track_commands(track.x_m, track.y_m, choice_junctions(net), config, changes)
    change = changes[0]
    during = (s >= change.s_start_m - config.lane_change_lead_m) & (s < change.s_end_m)
    assert np.all(commands[during] == CHANGE_LEFT)
    assert np.all(commands[s < change.s_start_m - config.lane_change_lead_m - 0.5] == FOLLOW)
    # then follow, left from 25 m before B until through it, and follow again on BC
    after = commands[s >= change.s_end_m]
    runs = [int(code) for k, code in enumerate(after) if k == 0 or code != after[k - 1]]
    assert runs == [FOLLOW, LEFT, FOLLOW]
    assert CHANGE_RIGHT not in commands
    # without the lane change, the same track reads as before: follow, then left
    plain = track_commands(track.x_m, track.y_m, choice_junctions(net), config)
    assert set(plain[during]) <= {FOLLOW, LEFT} and np.array_equal(plain[~during], commands[~during])


def test_the_steer_label_steers_left_into_the_move_and_back_out_of_it(drive):
    """SUMO moves the car over at a constant sideways speed: a 4 degree diagonal. Pure pursuit steers into it
    (left, negative) from its look-ahead before it, holds the wheel straight along it, and steers back (right)
    where it ends; gently, as a lane change is."""
    track, s, changes, _ = drive
    change = changes[0]
    steer = expert_labels(track)[0][:, 1]
    middle = (change.s_start_m + change.s_end_m) / 2.0
    into = (s >= change.s_start_m - CommandConfig().lane_change_lead_m) & (s < middle)
    out_of = (s > middle) & (s < change.s_end_m + 5.0)
    assert steer[into].min() < -0.02 and steer[into].max() < 0.005
    assert steer[out_of].max() > 0.02 and steer[out_of].min() > -0.005
    assert np.abs(steer[into | out_of]).max() < 0.1  # a lane change, not a turn
    assert np.abs(steer[s > change.s_end_m + 5.0][:20]).max() < 0.005  # then straight on


def test_a_planned_route_issues_the_same_commands_and_the_side_is_geometric(fork):
    net = read_net(fork.parent / "f.net.xml")
    route = route_geometry(net, ["ZA", "AB", "BC"])
    assert len(route.lane_changes) == 1 and route.lane_changes[0].side == 1
    change = route.lane_changes[0]
    commands = RouteCommands(route, choice_junctions(net))
    lead = CommandConfig().lane_change_lead_m
    assert commands.at(change.s_start_m - lead - 1.0).tolist() == [FOLLOW]
    assert commands.at([change.s_start_m - lead + 0.5, change.s_start_m, change.s_end_m - 0.1]).tolist() == [
        CHANGE_LEFT] * 3
    assert commands.at(change.s_end_m + 0.5).tolist() == [LEFT]
    assert route_geometry(net, ["ZA", "AB", "BD"]).lane_changes == ()  # straight on keeps the right lane
    assert lane_side(net.getLane("AB_0"), net.getLane("AB_1")) == 1
    assert lane_side(net.getLane("AB_1"), net.getLane("AB_0")) == -1
    assert multi_lane(net)


def test_a_change_to_the_right_reads_change_right_and_an_instant_change_holds_from_its_lead():
    xy = np.stack([np.arange(0.0, 200.0, 1.0), np.zeros(200)], axis=1)
    from crchfl_sumo.data.route_commands import PathCommands

    commands = PathCommands(xy, [], CommandConfig(lane_change_lead_m=10.0), [LaneChange(100.0, 100.0, -1)])
    codes = commands.at(np.array([89.0, 90.0, 99.9, 100.0]))
    assert codes.tolist() == [FOLLOW, CHANGE_RIGHT, CHANGE_RIGHT, FOLLOW]  # an empty move: its lead only


def test_the_lane_change_commands_are_named_once():  # a 4-command network reading them: tests/learning/test_model.py
    assert COMMAND_NAMES[CHANGE_LEFT] == "change_left" and COMMAND_NAMES[CHANGE_RIGHT] == "change_right"
