import math

import numpy as np
import pytest

from crchfl_sumo.core.resources import scenarios_dir
from crchfl_sumo.sumo.route import read_net
from crchfl_sumo.sumo.turns import Junction, arc_length_m, choice_junctions, junction_passages, next_passage

# A hand-made junction: the square |x|, |y| <= 6 m around the origin.
SQUARE = Junction("J", np.array([[-6.0, -6.0], [6.0, -6.0], [6.0, 6.0], [-6.0, 6.0]]))


def approach_then(turn: str) -> np.ndarray:
    """North along x = 0 from y = -60 to the junction's edge (y = -6), then left, right or straight.

    The turns are quarter circles of radius 6 m that leave the square at x = -6 (west) or x = 6 (east).
    """
    approach = np.stack([np.zeros(109), np.linspace(-60.0, -6.0, 109)], axis=1)
    phi = np.linspace(0.0, math.pi / 2, 60)[1:]
    if turn == "straight":
        rest = np.stack([np.zeros(132), np.linspace(-5.5, 60.0, 132)], axis=1)
    elif turn == "left":  # centre (-6, -6)
        arc = np.stack([-6.0 + 6.0 * np.cos(phi), -6.0 + 6.0 * np.sin(phi)], axis=1)
        rest = np.concatenate([arc, np.stack([np.linspace(-6.5, -60.0, 108), np.zeros(108)], axis=1)])
    else:  # right, centre (6, -6)
        arc = np.stack([6.0 - 6.0 * np.cos(phi), -6.0 + 6.0 * np.sin(phi)], axis=1)
        rest = np.concatenate([arc, np.stack([np.linspace(6.5, 60.0, 108), np.zeros(108)], axis=1)])
    return np.concatenate([approach, rest])


@pytest.mark.parametrize("turn, degrees, length_m", [("left", 90, 3 * math.pi), ("right", -90, 3 * math.pi),
                                                     ("straight", 0, 12.0)])
def test_one_pass_through_the_junction_with_its_turn(turn, degrees, length_m):
    (passage,) = junction_passages(approach_then(turn), [SQUARE])
    assert passage.junction == "J"
    assert passage.s_in_m == pytest.approx(54.0, abs=0.5)  # 60 - 6 m of approach
    assert passage.s_out_m - passage.s_in_m == pytest.approx(length_m, abs=0.6)
    assert math.degrees(passage.turn_rad) == pytest.approx(degrees, abs=3.0)


def test_next_passage_within_the_look_ahead_until_the_vehicle_leaves():
    passages = junction_passages(approach_then("left"), [SQUARE])
    # Entry at s = 54 m, exit at s = 54 + 3 pi = 63.4 m; look-ahead 25 m.
    index = next_passage(passages, [0.0, 28.0, 30.0, 54.0, 60.0, 64.5, 100.0], 25.0)
    assert index.tolist() == [-1, -1, 0, 0, 0, -1, -1]
    assert next_passage((), [1.0], 25.0).tolist() == [-1]


def test_a_path_that_stands_still_or_misses_the_junction():
    path = approach_then("right")
    waiting = np.concatenate([path[:100], np.repeat(path[100:101], 50, axis=0), path[100:]])
    (passage,) = junction_passages(waiting, [SQUARE])
    assert passage.s_in_m == pytest.approx(54.0, abs=0.5)  # standing adds no path
    far = path + np.array([100.0, 0.0])
    assert junction_passages(far, [SQUARE]) == ()
    assert junction_passages(path[:1], [SQUARE]) == ()


def test_arc_length():
    assert arc_length_m(np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 4.0], [3.0, 5.0]])).tolist() == [0.0, 5.0, 5.0, 6.0]


def test_town_junctions_with_a_choice_are_the_t_junctions_not_the_corners():
    town01 = choice_junctions(read_net(scenarios_dir() / "town01" / "town01.net.xml"))
    assert [j.id for j in town01] == ["E1", "E2", "E3", "M3", "N1", "N2", "N3", "S1", "S2", "W1", "W2", "W3"]
    assert all(len(j.shape_m) >= 3 for j in town01)
    town02 = choice_junctions(read_net(scenarios_dir() / "town02" / "town02.net.xml"))
    assert len(town02) == 8  # Town02's T-junctions; its four corners are lane following
