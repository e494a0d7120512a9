import math

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.resources import scenarios_dir
from crchfl_sumo.data.route_commands import CommandConfig, PathCommands, RouteCommands, command_from_turn, track_commands
from crchfl_sumo.data.labels import COMMAND_NAMES, FOLLOW, LEFT, RIGHT, STRAIGHT
from crchfl_sumo.sumo.route import read_net, route_geometry
from crchfl_sumo.sumo.turns import Junction, choice_junctions

SQUARE = Junction("J", np.array([[-6.0, -6.0], [6.0, -6.0], [6.0, 6.0], [-6.0, 6.0]]))


def route_through_square(turn: str) -> np.ndarray:
    """North from (0, -60) to the square's edge at y = -6, then a quarter circle of radius 6 m or straight on."""
    approach = np.stack([np.zeros(109), np.linspace(-60.0, -6.0, 109)], axis=1)
    phi = np.linspace(0.0, math.pi / 2, 60)[1:]
    side = {"left": -1.0, "right": 1.0}.get(turn)
    if side is None:
        rest = np.stack([np.zeros(132), np.linspace(-5.5, 60.0, 132)], axis=1)
    else:
        arc = np.stack([side * (6.0 - 6.0 * np.cos(phi)), -6.0 + 6.0 * np.sin(phi)], axis=1)
        rest = np.concatenate([arc, np.stack([side * np.linspace(6.5, 60.0, 108), np.zeros(108)], axis=1)])
    return np.concatenate([approach, rest])


def test_vocabulary():
    # the four junction commands keep the codes of every data set before format 6
    assert COMMAND_NAMES == ("follow", "left", "right", "straight", "change_left", "change_right")
    assert (FOLLOW, LEFT, RIGHT, STRAIGHT) == (0, 1, 2, 3)


@pytest.mark.parametrize("turn, code", [("left", LEFT), ("right", RIGHT), ("straight", STRAIGHT)])
def test_hand_made_route_commands_left_right_straight_and_follow(turn, code):
    commands = PathCommands(route_through_square(turn), [SQUARE], CommandConfig(lookahead_m=25.0))
    # The junction's outline starts at s = 54 m: the command shows from s = 29 m (25 m before it)
    # until the path leaves the outline (s = 66 m straight on, 54 + 3 pi = 63.4 m on a turn).
    at = commands.at([0.0, 28.0, 30.0, 53.0, 58.0, 67.0, 90.0])
    assert at.tolist() == [FOLLOW, FOLLOW, code, code, code, FOLLOW, FOLLOW]


def test_no_junction_near_is_follow():
    commands = PathCommands(route_through_square("left") + [200.0, 0.0], [SQUARE])
    assert commands.at(np.arange(0.0, 120.0, 5.0)).tolist() == [FOLLOW] * 24


def test_look_ahead_is_configurable():
    commands = PathCommands(route_through_square("right"), [SQUARE], CommandConfig(lookahead_m=10.0))
    assert commands.at([40.0, 45.0]).tolist() == [FOLLOW, RIGHT]


def test_track_commands_hold_while_the_vehicle_waits():
    path = route_through_square("left")
    track = np.concatenate([path[:100], np.repeat(path[100:101], 40, axis=0), path[100:]])  # waits 4.5 m short
    commands = track_commands(track[:, 0], track[:, 1], [SQUARE])
    assert commands[0] == FOLLOW and (commands[100:140] == LEFT).all()
    assert commands[-1] == FOLLOW


def test_turn_thresholds():
    degrees = np.radians([0.0, 44.0, 46.0, 90.0, -46.0, -90.0])
    assert command_from_turn(degrees).tolist() == [STRAIGHT, STRAIGHT, LEFT, LEFT, RIGHT, RIGHT]
    with pytest.raises(CrchflError, match="command.lookahead_m"):
        from_mapping(CommandConfig, {"lookahead_m": -1.0})
    with pytest.raises(CrchflError, match="command.straight_within_deg"):
        from_mapping(CommandConfig, {"straight_within_deg": 95.0})


def test_route_commands_agree_with_sumo_link_directions_on_a_town_route():
    # town01_right_left (scenarios/drive_routes.toml): right at W1, left at E1, straight through E2.
    net = read_net(scenarios_dir() / "town01" / "town01.net.xml")
    route = route_geometry(net, ["S1_W1", "W1_E1", "E1_E2", "E2_E3"])
    commands = RouteCommands(route, choice_junctions(net))
    expected = {"r": RIGHT, "l": LEFT, "s": STRAIGHT}
    assert [c.direction for c in route.crossings] == ["r", "l", "s"]
    for crossing in route.crossings:
        # The stop line is the outline's edge; the vehicle centre is on the lane centre line.
        assert commands.at(crossing.s_start_m - 10.0)[0] == expected[crossing.direction]
        assert commands.at(0.5 * (crossing.s_start_m + crossing.s_end_m))[0] == expected[crossing.direction]
        assert commands.at(crossing.s_end_m + 2.0)[0] == FOLLOW
    assert commands.at(route.crossings[0].s_start_m - 40.0)[0] == FOLLOW
