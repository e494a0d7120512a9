"""Closed-loop driving: bicycle model and metrics by hand, then drives on tiny networks built here."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.route_commands import RouteCommands
from crchfl_sumo.data.expert import ExpertConfig, pedals, steer_from_curvature
from crchfl_sumo.data.labels import LEFT, RIGHT, STEER_CLASS_VALUES, digitize_steer, steer_bin_values
from crchfl_sumo.driving.drive import (
    DriveConfig,
    count_onsets,
    drive,
    lane_departed,
    red_light_violations,
)
from crchfl_sumo.driving.dagger import ExpertLabelled
from crchfl_sumo.driving.dagger_settings import DaggerConfig
from crchfl_sumo.driving.route_drive import drive_route
from crchfl_sumo.driving.dynamics import (
    VehicleState,
    acceleration_from_pedals,
    bicycle_step,
    curvature_from_steer,
)
from crchfl_sumo.driving.named_routes import load_drive_routes, resolve_route
from crchfl_sumo.driving.plots import action_panel, compare_runs, pick_moments, read_trajectory_csv, turn_moment
from crchfl_sumo.driving.policies import (
    ConstantPolicy,
    ModelPolicy,
    RoutePolicy,
    RoutePolicyConfig,
)
from crchfl_sumo.learning.checkpoint import save_checkpoint
from crchfl_sumo.learning.model import build_model
from crchfl_sumo.learning.settings import ModelConfig
from crchfl_sumo.sumo.route import (
    Crossing,
    RouteGeometry,
    next_crossing,
    on_road,
    point_at,
    project_points,
    read_net,
    road_area,
    route_geometry,
    signal_letter,
)
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.turns import choice_junctions
from crchfl_sumo.vision.raster import Renderer
from crchfl_sumo.vision.world import build_world

from helpers import netconvert

EXPERT = ExpertConfig()
NO_WARMUP = DriveConfig(warmup_s=0.0)


# --- pure parts ---------------------------------------------------------------------------------


def test_bicycle_straight_line_and_stopping_within_a_step():
    state = bicycle_step(VehicleState(1.0, 2.0, math.pi / 2, 10.0), 0.0, 0.0, 0.5)
    assert state.x_m == pytest.approx(1.0) and state.y_m == pytest.approx(7.0)
    assert state.heading_rad == pytest.approx(math.pi / 2) and state.speed_mps == 10.0
    # Speed 1 m/s, braking at 4 m/s^2: stands after 0.25 s, having rolled 1 / 8 m, never backwards.
    stopped = bicycle_step(VehicleState(0.0, 0.0, 0.0, 1.0), -4.0, 0.0, 1.0)
    assert stopped.speed_mps == 0.0 and stopped.x_m == pytest.approx(0.125)
    assert bicycle_step(stopped, -4.0, 0.0, 1.0).x_m == pytest.approx(0.125)
    # Constant acceleration: distance (v0 + v1) / 2 * dt exactly.
    assert bicycle_step(VehicleState(0.0, 0.0, 0.0, 2.0), 1.0, 0.0, 2.0).x_m == pytest.approx(6.0)


@pytest.mark.parametrize("steer", [0.425, -0.275, 0.125])
def test_bicycle_constant_steer_drives_a_circle_of_radius_wheelbase_over_tan_delta(steer):
    delta = -steer * math.radians(EXPERT.max_steer_angle_deg)
    radius = EXPERT.wheelbase_m / math.tan(abs(delta))
    kappa = math.tan(delta) / EXPERT.wheelbase_m
    state = VehicleState(3.0, -1.0, 0.3, 5.0)
    centre = np.array([3.0 - math.sin(0.3) / kappa, -1.0 + math.cos(0.3) / kappa])
    headings = []
    for _ in range(80):
        state = bicycle_step(state, 0.0, steer, 0.1)
        assert math.hypot(state.x_m - centre[0], state.y_m - centre[1]) == pytest.approx(radius, rel=1e-9)
        headings.append(state.heading_rad)
    # Positive steer turns right: the CCW heading falls; negative turns left.
    step = np.angle(np.exp(1j * np.diff(np.unwrap(headings))))
    assert np.all(np.sign(step) == -np.sign(steer))
    assert abs(step[0]) == pytest.approx(5.0 * 0.1 / radius)


def test_steer_and_pedal_mappings_invert_the_expert():
    for steer in STEER_CLASS_VALUES:
        back = steer_from_curvature(curvature_from_steer(float(steer)), EXPERT)
        assert back == pytest.approx(float(steer), abs=1e-12)
    speeds = np.array([0.5, 3.0, 8.0, 13.0, 13.0])
    accels = np.array([1.0, 0.0, -2.0, 0.3, -4.0])
    throttle, brake = pedals(speeds, accels, np.full(5, 2.6), np.full(5, 4.5), EXPERT)
    for v, a, t, b in zip(speeds, accels, throttle, brake):
        assert acceleration_from_pedals(t, b, v, 2.6, 4.5, EXPERT) == pytest.approx(a, abs=1e-12)
    # Standing with the held brake: the car stays put (speed is clipped at 0 by the bicycle model).
    assert acceleration_from_pedals(0.0, EXPERT.hold_brake, 0.0, 2.6, 4.5) == pytest.approx(-0.9 * 4.5)


def _route(points, crossings=()) -> RouteGeometry:
    xy = np.asarray(points, dtype=np.float64)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    n = len(xy) - 1
    return RouteGeometry(("e",), xy, s, np.full(n, 4.0), np.zeros(n, bool), tuple(crossings))


def test_projection_on_a_polyline_by_hand():
    route = _route([(0, 0), (10, 0), (10, 10)])
    s, offset, width = project_points(route, [5.0, 11.0, 9.0, -2.0], [1.0, 5.0, 3.0, 0.0])
    assert s.tolist() == pytest.approx([5.0, 15.0, 13.0, 0.0])
    # Left of the direction of travel is positive: (11, 5) is right of the northbound leg.
    assert offset.tolist() == pytest.approx([1.0, -1.0, 1.0, 2.0])
    assert width.tolist() == [4.0] * 4
    assert point_at(route, 12.0) == pytest.approx((10.0, 2.0, math.pi / 2))
    assert point_at(route, 25.0) == pytest.approx((10.0, 15.0, math.pi / 2))  # straight on past the end


def test_projection_window_keeps_a_route_that_passes_twice_on_its_own_pass():
    # Out along y = 0, back along y = 3 (a U): (5, 1.5) is as near to both passes.
    route = _route([(0, 0), (10, 0), (10, 3), (0, 3)])
    s_out, off_out, _ = project_points(route, 5.0, 1.4, 0.0, 10.0)
    s_back, off_back, _ = project_points(route, 5.0, 1.6, 13.0, 23.0)
    assert s_out[0] == pytest.approx(5.0) and off_out[0] == pytest.approx(1.4)
    assert s_back[0] == pytest.approx(18.0) and off_back[0] == pytest.approx(1.4)


def test_departure_onsets_and_red_light_rules_by_hand():
    assert lane_departed([0.0, 1.0, -1.2, 1.3], [4.0] * 4, 1.8).tolist() == [False, False, True, True]
    assert count_onsets([False, True, True, False, True]) == 2
    assert count_onsets([True, False, False]) == 1 and count_onsets([]) == 0
    crossings = (Crossing(50.0, 60.0, "J", 1, "s"), Crossing(80.0, 90.0, "", -1, "l"))
    assert signal_letter(crossings[0], {"J": "GrG"}) == "r"
    assert signal_letter(crossings[1], {"J": "GrG"}) == ""
    assert [c.s_start_m for c in red_light_violations(crossings, 49.0, 51.0, {"J": "GrG"})] == [50.0]
    assert red_light_violations(crossings, 49.0, 51.0, {"J": "GuG"})  # red-yellow is still red
    assert not red_light_violations(crossings, 49.0, 51.0, {"J": "GyG"})  # yellow is not
    assert not red_light_violations(crossings, 50.5, 52.0, {"J": "GrG"})  # already past the line
    assert not red_light_violations(crossings, 79.0, 81.0, {"J": "rrr"})  # no signal at that junction
    assert next_crossing(crossings, 49.0) == 0 and next_crossing(crossings, 55.0) == 1
    assert next_crossing(crossings, 85.0) == -1


def test_pick_moments_finds_red_then_green_at_the_same_line():
    from crchfl_sumo.driving.drive import DriveLog

    n = 6
    letters = np.array(["G", "r", "r", "G", "G", ""])
    log = DriveLog(
        t_s=np.arange(n) * 0.5, x_m=np.zeros(n), y_m=np.zeros(n), heading_rad=np.zeros(n), speed_mps=np.zeros(n),
        throttle=np.array([0.5, 0, 0, 0.6, 0.6, np.nan]), steer=np.zeros(n), brake=np.zeros(n),
        progress_m=np.array([0.0, 10, 20, 20, 25, 40]), offset_m=np.zeros(n), lane_width_m=np.full(n, 4.0),
        on_road=np.ones(n, bool), colliding=np.zeros(n, bool), red_light=np.zeros(n, bool),
        signal_letter=letters, signal_dist_m=np.array([40.0, 15, 5, 5, 1, np.inf]),
        crossing_ahead=np.array([0, 0, 0, 0, 0, -1]), traffic_speed_mps=np.full(n, np.nan),
        leader_gap_m=np.full(n, np.inf),
    )
    assert pick_moments(log) == {"red_light": 1, "green_light": 3}
    waiting = dataclasses.replace(log, brake=np.array([0.0, 0.9, 0.9, 0.9, 0.0, np.nan]))
    assert pick_moments(waiting)["green_light"] == 4  # the first green step with more throttle than brake
    route = _route([(0, 0), (40, 0)], [Crossing(18.0, 28.0, "J", 0, "l")])
    assert turn_moment(log, route) == 4  # rows 3 and 4 (progress 20, 25) are in the turn; 25 is nearer its middle, 23
    assert action_panel(400, (0.5, -0.275, 0.0), "left").shape == (64, 400, 3)


# --- routes ---------------------------------------------------------------------------------------


def test_named_routes_resolve_in_both_towns_with_turns_and_signals():
    routes = load_drive_routes()
    assert {r.scenario for r in routes.values()} == {"town01", "town02"}
    for name, entry in routes.items():
        scenario = load_scenario(entry.scenario)
        geometry = route_geometry(read_net(Path(scenario.net_path)), entry.edges)
        signalised = [c for c in geometry.crossings if c.tls_id]
        assert signalised, name
        assert {c.direction for c in signalised} & {"l", "r"}, name
        # The centre line is continuous: no gap between consecutive vertices beyond a lane's curve step.
        assert np.all(np.diff(geometry.s_m) > 0)
        assert np.max(np.diff(geometry.s_m)) < 300.0
        assert all(c.s_start_m <= c.s_end_m for c in geometry.crossings)
    assert resolve_route("town01_west_loop", None)[0] == "town01"
    assert resolve_route("AB, BC", "x.sumocfg") == ("x.sumocfg", ("AB", "BC"))
    with pytest.raises(CrchflError, match="runs in scenario"):
        resolve_route("town01_west_loop", "town02")
    with pytest.raises(CrchflError, match="not a named route"):
        resolve_route("nowhere", None)


# key: (values just outside its range, values at or just inside its ends); hand-written from the reasons in drive.py
DRIVE_RANGES = {
    "warmup_s": ((-0.01, 3600.01), (0, 3600)),
    "insert_timeout_s": ((0, 3600.01), (0.01, 3600)),
    "finish_before_end_m": ((-0.01, 100.01), (0, 100)),
    "lost_offset_m": ((0, 100.01), (0.01, 100)),
    "off_road_margin_m": ((-0.01, 10.01), (0, 10)),
    "stuck_s": ((0, 3600.01, -math.inf), (0.01, 3600, math.inf)),  # inf: a drive never ends stuck
}


def test_every_numeric_drive_setting_has_a_finite_range():
    numeric = {f.name for f in dataclasses.fields(DriveConfig) if f.type in ("float", "int", float, int)}
    assert set(DRIVE_RANGES) == numeric
    for key, (refused, accepted) in DRIVE_RANGES.items():
        for value in (*refused, 1e308, -1e308, 2**63 - 1, math.nan):
            with pytest.raises(CrchflError, match=rf"^drive\.{key}: .+; give .+ in [\[(]"):
                DriveConfig(**{key: value})
        for value in accepted:
            assert getattr(DriveConfig(**{key: value}), key) == value
    with pytest.raises(CrchflError, match=r"^drive\.warmup_s: inf is not a finite number; give simulated seconds in \[0, 3600\]$"):
        DriveConfig(warmup_s=math.inf)  # only stuck_s's inf means "no limit"


def test_settings_and_route_files_are_checked(tmp_path):
    with pytest.raises(CrchflError, match="drive.warmup_s"):
        DriveConfig(warmup_s=-1.0)
    with pytest.raises(CrchflError, match="drive.lost_offset_m"):
        DriveConfig(lost_offset_m=0.0)
    with pytest.raises(CrchflError, match="route_policy.target_speed_mps"):
        RoutePolicyConfig(target_speed_mps=0.0)
    routes = tmp_path / "routes.toml"
    routes.write_text('[routes.a]\nscenario = "town01"\nedges = ["S1_W1"]\nlanes = 2\n')
    with pytest.raises(CrchflError, match="unknown key"):
        load_drive_routes(routes)
    routes.write_text('[routes.a]\nscenario = "town01"\nedges = ["S1_W1", "W1_E1"]\n')
    assert load_drive_routes(routes)["a"].edges == ("S1_W1", "W1_E1")


def test_route_geometry_through_a_grid_junction(grid_dir):
    net = read_net(Path(grid_dir / "grid.net.xml"))
    geometry = route_geometry(net, ["A0B0", "B0B1"])  # east along y = 0, left at B0, north
    (crossing,) = geometry.crossings
    assert crossing.tls_id == "B0" and crossing.direction == "l"
    first_lane = net.getEdge("A0B0").getLanes()[0]
    assert crossing.s_start_m == pytest.approx(first_lane.getLength(), abs=0.05)
    assert geometry.in_junction.any()
    start, end = geometry.xy_m[0], geometry.xy_m[-1]
    assert start[1] < 0 and end[0] > 200  # right-hand traffic: south of the eastbound axis, east of the northbound
    with pytest.raises(CrchflError, match="does not lead to"):
        route_geometry(net, ["A0B0", "A1B1"])
    with pytest.raises(CrchflError, match="not in the network"):
        route_geometry(net, ["nope"])


# --- drives on tiny networks -----------------------------------------------------------------------


CFG = """<configuration>
  <input><net-file value="{net}"/>{routes}</input>
  <time><step-length value="0.25"/></time>
</configuration>
"""


@pytest.fixture(scope="module")
def roads(tmp_path_factory) -> Path:
    """A 300 m straight road (one 3.5 m lane a direction) behind a 100 m approach; a road with an always-red light."""
    folder = tmp_path_factory.mktemp("roads")
    (folder / "s.nod.xml").write_text(
        '<nodes><node id="X" x="-100" y="0"/><node id="A" x="0" y="0"/><node id="C" x="300" y="0"/></nodes>'
    )
    (folder / "s.edg.xml").write_text(
        "<edges>"
        + "".join(
            f'<edge id="{a}{b}" from="{a}" to="{b}" numLanes="1" speed="13.89" width="3.5"/>'
            for a, b in (("X", "A"), ("A", "X"), ("A", "C"), ("C", "A"))
        )
        + "</edges>"
    )
    (folder / "t.nod.xml").write_text(
        '<nodes><node id="A" x="0" y="0"/><node id="B" x="150" y="0" type="traffic_light"/>'
        '<node id="C" x="300" y="0"/></nodes>'
    )
    (folder / "t.edg.xml").write_text(
        "<edges>"
        + "".join(
            f'<edge id="{a}{b}" from="{a}" to="{b}" numLanes="1" speed="13.89" width="3.5"/>'
            for a, b in (("A", "B"), ("B", "A"), ("B", "C"), ("C", "B"))
        )
        + "</edges>"
    )
    (folder / "t.tll.xml").write_text(
        '<tlLogics><tlLogic id="B" type="static" programID="0" offset="0"><phase duration="1000" state="rr"/>'
        "</tlLogic></tlLogics>"
    )
    for stem, extra in (("straight", []), ("signal", ["--tllogic-files", str(folder / "t.tll.xml")])):
        prefix = "s" if stem == "straight" else "t"
        netconvert(folder / f"{prefix}.nod.xml", folder / f"{prefix}.edg.xml", folder / f"{stem}.net.xml", *extra)
    (folder / "follower.rou.xml").write_text(
        '<routes><vehicle id="follower" depart="0" departSpeed="max"><route edges="XA AC"/></vehicle></routes>'
    )
    (folder / "blocker.rou.xml").write_text(
        '<routes><vehicle id="blocker" depart="0" departPos="200" departSpeed="0"><route edges="AC"/>'
        '<stop lane="AC_0" endPos="205" duration="1000"/></vehicle></routes>'
    )
    for name, net, routes in (
        ("straight", "straight.net.xml", ""),
        ("follow", "straight.net.xml", "follower.rou.xml"),
        ("block", "straight.net.xml", "blocker.rou.xml"),
        ("signal", "signal.net.xml", ""),
    ):
        route_option = f'<route-files value="{routes}"/>' if routes else ""
        (folder / f"{name}.sumocfg").write_text(CFG.format(net=net, routes=route_option))
    return folder


def _drive(roads, cfg, edges, policy_of, max_s, **kwargs):
    scenario = load_scenario(roads / f"{cfg}.sumocfg")
    geometry = route_geometry(read_net(Path(scenario.net_path)), edges)
    return drive(scenario, geometry, policy_of(geometry), seed=1, max_s=max_s, config=NO_WARMUP, **kwargs)


def test_perfect_steer_keeps_the_lane_and_completes_the_road(roads):
    result = _drive(roads, "straight", ["AC"], RoutePolicy, max_s=80.0)
    m = result.metrics
    assert m["end_reason"] == "completed" and m["completion"] == pytest.approx(1.0)
    assert m["lane_departures"] == 0 and m["off_road_events"] == 0 and m["collisions"] == 0
    assert m["max_abs_offset_m"] < 0.05
    assert m["distance_m"] == pytest.approx(300.0 - 5.0 - result.log.progress_m[0], abs=0.5)
    # SUMO sees the ego where the bicycle model put it: the front bumper at lane position s + length / 2.
    ego = result.ego_id
    for frame, s in list(zip(result.frames, result.log.progress_m))[5:-1:20]:
        row = frame.index_of(ego)
        assert frame.lane_id[row] == "AC_0"
        assert frame.lane_pos_m[row] == pytest.approx(s + result.vehicle_length_m / 2.0, abs=0.05)


def test_constant_hard_steer_leaves_the_lane_within_seconds(roads):
    result = _drive(roads, "straight", ["AC"], lambda g: ConstantPolicy(0.5, 0.425, 0.0), max_s=30.0)
    log = result.log
    departed = lane_departed(log.offset_m, log.lane_width_m, result.vehicle_width_m)
    assert departed.any() and log.t_s[np.argmax(departed)] < 5.0
    assert log.offset_m[np.argmax(departed)] < 0  # a right steer leaves on the right
    assert result.metrics["lane_departures"] >= 1 and result.metrics["off_road_events"] >= 1
    assert result.metrics["end_reason"] == "left the route" and result.metrics["completion"] < 0.2


def test_other_traffic_stops_behind_a_standing_ego(roads):
    result = _drive(roads, "follow", ["AC"], lambda g: ConstantPolicy(0.0, 0.0, 1.0), max_s=30.0)
    last = result.frames[-1]
    ego, follower = last.index_of(result.ego_id), last.index_of("follower")
    assert last.x_m[ego] == pytest.approx(result.log.x_m[0])  # the ego never moved
    assert last.speed_mps[follower] < 0.1
    assert last.x_m[ego] - last.x_m[follower] > result.vehicle_length_m
    assert result.metrics["collisions"] == 0


def test_driving_into_a_standing_vehicle_is_a_collision(roads):
    result = _drive(roads, "block", ["AC"], lambda g: ConstantPolicy(0.6, 0.0, 0.0), max_s=25.0)
    assert result.metrics["collisions"] == 1
    hit = np.argmax(result.log.colliding)
    # The blocker stands with its front at lane position 205, its rear at 200; the ego's front
    # reaches it within the step (at most 0.25 s * 25 m/s beyond).
    front_m = result.log.progress_m[hit] + result.vehicle_length_m / 2.0
    assert 200.0 <= front_m <= 200.0 + 0.25 * result.log.speed_mps[hit]


def test_red_light_run_by_full_throttle_and_respected_by_the_route_policy(roads):
    run = _drive(roads, "signal", ["AB", "BC"], lambda g: ConstantPolicy(0.8, 0.0, 0.0), max_s=30.0)
    assert run.metrics["red_light_violations"] == 1
    line = run.route.crossings[0].s_start_m
    row = np.argmax(run.log.red_light)
    front = run.log.progress_m + run.vehicle_length_m / 2
    assert front[row - 1] < line <= front[row]
    stop = _drive(roads, "signal", ["AB", "BC"], RoutePolicy, max_s=40.0)
    assert stop.metrics["red_light_violations"] == 0 and stop.metrics["end_reason"] == "time limit"
    front = stop.log.progress_m[-1] + stop.vehicle_length_m / 2
    assert 0.0 < line - front < 2.0 and stop.log.speed_mps[-1] == 0.0
    assert stop.log.signal_letter[-1] == "r"


def test_standing_short_of_a_red_light_the_labeller_holds_where_the_driver_creeps(roads):
    seen = []

    class ShortStopper(RoutePolicy):  # stops 6 m before the line, as a learner may
        def __call__(self, observation):
            seen.append(observation)
            return super().__call__(observation)

    run = _drive(roads, "signal", ["AB", "BC"], lambda g: ShortStopper(g, RoutePolicyConfig(stop_gap_m=6.0)), max_s=40.0)
    line = run.route.crossings[0].s_start_m
    front = run.log.progress_m[-1] + run.vehicle_length_m / 2
    assert 5.0 < line - front < 7.0 and run.log.speed_mps[-1] == 0.0
    standing = seen[-1]
    max_accel = standing.frame.max_accel_mps2[standing.ego_row]
    max_decel = standing.frame.max_decel_mps2[standing.ego_row]
    # The driver (1 m stop gap) creeps up to the line: sqrt(2.5 x ~5 m) x 1.5 per s is more than its
    # acceleration allows. The labeller holds within hold_short_m of the line, and creeps from farther.
    assert RoutePolicy(run.route).wanted_accel_mps2(standing) == pytest.approx(max_accel)
    assert RoutePolicy(run.route, RoutePolicyConfig(hold_short_m=10.0)).wanted_accel_mps2(standing) == -max_decel
    farther = RoutePolicy(run.route, RoutePolicyConfig(hold_short_m=3.0))
    assert farther.wanted_accel_mps2(standing) == pytest.approx(max_accel)
    assert DaggerConfig().expert.hold_short_m == 10.0  # DAgger labels with the holding expert
    with pytest.raises(CrchflError, match="hold_short_m"):
        RoutePolicyConfig(hold_short_m=-1.0)


def test_an_ego_that_sumo_removes_ends_the_drive(roads, monkeypatch):
    import crchfl_sumo.driving.drive as drive_module

    class Vanishing(drive_module.Simulation):
        def step(self):
            frame = super().step()
            return frame.select(frame.ids != "ego") if self.t_s >= 3.0 else frame

    monkeypatch.setattr(drive_module, "Simulation", Vanishing)
    result = _drive(roads, "straight", ["AC"], RoutePolicy, max_s=20.0)
    assert result.metrics["end_reason"] == "removed by SUMO"
    assert result.log.t_s[-1] == pytest.approx(3.0 - 0.25)  # inserted at 0.25 s
    assert len(result.frames) == len(result.log) and np.isnan(result.log.throttle[-1])


def test_on_road_by_hand(roads):
    area = road_area(read_net(roads / "straight.net.xml"))
    assert on_road(area, 100.0, -1.6) and on_road(area, 100.0, 1.6)  # either direction's lane
    assert not on_road(area, 100.0, -5.0) and not on_road(area, 100.0, 20.0)



def test_the_crack_between_two_lanes_of_an_edge_is_road(tmp_path):
    """bs3d's lanes lie 3.3 m apart and 3.2 m wide: a lane change crossed the 0.1 m between them off the road. The
    strip between the centre lines is road; beyond them it is as before (a lane's half width, 1.6 m)."""
    net = tmp_path / "crack.net.xml"
    net.write_text(
        '<net version="1.20"><edge id="e" from="A" to="B"><lane id="e_0" index="0" speed="13.89" length="100" width="3.2" '
        'shape="0,0 100,0"/><lane id="e_1" index="1" speed="13.89" length="100" width="3.2" shape="0,3.3 100,3.3"/>'
        '</edge><junction id="A" type="priority" x="0" y="0" incLanes="" intLanes="" shape=""/>'
        '<junction id="B" type="priority" x="100" y="0" incLanes="e_0 e_1" intLanes="" shape=""/></net>'
    )
    area = road_area(read_net(net))
    assert on_road(area, 50.0, 1.65)  # 1.65 m from both centres: in the crack
    assert on_road(area, 50.0, -1.59) and on_road(area, 50.0, 4.89)
    assert not on_road(area, 50.0, -1.61) and not on_road(area, 50.0, 4.91)  # outside the outer lanes' edges

def _straight_road_with_cameras(roads):
    """The straight road's scenario, route AC, its commands and a renderer: what a model needs to drive it."""
    scenario = load_scenario(roads / "straight.sumocfg")
    net = read_net(Path(scenario.net_path))
    geometry = route_geometry(net, ["AC"])
    return scenario, geometry, RouteCommands(geometry, choice_junctions(net)), Renderer(build_world(scenario.net_path))


def test_untrained_model_drives_through_the_loop(roads):
    scenario, geometry, commands, renderer = _straight_road_with_cameras(roads)
    model = build_model(ModelConfig(), seed=0)
    policy = ModelPolicy(model, commands, steer_decoding="argmax")  # the DAC: every steer is a bin's value
    result = drive(scenario, geometry, policy, seed=1, max_s=2.0, config=NO_WARMUP, renderer=renderer)
    acted = result.log.steer[:-1]
    assert len(acted) == 8 and np.isin(acted.astype(np.float32), steer_bin_values(model.config.steer_bins)).all()
    assert np.all((result.log.throttle[:-1] >= 0) & (result.log.throttle[:-1] <= 1))
    assert not np.any((result.log.throttle[:-1] > 0) & (result.log.brake[:-1] > 0))  # one pedal at a time
    with pytest.raises(CrchflError, match="needs camera images"):
        drive(scenario, geometry, ModelPolicy(model, commands), max_s=1.0, config=NO_WARMUP)
    with pytest.raises(CrchflError, match="needs the route's commands"):
        ModelPolicy(model)
    ModelPolicy(build_model(ModelConfig(arch="paper"), seed=0))  # the paper's network sees no command
    with pytest.raises(CrchflError, match="steer decoding must be one of auto, argmax, expected"):
        ModelPolicy(model, commands, steer_decoding="mean")


def test_a_model_output_that_is_not_finite_is_an_error_naming_the_model(roads):
    scenario, geometry, commands, renderer = _straight_road_with_cameras(roads)
    model = build_model(ModelConfig(), seed=0)
    with torch.no_grad():  # what a diverged model gives: a NaN target speed
        model.branch_throttle_brake.heads[0][-1].bias.fill_(float("nan"))
    policy = ModelPolicy(model, commands, source="runs/x/final_model.pt")
    with pytest.raises(CrchflError, match=r"^runs/x/final_model\.pt: the model's output at t = .* is not finite"):
        drive(scenario, geometry, policy, seed=1, max_s=1.0, config=NO_WARMUP, renderer=renderer)


class _Commands:
    """Route commands by hand: LEFT before 5 m of progress, RIGHT after."""

    def at(self, s_m):
        return np.where(np.atleast_1d(s_m) < 5.0, LEFT, RIGHT)


def test_model_policy_feeds_the_route_command_and_the_ego_speed(roads):
    scenario = load_scenario(roads / "straight.sumocfg")
    geometry = route_geometry(read_net(Path(scenario.net_path)), ["AC"])
    model = build_model(ModelConfig(steer_bins=7), seed=0)
    with torch.no_grad():  # steer head k says class k + 1, whatever the images; a 14 m/s target speed
        for k, head in enumerate(model.branch_steer.heads):
            head[-1].weight.zero_()
            head[-1].bias.copy_(torch.nn.functional.one_hot(torch.tensor(k + 1), 7) * 5.0)
        target_out = model.branch_throttle_brake.heads[0][-1]
        target_out.weight.zero_()
        target_out.bias.fill_(1.4)
    seen = []
    model.branch_throttle_brake.register_forward_pre_hook(lambda module, args: seen.append(args[2].clone()))
    renderer = Renderer(build_world(scenario.net_path))
    result = drive(
        scenario, geometry, ModelPolicy(model, _Commands()), seed=1, max_s=3.0, config=NO_WARMUP, renderer=renderer
    )
    acted = result.log.steer[:-1].astype(np.float32)
    progress = result.log.progress_m[:-1]
    expected = np.where(progress < 5.0, STEER_CLASS_VALUES[LEFT + 1], STEER_CLASS_VALUES[RIGHT + 1])
    assert (progress < 5.0).any() and (progress >= 5.0).any()
    assert acted == pytest.approx(expected)
    assert [float(s[0]) for s in seen] == pytest.approx(result.log.speed_mps[:-1], abs=1e-5)
    assert result.log.speed_mps[-1] > 1.0


@pytest.mark.slow
def test_drive_route_writes_metrics_pictures_and_video(roads, tmp_path):
    checkpoint = tmp_path / "model.pt"
    model = build_model(ModelConfig(), seed=0)
    save_checkpoint(checkpoint, model.config, model.state_dict())
    scenario = str(roads / "signal.sumocfg")
    scripted = drive_route(None, scenario, "AB,BC", tmp_path / "script", seed=1, max_s=30.0, config=NO_WARMUP)
    learned = drive_route(checkpoint, scenario, "AB,BC", tmp_path / "model", seed=1, max_s=3.0, config=NO_WARMUP)
    for folder, metrics in ((tmp_path / "script", scripted), (tmp_path / "model", learned)):
        assert json.loads((folder / "metrics.json").read_text()) == metrics
        assert (folder / "trajectory.png").stat().st_size > 0 and (folder / "drive.mp4").stat().st_size > 0
        # SUMO's warnings went to the folder's sumo.log, counted in the metrics
        assert (folder / "sumo.log").is_file() and metrics["sumo_warnings"] == sum(
            line.startswith("Warning:") for line in (folder / "sumo.log").read_text().splitlines())
        log = read_trajectory_csv(folder / "trajectory.csv")
        assert len(log) == int(round(metrics["duration_s"] / 0.25)) + 1
    assert scripted["model"] == "" and learned["model"] == str(checkpoint)
    assert (tmp_path / "script" / "frames" / "red_light.png").is_file()  # it waited at the red light
    out = compare_runs([tmp_path / "script", tmp_path / "model"], ["script", "untrained"], tmp_path / "fig5.png")
    assert out.stat().st_size > 0
    with pytest.raises(CrchflError, match="one per folder"):
        compare_runs([tmp_path / "script"], ["a", "b"], tmp_path / "x.png")
    # damaged result files are refused by name, with the fix
    metrics_path = tmp_path / "model" / "metrics.json"
    for damage, message in (('{"scenario": "x"', "not readable JSON"), ('{"scenario": "x"}', "lacks edges"),
                            ('[1, 2]', "lacks scenario, edges"), ('{"scenario": 3, "edges": "AB"}', "damaged")):
        metrics_path.write_text(damage)
        with pytest.raises(CrchflError, match=f"metrics.json: .*{message}.*drive the route again"):
            compare_runs([tmp_path / "script", tmp_path / "model"], None, tmp_path / "y.png")
    trajectory = tmp_path / "script" / "trajectory.csv"
    trajectory.write_text(trajectory.read_text().replace("0.25", "x", 1))
    with pytest.raises(CrchflError, match="trajectory.csv: damaged"):
        read_trajectory_csv(trajectory)
    assert not (tmp_path / "y.png").exists()


def test_one_pedal_keeps_the_stronger_pedal():
    from crchfl_sumo.driving.policies import one_pedal

    assert one_pedal(0.46, 0.45) == (0.46, 0.0)  # a hedging model still drives off
    assert one_pedal(0.2, 0.7) == (0.0, 0.7)
    assert one_pedal(0.5, 0.5) == (0.0, 0.5)  # a tie brakes
    assert one_pedal(0.0, 0.0) == (0.0, 0.0)


def test_a_correction_is_the_expert_braking_harder_or_steering_elsewhere_by_hand():
    from crchfl_sumo.driving.dagger import is_correction

    assert is_correction((0.5, 0.0, 0.0), (0.0, 0.0, 0.9))  # the learner drives on, the expert brakes
    assert not is_correction((0.0, 0.0, 0.9), (0.0, 0.0, 0.9))  # both brake
    assert not is_correction((0.3, 0.0, 0.0), (0.8, 0.0, 0.0))  # the expert would go faster: no correction
    assert not is_correction((0.0, 0.0, 0.5), (0.0, 0.0, 0.5 + 0.1))  # 0.1 harder is within the margin
    assert is_correction((0.3, 0.05, 0.0), (0.3, -0.1, 0.0))  # 0.15 apart in steer
    assert not is_correction((0.3, 0.05, 0.0), (0.3, 0.1, 0.0))
    # Inside a junction the learner braking where the expert drives on is a correction too (clear the junction)
    assert not is_correction((0.0, 0.0, 0.9), (0.5, 0.0, 0.0))
    assert is_correction((0.0, 0.0, 0.9), (0.5, 0.0, 0.0), inside_junction=True)
    assert not is_correction((0.0, 0.0, 0.3), (0.0, 0.0, 0.3 - 0.1), inside_junction=True)  # within the margin
    assert not is_correction((0.5, 0.0, 0.0), (0.8, 0.0, 0.0), inside_junction=True)  # slower, not braking


def test_inside_crossing_from_the_front_bumper_to_the_centre_leaving_by_hand():
    from crchfl_sumo.sumo.route import inside_crossing
    from crchfl_sumo.sumo.route import Crossing

    crossings = [Crossing(100.0, 116.0, "B", 0, "l"), Crossing(300.0, 310.0, "C", 1, "s")]
    length = 4.0  # the front bumper is 2 m ahead of the centre
    assert not inside_crossing(crossings, 97.9, length)  # front at 99.9: short of the stop line
    assert not inside_crossing(crossings, 98.0, length)  # front exactly on the line: not yet in
    assert inside_crossing(crossings, 98.1, length)
    assert inside_crossing(crossings, 115.9, length)  # the centre still inside
    assert not inside_crossing(crossings, 116.0, length)  # the centre has left
    assert not inside_crossing(crossings, 200.0, length)  # between the junctions
    assert inside_crossing(crossings, 305.0, length)
    assert not inside_crossing([], 305.0, length)


def test_a_corrections_only_labeller_keeps_exactly_the_corrected_steps(roads):
    from crchfl_sumo.driving.dagger import is_correction

    scenario = load_scenario(roads / "signal.sumocfg")
    net = read_net(Path(scenario.net_path))
    geometry = route_geometry(net, ["AB", "BC"])
    renderer = Renderer(build_world(scenario.net_path))

    class FullThrottle(ModelPolicy):  # a learner that never brakes, towards an always-red light
        def __call__(self, observation):
            super().__call__(observation)
            return (0.8, 0.0, 0.0)

    learner = FullThrottle(build_model(ModelConfig(), seed=0), RouteCommands(geometry, choice_junctions(net)))
    expert = RoutePolicy(geometry)
    steps = []

    class Checked(ExpertLabelled):
        def __call__(self, observation):
            steps.append((learner(observation), expert(observation)))
            return super().__call__(observation)

    policy = Checked(learner, expert, every=2, corrections_only=True)
    drive(scenario, geometry, policy, seed=1, max_s=12.0, config=NO_WARMUP, renderer=renderer)
    labelled = steps[::2]
    kept = [e for a, e in labelled if is_correction(a, e)]
    assert 0 < len(kept) < len(labelled)  # it cruised with the learner at first, then braked for the light
    np.testing.assert_allclose(policy.arrays()["actions"], np.asarray(kept, dtype=np.float32), rtol=1e-6)
    assert len(policy.arrays()["images"]) == len(policy.arrays()["target_speed_mps"]) == len(kept)


def test_the_labeller_corrects_a_learner_that_stops_inside_a_junction(ladder):
    from crchfl_sumo.driving.drive_bench_tasks import without_traffic
    from crchfl_sumo.sumo.route import inside_crossing

    scenario = without_traffic(load_scenario(ladder / "ladder.sumocfg"))
    net = read_net(Path(scenario.net_path))
    geometry = route_geometry(net, ["AB", "BE"])  # a left turn at B
    expert = RoutePolicy(geometry)
    inside_steps = []

    class StopsInTheJunction(ModelPolicy):  # drives as the expert does, but brakes once inside the junction
        def __call__(self, observation):
            super().__call__(observation)
            length_m = float(observation.frame.length_m[observation.ego_row])
            inside = inside_crossing(geometry.crossings, observation.progress_m, length_m)
            inside_steps.append(inside)
            throttle, steer, _ = expert(observation)
            return (0.0, steer, 1.0) if inside else (throttle, steer, 0.0)

    learner = StopsInTheJunction(build_model(ModelConfig(), seed=0), RouteCommands(geometry, choice_junctions(net)))
    policy = ExpertLabelled(learner, expert, every=1, corrections_only=True)
    drive(scenario, geometry, policy, seed=1, max_s=30.0, config=NO_WARMUP, renderer=Renderer(build_world(scenario.net_path)))
    labels = policy.arrays()["actions"]
    # Outside the junction learner and expert agree (nothing kept); inside, every step is one where the expert
    # drives on and the learner brakes: kept, labelled with no brake.
    assert sum(inside_steps) > 10 and len(labels) == sum(inside_steps)
    assert np.all(labels[:, 2] == 0.0) and np.all(labels[:, 0] > 0.0)


def test_expert_labelled_drive_records_the_route_policys_actions_on_the_learners_states(roads):
    scenario, geometry, commands, renderer = _straight_road_with_cameras(roads)
    learner = ModelPolicy(build_model(ModelConfig(), seed=0), commands)
    expert = RoutePolicy(geometry)
    seen = []

    class Checked(ExpertLabelled):
        def __call__(self, observation):
            seen.append((observation, expert(observation), learner(observation)))
            return super().__call__(observation)

    policy = Checked(learner, expert, every=3)
    result = drive(scenario, geometry, policy, seed=1, max_s=2.0, config=NO_WARMUP, renderer=renderer)
    arrays = policy.arrays()
    acted = len(result.log) - 1
    assert acted == 8 and len(arrays["actions"]) == 3  # steps 0, 3 and 6 of 8
    # The learner drove: the log holds its actions, not the expert's.
    np.testing.assert_allclose(result.log.steer[:-1], [s[2][1] for s in seen])
    for i, step in enumerate((0, 3, 6)):
        observation, expert_action, _ = seen[step]
        np.testing.assert_allclose(arrays["actions"][i], expert_action, rtol=1e-6)
        np.testing.assert_array_equal(arrays["images"][i], observation.images)
        assert arrays["command"][i] == learner.command(observation)
        speed = observation.frame.speed_mps[observation.ego_row]
        assert arrays["speed_mps"][i] == pytest.approx(speed)
        # the speed the expert's wanted acceleration reaches over the learner's horizon (1 s; it has
        # no recorded future here)
        wanted = expert.wanted_accel_mps2(observation)
        assert arrays["target_speed_mps"][i] == pytest.approx(max(0.0, speed + 1.0 * wanted), rel=1e-6)
    assert arrays["target_speed_mps"][0] > 2.0  # pulling away from standstill: 1 s at full acceleration
    assert arrays["steer_class"].tolist() == digitize_steer(arrays["actions"][:, 1]).tolist()
    assert arrays["actions"][0, 0] > 0  # from standstill on an empty road the expert pulls away
    assert arrays["images"].dtype == np.uint8 and arrays["images"].shape[1:] == (4, 64, 128, 3)


def test_a_drive_writes_sumos_own_fcd_with_the_ego_in_it(roads, tmp_path, capsys):
    import sumolib

    from crchfl_sumo.cli import main

    out = tmp_path / "drive"
    assert main(["drive", "reference", "--route", "AB,BC", "--scenario", str(roads / "signal.sumocfg"), "--out",
                 str(out), "--max-s", "10", "--warmup-s", "0", "--no-video", "--sumo-output", "fcd,tripinfo"]) == 0
    steps = [(float(s.time), [v.id for v in (s.vehicle if s.hasChild("vehicle") else [])])
             for s in sumolib.xml.parse(str(out / "sumo-fcd.xml"), "timestep")]
    assert any("ego" in ids for _, ids in steps)  # SUMO's copy of the ego, step by step
    assert (out / "sumo-tripinfo.xml").is_file() and not list(out.glob(".*.partial"))
    capsys.readouterr()
    assert main(["drive", "reference", "--route", "AB,BC", "--scenario", str(roads / "signal.sumocfg"), "--out",
                 str(tmp_path / "bad"), "--sumo-output", "lanes"]) == 2
    assert "--sumo-output: lanes unknown" in capsys.readouterr().err
