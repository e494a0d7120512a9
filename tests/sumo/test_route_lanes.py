"""Lane-level routes: a hand-made two-lane road whose left turn leaves only from the left lane."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from helpers import fork_network

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.route import LANE_CHANGE_END_M, LANE_CHANGE_M, plan_lanes, project_points, read_net, route_geometry

WIDTH = 3.2


@pytest.fixture(scope="module")
def fork(tmp_path_factory) -> Path:
    """Z -> A (one lane), A -> B (two lanes, 200 m), then B -> C left (from the left lane only) or B -> D
    straight on (from the right lane only)."""
    return fork_network(tmp_path_factory.mktemp("fork"))


def test_a_turn_from_the_other_lane_plans_a_lane_change_finished_before_the_stop_line(fork):
    net = read_net(fork)
    plan = plan_lanes([net.getEdge(e) for e in ("ZA", "AB", "BC")])
    assert [(entry.getID(), exit_lane.getID()) for entry, exit_lane, _ in plan] == [
        ("ZA_0", "ZA_0"), ("AB_0", "AB_1"), ("BC_0", "BC_0")]  # enters AB on the right, leaves it on the left
    route = route_geometry(net, ["ZA", "AB", "BC"])
    ab = net.getEdge("AB")
    right, left = (np.asarray(ab.getLane(i).getShape()) for i in (0, 1))
    # the centre line's sideways offset from AB's right lane: 0 before the change, one lane width after it
    ab_start = float(route.crossings[0].s_end_m)  # where the route enters AB
    stop_line = float(route.crossings[1].s_start_m)  # AB's end
    length = stop_line - ab_start
    change_end, change_start = length - LANE_CHANGE_END_M, length - LANE_CHANGE_END_M - LANE_CHANGE_M
    for along, lanes_over in ((5.0, 0.0), (change_start - 1.0, 0.0), (change_end + 1.0, 1.0), (length - 1.0, 1.0)):
        x, y = route.xy_m[np.searchsorted(route.s_m, ab_start + along)]
        assert y - right[0, 1] == pytest.approx(lanes_over * WIDTH, abs=0.05), along
    # smooth: halfway through the change it is halfway across, and the heading never turns by more than 10 deg
    mid = ab_start + (change_start + change_end) / 2.0
    x, y = route.xy_m[np.searchsorted(route.s_m, mid)]
    assert y - right[0, 1] == pytest.approx(WIDTH / 2.0, abs=0.2)
    on_ab = (route.s_m[:-1] >= ab_start) & (route.s_m[1:] <= stop_line)
    heading = np.degrees(np.arctan2(*np.diff(route.xy_m, axis=0)[on_ab][:, ::-1].T))
    assert np.abs(heading).max() < 10.0
    # and it leaves AB on the left lane's end, into BC
    assert np.allclose(route.xy_m[np.searchsorted(route.s_m, stop_line)], left[-1], atol=0.05)
    assert route.crossings[1].direction == "l"
    # straight on keeps the right lane: no change at all
    straight = route_geometry(net, ["ZA", "AB", "BD"])
    s, offset, _ = project_points(straight, right[:, 0], right[:, 1])
    assert np.abs(offset).max() < 1e-6


def test_a_route_starts_on_the_lane_sumo_inserts_the_ego_on(fork):
    """SUMO inserts the ego on the first edge's rightmost lane (departLane "first"): a route starting on AB that
    turns left to C changes lanes on AB, as one entering AB from Z does; it was planned on AB's left lane all
    along, and the ego stood one lane width off its centre line (A10KW: one or two)."""
    net = read_net(fork)
    plan = plan_lanes([net.getEdge(e) for e in ("AB", "BC")])
    assert [(entry.getID(), exit_lane.getID()) for entry, exit_lane, _ in plan] == [("AB_0", "AB_1"), ("BC_0", "BC_0")]
    route = route_geometry(net, ["AB", "BC"])
    right = np.asarray(net.getEdge("AB").getLane(0).getShape())
    assert np.allclose(route.xy_m[0], right[0]) and route.lane_at(1.0) == "AB_0"
    assert route.lane_at(route.crossings[0].s_start_m - 1.0) == "AB_1"


@pytest.mark.slow
def test_the_reference_driver_starts_on_its_route(fork):
    from crchfl_sumo.driving.drive import DriveConfig, drive
    from crchfl_sumo.driving.drive_bench_tasks import without_traffic
    from crchfl_sumo.driving.policies import RoutePolicy
    from crchfl_sumo.sumo.scenario import load_scenario

    (fork.parent / "f.sumocfg").write_text('<configuration><input><net-file value="f.net.xml"/></input>'
                                           '<time><step-length value="0.25"/></time></configuration>')
    scenario = without_traffic(load_scenario(fork.parent / "f.sumocfg"))
    route = route_geometry(read_net(fork), ["AB", "BC"])
    result = drive(scenario, route, RoutePolicy(route), max_s=90.0, config=DriveConfig(warmup_s=0.0))
    assert abs(result.log.offset_m[0]) < 0.05  # was 3.2 m: inserted on AB_0, planned on AB_1
    assert result.metrics["end_reason"] == "completed" and result.metrics["lane_departures"] == 0


def test_lane_plans_need_connected_edges(fork):
    net = read_net(fork)
    with pytest.raises(CrchflError, match="edge 'BC' does not lead to 'AB'"):
        route_geometry(net, ["BC", "AB"])
    with pytest.raises(CrchflError, match="edge 'AB' has no lane 2"):
        route_geometry(net, ["AB"], lane_index=2)
    one = route_geometry(net, ["AB"], lane_index=1)  # a single edge on the lane asked for
    assert one.crossings == () and np.allclose(one.xy_m, np.asarray(net.getEdge("AB").getLane(1).getShape()))


@pytest.mark.slow
def test_the_reference_driver_changes_lane_and_turns(fork):
    from crchfl_sumo.driving.drive import DriveConfig, drive
    from crchfl_sumo.driving.drive_bench_tasks import without_traffic
    from crchfl_sumo.driving.policies import RoutePolicy
    from crchfl_sumo.sumo.scenario import load_scenario

    (fork.parent / "f.sumocfg").write_text('<configuration><input><net-file value="f.net.xml"/></input>'
                                           '<time><step-length value="0.25"/></time></configuration>')
    scenario = without_traffic(load_scenario(fork.parent / "f.sumocfg"))
    route = route_geometry(read_net(fork), ["ZA", "AB", "BC"])
    result = drive(scenario, route, RoutePolicy(route), max_s=90.0, config=DriveConfig(warmup_s=0.0))
    assert result.metrics["end_reason"] == "completed"
    assert result.metrics["max_abs_offset_m"] < 1.0 and result.metrics["lane_departures"] == 0


def test_the_route_names_the_lane_it_plans_at_every_point(fork):
    net = read_net(fork)
    route = route_geometry(net, ["ZA", "AB", "BC"])
    assert len(route.lane_ids) == len(route.s_m) - 1
    ab_start, stop_line = float(route.crossings[0].s_end_m), float(route.crossings[1].s_start_m)
    assert route.lane_at(1.0) == "ZA_0" and route.lane_at(ab_start + 5.0) == "AB_0"
    assert route.lane_at(stop_line - 1.0) == "AB_1"  # the change is done by the stop line
    assert route.lane_at((route.crossings[1].s_start_m + route.crossings[1].s_end_m) / 2).startswith(":")
    assert route.lane_at(route.length_m + 5.0) == "BC_0"


@pytest.mark.slow
def test_sumo_keeps_the_ego_on_its_planned_lanes_wherever_it_drives(fork):
    """The ego's route plans AB's right lane (straight on to D), but it drives the geometry of the left
    turn (into AB's left lane, then towards C): SUMO has it on its planned lanes all the way, never on
    AB_1 or the left turn's internal lane."""
    from crchfl_sumo.driving.drive import DriveConfig, drive
    from crchfl_sumo.driving.drive_bench_tasks import without_traffic
    from crchfl_sumo.driving.policies import RoutePolicy
    from crchfl_sumo.sumo.scenario import load_scenario

    (fork.parent / "f.sumocfg").write_text('<configuration><input><net-file value="f.net.xml"/></input>'
                                           '<time><step-length value="0.25"/></time></configuration>')
    scenario = without_traffic(load_scenario(fork.parent / "f.sumocfg"))
    net = read_net(fork)
    planned, driven = route_geometry(net, ["ZA", "AB", "BD"]), route_geometry(net, ["ZA", "AB", "BC"])
    result = drive(scenario, planned, RoutePolicy(driven), max_s=60.0, config=DriveConfig(warmup_s=0.0),
                   keep_frames=True)
    left_lane = np.asarray(net.getEdge("AB").getLane(1).getShape())
    rows = [(f, f.index_of("ego")) for f in result.frames]
    in_left = [str(f.lane_id[i]) for f, i in rows if abs(f.y_m[i] - left_lane[0, 1]) < 0.3 and left_lane[0, 0] < f.x_m[i] < left_lane[-1, 0] - 10.0]
    assert len(in_left) >= 3 and set(in_left) == {"AB_0"}  # it drove in AB's left lane; SUMO kept it on the right
    lanes = {str(f.lane_id[i]) for f, i in rows}
    assert lanes <= set(planned.lane_ids) and ":B_0_0" in lanes  # and in the junction on the straight-on lane
