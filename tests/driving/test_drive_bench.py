"""The driving benchmark: its arithmetic by hand, route drawing on a known network, and tiny suites driven."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from helpers import netconvert

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.intervals import wilson_interval
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.driving.drive_bench import STUCK_S, BenchConfig, run_benchmark
from crchfl_sumo.driving.drive_bench_behaviour import ABILITIES
from crchfl_sumo.driving.drive_bench_score import (
    penalty,
    pool_task_summaries,
    route_completion,
    score_episode,
    succeeded,
    summarize_task,
)
from crchfl_sumo.driving.drive_bench_tasks import (
    TASKS,
    MAX_RED_S,
    TIME_BUDGET_SPEED_MPS,
    TaskConfig,
    Candidate,
    apart_from_data,
    candidate_routes,
    count_turns,
    crossing_turn_rad,
    data_routes,
    drawable,
    draw_episodes,
    queue_edges,
    drives_stretch_of,
    longest_waits_s,
    listed_files,
    route_files,
    task_by_name,
    time_limit_s,
    without_traffic,
)
from crchfl_sumo.driving.drive import DriveConfig, drive, footprints_overlap, sumo_warnings, warnings_to
from crchfl_sumo.driving.policies import ConstantPolicy, RoutePolicy
from crchfl_sumo.sumo.route import Crossing, RouteGeometry, read_net, route_geometry
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation

# --- arithmetic by hand ---------------------------------------------------------------------------


def test_penalty_and_success_rules_by_hand():
    assert penalty({}) == 1.0
    assert penalty({"collisions": 1, "red_light_violations": 1}) == pytest.approx(0.60 * 0.70)
    assert penalty({"collisions": 2, "red_light_violations": 0}) == pytest.approx(0.36)
    assert penalty({"red_light_violations": 3, "lane_departures": 5}) == pytest.approx(0.343)  # departures: no penalty
    assert succeeded("completed", 0, 0)
    assert not succeeded("completed", 1, 0)  # a collision
    assert not succeeded("completed", 0, 1)  # off the road
    assert not succeeded("time limit", 0, 0) and not succeeded("left the route", 0, 0)


def test_route_completion_leaves_out_progress_made_off_the_road_and_going_back():
    # 10 m a step; the step that ends off the road (row 2) adds nothing: 30 of 40 m.
    assert route_completion([0, 10, 20, 30, 40], [1, 1, 0, 1, 1], 0.0, 40.0) == pytest.approx(0.75)
    # Backwards and forwards again: only new best progress counts (10 + 5 of 20).
    assert route_completion([0, 10, 5, 15], [1, 1, 1, 1], 0.0, 20.0) == pytest.approx(0.75)
    # Starts 2 m in, goal at 42: all on the road and past the goal is 1, never more.
    assert route_completion([2, 30, 50], [1, 1, 1], 2.0, 42.0) == 1.0


def _record(end, completion, distance_m, collisions=0, red=0, off_road=0, departures=0, min_speed=1.0,
            efficiency=None, smoothness=None, turns=(0, 0)):
    metrics = {"end_reason": end, "collisions": collisions, "red_light_violations": red,
               "off_road_events": off_road, "lane_departures": departures}
    abilities = {name: [0, 0] for name in ABILITIES} | {"turn_at_junction": list(turns)}
    return {**metrics, "distance_m": distance_m, **score_episode(metrics, completion, min_speed),
            "efficiency": efficiency, "smoothness": smoothness, "abilities": abilities}


def test_task_summary_of_scripted_episodes_by_hand():
    records = [
        _record("completed", 1.0, 400.0),  # success, score 1
        _record("completed", 1.0, 300.0, collisions=1, red=1),  # reached the goal but collided: 0.42
        _record("time limit", 0.8, 200.0, red=2, departures=1),  # 0.8 * 0.49 = 0.392
        _record("left the route", 0.25, 100.0, off_road=1, departures=1),  # 0.25
    ]
    assert [r["driving_score"] for r in records] == pytest.approx([1.0, 0.42, 0.392, 0.25])
    s = summarize_task(records)
    assert s["episodes"] == 4
    assert s["success_rate"] == pytest.approx(0.25)
    assert s["route_completion"] == pytest.approx((1.0 + 1.0 + 0.8 + 0.25) / 4)
    assert s["driving_score"] == pytest.approx((1.0 + 0.42 + 0.392 + 0.25) / 4)
    # 1 + 1 + 2 + 1 + 1 + 1 = 7 infractions over 1 km
    assert s["infractions_per_km"] == pytest.approx(7.0)
    assert s["infractions"] == {"collisions": 1, "red_light_violations": 3, "off_road_events": 1, "lane_departures": 2}
    assert summarize_task([_record("time limit", 0.0, 0.0)])["infractions_per_km"] is None  # never moved


def test_the_leaderboard_2_keys_of_a_cell_by_hand():
    records = [
        _record("completed", 1.0, 400.0, efficiency=80.0, smoothness=1.0, turns=(2, 2)),  # strict success
        _record("completed", 1.0, 300.0, red=1, min_speed=0.85, efficiency=120.0, turns=(1, 1)),  # success, not strict
        _record("stuck", 0.5, 200.0, min_speed=0.7, smoothness=0.5, turns=(1, 0)),  # blocked
        _record("time limit", 0.8, 100.0, red=2, turns=(1, 0)),
    ]
    assert [r["strict_success"] for r in records] == [True, False, False, False]
    assert [r["driving_score_lb2"] for r in records] == pytest.approx([1.0, 0.7 * 0.85, 0.5 * 0.7, 0.8 * 0.49])
    s = summarize_task(records)
    assert s["success_rate"] == 0.5 and s["strict_success_rate"] == 0.25
    assert s["success_ci95"] == list(wilson_interval(2, 4)) and s["strict_success_ci95"] == list(wilson_interval(1, 4))
    assert s["red_lights_per_km"] == pytest.approx(3.0)  # 3 red lights over 1 km
    assert (s["efficiency"], s["efficiency_episodes"]) == (100.0, 2)  # the mean of the episodes that have one
    assert (s["smoothness"], s["smoothness_episodes"]) == (0.75, 2)
    assert s["agent_blocked"] == 1 and s["route_timeouts"] == 1
    turn = s["abilities"]["turn_at_junction"]
    assert (turn["attempts"], turn["successes"], turn["success_rate"]) == (5, 3, 0.6)
    assert s["abilities"]["stop_at_red"] == {"attempts": 0, "successes": 0, "success_rate": None,
                                             "success_ci95": [0.0, 1.0]}


def test_pooled_task_summaries_equal_the_summary_of_all_episodes():
    first = [_record("completed", 1.0, 400.0), _record("completed", 1.0, 300.0, collisions=1, red=1)]
    second = [_record("time limit", 0.8, 200.0, red=2, departures=1), _record("left the route", 0.25, 100.0, off_road=1),
              _record("completed", 1.0, 500.0)]
    pooled = pool_task_summaries([summarize_task(first), summarize_task(second)])
    together = summarize_task(first + second)
    assert pooled.pop("infractions") == together.pop("infractions")
    assert pooled.pop("abilities") == together.pop("abilities")
    assert pooled.keys() == together.keys()
    for key, value in together.items():
        assert pooled[key] == (value if value is None else pytest.approx(value)), key
    # by hand: 2 of 5 succeed; 1 + 1 + 2 + 1 + 1 = 6 infractions over 1.5 km
    assert pooled["episodes"] == 5 and pooled["success_rate"] == pytest.approx(0.4)
    assert pooled["infractions_per_km"] == pytest.approx(4.0)


def test_footprint_overlap_by_hand():
    def overlaps(x, y, heading=0.0, length=4.5, width=1.8):
        return bool(footprints_overlap(0.0, 0.0, 0.0, 4.5, 1.8, [x], [y], [heading], [length], [width])[0])

    assert overlaps(4.4, 0.0) and not overlaps(4.6, 0.0)  # nose to tail: 4.5 m between centres touch
    assert overlaps(0.0, 1.7) and not overlaps(0.0, 1.9)  # side by side: 1.8 m
    # A 2 m square turned 45 degrees off the ego's corner: apart along the square's own diagonal
    # axis (gap 3.92 m > 2.23 + 1.00) although neither of the ego's axes separates them ...
    assert not overlaps(3.45, 2.1, math.pi / 4, 2.0, 2.0)
    # ... and touching when 0.7 m nearer on both axes (gap 2.93 m < 3.23 m).
    assert overlaps(2.75, 1.4, math.pi / 4, 2.0, 2.0)


def test_longest_waits_wrap_round_the_cycle_and_time_limit_by_hand(tmp_path):
    net = tmp_path / "tls.net.xml"
    net.write_text(
        '<net><tlLogic id="J" type="static" programID="0" offset="0">'
        '<phase duration="10" state="Gr"/><phase duration="3" state="yr"/>'
        '<phase duration="20" state="rG"/><phase duration="5" state="Gr"/></tlLogic></net>'
    )
    waits = longest_waits_s(net)
    assert waits[("J", 0)] == pytest.approx(23.0)  # yellow 3 + red 20
    assert waits[("J", 1)] == pytest.approx(18.0)  # red 5 at the end + 10 + 3 at the start
    xy = np.array([[0.0, 0.0], [250.0, 0.0]])
    route = RouteGeometry(("e",), xy, np.array([0.0, 250.0]), np.array([3.2]), np.array([False]),
                          (Crossing(100.0, 110.0, "J", 1, "s"), Crossing(200.0, 210.0, "", -1, "l")))
    assert TIME_BUDGET_SPEED_MPS == pytest.approx(10 / 3.6)
    assert time_limit_s(route, waits) == pytest.approx(250.0 / (10 / 3.6) + 10.0 + 18.0)  # 90 + 10 + 18 s


def test_longest_waits_read_the_program_sumo_runs_the_last_loaded(tmp_path):
    """bs3d's net holds four programs of its game signal and SUMO runs the last (traci: program '3'); reading the
    first, drive-bench drew routes through links the running program holds red for 1006 s and the reference ended
    stuck at them. An additional file's program comes after the net's."""
    net = tmp_path / "tls.net.xml"
    net.write_text(
        '<net><tlLogic id="J" type="static" programID="0" offset="0">'
        '<phase duration="4" state="rG"/><phase duration="1000" state="rG"/></tlLogic>'
        '<tlLogic id="J" type="static" programID="1" offset="0">'
        '<phase duration="4" state="yr"/><phase duration="1000" state="Gr"/></tlLogic></net>'
    )
    waits = longest_waits_s(net)
    assert waits[("J", 0)] == pytest.approx(4.0)  # program 1's yellow
    assert waits[("J", 1)] == pytest.approx(1004.0)  # never green in program 1
    extra = tmp_path / "tls.add.xml"
    extra.write_text(
        '<additional><tlLogic id="J" type="static" programID="2" offset="0">'
        '<phase duration="30" state="Gr"/><phase duration="20" state="rG"/></tlLogic></additional>'
    )
    assert longest_waits_s(net, [extra]) == {("J", 0): pytest.approx(20.0), ("J", 1): pytest.approx(30.0)}
    scenario = SimpleNamespace(sumo_options=("--route-files=a.rou.xml", f"--additional-files={extra},b.add.xml"))
    assert listed_files(scenario, "--additional-files") == [extra, Path("b.add.xml")]
    assert route_files(scenario) == [Path("a.rou.xml")]


def test_turning_back_and_a_red_longer_than_a_drive_may_stand_are_not_drawn():
    """A10KW's dual carriageways end in links SUMO calls 's' or 'l' that turn back by 150 degrees or more, and its
    signals (the SUMO game's, switched by a player) hold a link red for 20012 s: the reference driver left the road
    turning back and ended stuck at the red. A 90 degree turn and a 90 s red are drawn."""
    def route(points, crossing):
        xy = np.asarray(points, dtype=np.float64)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        return RouteGeometry(("a", "b"), xy, s, np.full(len(xy) - 1, 3.2), np.zeros(len(xy) - 1, bool), (crossing,))

    # stop line at s = 20, junction to s = 26 (6 m across), then out: left by 90 degrees, or back 6 m to the left
    left = route([(0, 0), (20, 0), (26, 0), (26, 30)], Crossing(20.0, 26.0, "", -1, "l"))
    back = route([(0, 0), (20, 0), (26, 0), (26, 6), (0, 6)], Crossing(20.0, 32.0, "", -1, "s"))
    assert crossing_turn_rad(left, left.crossings[0]) == pytest.approx(math.pi / 2)
    assert abs(crossing_turn_rad(back, back.crossings[0])) == pytest.approx(math.pi)
    assert drawable(left, {}) and not drawable(back, {})
    assert not drawable(route([(0, 0), (20, 0), (40, 0)], Crossing(20.0, 26.0, "", -1, "t")), {})  # SUMO's U-turn
    assert MAX_RED_S <= STUCK_S  # a drive obeying a longer red would end stuck
    signal = route([(0, 0), (20, 0), (40, 0)], Crossing(20.0, 26.0, "J", 0, "s"))
    assert drawable(signal, {("J", 0): 90.0})
    assert not drawable(signal, {("J", 0): 20012.0})


def test_edges_whose_every_way_on_waits_at_a_red_longer_than_a_drive_are_queues(tmp_path):
    """Z -> A, then A -> D (free) or A -> M -> B -> C with a signal at B: with B's link red for 20012 s (A10KW's
    game signals) MB and AM, whose only way on is MB, fill with a queue that never moves; ZA can turn to D. With a
    50 s red (the towns' longest) nothing queues for ever."""
    (tmp_path / "q.nod.xml").write_text(
        '<nodes><node id="Z" x="-100" y="0"/><node id="A" x="0" y="0"/><node id="D" x="0" y="-100"/>'
        '<node id="M" x="100" y="0"/><node id="B" x="200" y="0" type="traffic_light"/><node id="C" x="300" y="0"/>'
        '</nodes>'
    )
    (tmp_path / "q.edg.xml").write_text(
        "<edges>" + "".join(f'<edge id="{a}{b}" from="{a}" to="{b}" numLanes="1" speed="13.89"/>'
                            for a, b in ("ZA", "AD", "AM", "MB", "BC")) + "</edges>"
    )
    netconvert(tmp_path / "q.nod.xml", tmp_path / "q.edg.xml", tmp_path / "q.net.xml")
    net = read_net(tmp_path / "q.net.xml")
    (link,) = net.getEdge("MB").getConnections(net.getEdge("BC"))
    assert (link.getTLSID(), link.getTLLinkIndex()) == ("B", 0)
    assert queue_edges(net, {("B", 0): 20012.0}) == {"MB", "AM"}
    assert queue_edges(net, {("B", 0): 50.0}) == set()
    route = RouteGeometry(("ZA", "AM"), np.array([[-100.0, 0.0], [100.0, 0.0]]), np.array([0.0, 200.0]),
                          np.array([3.2]), np.array([False]), ())
    assert drawable(route, {}) and not drawable(route, {}, {"MB", "AM"})



def test_an_edge_each_of_whose_lanes_has_a_red_longer_than_a_drive_is_a_queue(tmp_path):
    """bs3d: the game signal holds an approach's straight links red for 1006 s and its left turn green, on a lane
    shared with a straight link; the cars for the red stand at that lane's head and the ego, turning left behind
    them, ended stuck. A -> M -> B, then B -> C (straight) or B -> D (left), signal at B."""
    (tmp_path / "l.nod.xml").write_text(
        '<nodes><node id="A" x="0" y="0"/><node id="M" x="100" y="0"/><node id="B" x="200" y="0" type="traffic_light"/>'
        '<node id="C" x="300" y="0"/><node id="D" x="200" y="100"/></nodes>'
    )
    def net_with(lanes: int, connections: str):
        (tmp_path / "l.edg.xml").write_text(
            "<edges>" + "".join(f'<edge id="{a}{b}" from="{a}" to="{b}" numLanes="{n}" speed="13.89"/>'
                                for a, b, n in (("A", "M", 1), ("M", "B", lanes), ("B", "C", 1), ("B", "D", 1)))
            + "</edges>"
        )
        (tmp_path / "l.con.xml").write_text(f"<connections>{connections}</connections>")
        out = tmp_path / f"l{lanes}.net.xml"  # read_net caches by path
        netconvert(tmp_path / "l.nod.xml", tmp_path / "l.edg.xml", out, "-x", str(tmp_path / "l.con.xml"))
        net = read_net(out)
        (straight,) = net.getEdge("MB").getConnections(net.getEdge("BC"))
        (left,) = net.getEdge("MB").getConnections(net.getEdge("BD"))
        return net, {(straight.getTLSID(), straight.getTLLinkIndex()): 1006.0, (left.getTLSID(), left.getTLLinkIndex()): 6.0}

    # one lane, both links from it: its head is blocked for ever, and AM, whose only way on is MB, queues too
    net, waits = net_with(1, '<connection from="MB" to="BC"/><connection from="MB" to="BD"/>')
    assert queue_edges(net, waits) == {"MB", "AM"}
    # two lanes, the left turn on its own: the queue for the red leaves it free
    net, waits = net_with(2, '<connection from="MB" to="BC" fromLane="0" toLane="0"/>'
                             '<connection from="MB" to="BD" fromLane="1" toLane="0"/>')
    assert queue_edges(net, waits) == set()

# --- routes on a known network ----------------------------------------------------------------------


def test_turns_are_counted_on_a_known_network(ladder):
    net = read_net(ladder / "ladder.net.xml")
    assert count_turns(route_geometry(net, ["AB", "BC"])) == 0  # straight through B
    assert count_turns(route_geometry(net, ["AB", "BE"])) == 1  # left at B
    assert count_turns(route_geometry(net, ["CF", "FE"])) == 1  # the corner F counts: the wheel must turn
    assert count_turns(route_geometry(net, ["AB", "BE", "ED"])) == 2  # left at B, left at E
    assert count_turns(route_geometry(net, ["DA", "AB", "BC"])) == 1  # left at the corner A, straight at B
    scenario = load_scenario(ladder / "ladder.sumocfg")
    candidates = {c.edges: c for c in candidate_routes(scenario)}
    assert candidates[("AB", "BC")].turns == 0 and candidates[("AB", "BE")].turns == 1
    assert candidates[("AB", "BE", "ED")].turns == 2  # the shortest way from AB to ED
    assert ("AB", "BC", "CF", "FE", "ED") not in candidates  # the long way round is never drawn
    for c in candidates.values():
        assert c.turns == count_turns(route_geometry(net, c.edges))


def test_episodes_are_drawn_by_seed_into_their_suites(ladder):
    scenario = load_scenario(ladder / "ladder.sumocfg")
    tasks = [task_by_name(n) for n in ("straight", "one_turn", "navigation", "navigation_traffic")]
    first = draw_episodes(scenario, tasks, 3, seed=7)
    assert first == draw_episodes(scenario, tasks, 3, seed=7)  # the same seed, the same episodes
    other = draw_episodes(scenario, tasks, 3, seed=8)
    assert [e.sumo_seed for e in first] != [e.sumo_seed for e in other]
    by_task = {t.name: [e for e in first if e.task == t.name] for t in tasks}
    assert all(len(v) == 3 for v in by_task.values())
    assert all(e.turns == 0 for e in by_task["straight"]) and all(e.turns == 1 for e in by_task["one_turn"])
    assert all(e.turns >= 2 for e in by_task["navigation"])
    # With and without traffic drive the same routes, seeds and warm-ups (CoRL2017's navigation pair).
    assert [(e.edges, e.sumo_seed, e.warmup_s) for e in by_task["navigation"]] == [
        (e.edges, e.sumo_seed, e.warmup_s) for e in by_task["navigation_traffic"]
    ]
    # Without replacement while routes last: the straight suite's three routes differ.
    assert len({e.edges for e in by_task["straight"]}) == 3
    assert all(20.0 <= e.warmup_s <= 110.0 for e in first)


def test_bounded_searches_find_the_shortest_routes_of_the_pairs_they_reach(ladder, monkeypatch):
    from crchfl_sumo.driving import drive_bench_tasks

    scenario = load_scenario(ladder / "ladder.sumocfg")
    net = read_net(Path(scenario.net_path))
    # from AB within 250 m: AB alone (100 m), on to BC or BE (200 m each; the ladder has no U-turns)
    paths = drive_bench_tasks.shortest_paths_from(net.getEdge("AB"), 250.0)
    assert {goal: [e.getID() for e in path] for goal, path in paths.items()} == {
        "AB": ["AB"], "BC": ["AB", "BC"], "BE": ["AB", "BE"]}
    every = {c.edges: c for c in drive_bench_tasks.candidate_routes(scenario)}
    # as on a large network: sampled starts, a few goals each; each a shortest route of its pair
    monkeypatch.setattr(drive_bench_tasks, "ALL_PAIRS_MAX_EDGES", 0)
    monkeypatch.setattr(drive_bench_tasks, "BOUNDED_STARTS", 5)
    monkeypatch.setattr(drive_bench_tasks, "BOUNDED_GOALS", 3)
    bounded = drive_bench_tasks.candidate_routes(scenario)
    assert 0 < len(bounded) <= 15 and bounded == drive_bench_tasks.candidate_routes(scenario)
    by_pair = {(c.edges[0], c.edges[-1]): c for c in every.values()}
    for c in bounded:
        assert c.length_m == pytest.approx(by_pair[(c.edges[0], c.edges[-1])].length_m)


def test_the_suites_length_and_turn_limits_are_settings(ladder):
    scenario = load_scenario(ladder / "ladder.sumocfg")
    tasks = [task_by_name(n) for n in ("straight", "navigation", "navigation_traffic")]
    limited = TaskConfig(min_route_m=250.0, navigation_turns=(3, 3))
    drawn = draw_episodes(scenario, tasks, 4, seed=1, config=limited)
    navigation = [e for e in drawn if e.task == "navigation"]
    assert navigation and all(e.turns == 3 for e in navigation)
    assert all(e.length_m >= 250.0 for e in drawn)
    assert [e.edges for e in navigation] == [e.edges for e in drawn if e.task == "navigation_traffic"]
    for bad, key in (({"min_route_m": 700.0}, "min_route_m"), ({"navigation_turns": (1, 3)}, "navigation_turns"),
                     ({"navigation_turns": (4, 3)}, "navigation_turns"), ({"warmup_range_s": (50.0, 10.0)}, "warmup_range_s")):
        with pytest.raises(CrchflError, match=key):
            TaskConfig(**bad)


def test_a_task_without_a_route_is_skipped_and_the_rest_runs(ladder, tmp_path):
    # on the ladder a straight route (two 100 m edges) fits in 250 m, a route of two turns does not
    config = BenchConfig(tasks=("straight", "navigation"), routes=TaskConfig(max_route_m=250.0))
    summary = run_benchmark(None, tmp_path / "b", episodes=1, towns=(str(ladder / "ladder.sumocfg"),), config=config)
    assert list(summary["results"]["ladder"]) == ["straight"]
    assert summary["skipped"] == [{"town": "ladder", "task": "navigation", "reason": "no candidate route"}]
    assert "Skipped: navigation in ladder (no candidate route)." in (tmp_path / "b" / "results.md").read_text()


def test_data_vehicle_routes_are_left_out():
    assert drives_stretch_of(["c", "a"], ["a", "b", "c"])  # across the end of the repeated loop
    assert drives_stretch_of(["b", "c", "a", "b"], ["a", "b", "c"])
    assert not drives_stretch_of(["a", "c"], ["a", "b", "c"])
    assert not apart_from_data(["a", "x"], [["a", "b"]])  # a data vehicle started on edge a
    assert apart_from_data(["b", "x"], [["a", "b"]])
    scenario = load_scenario("town01")
    loops = data_routes(scenario)
    assert [loop[0] for loop in loops] == ["S1_W1", "S2_SE"]  # t01_data_0, t01_data_1 (town01.ego.rou.xml)
    candidates = candidate_routes(scenario)
    assert {min(c.turns, 2) for c in candidates} == {0, 1, 2}
    for c in candidates:
        assert c.edges[0] not in ("S1_W1", "S2_SE")
        assert not any(drives_stretch_of(c.edges, loop) for loop in loops)
    assert isinstance(candidates[0], Candidate)


def test_suites_without_traffic_run_no_vehicle(ladder):
    scenario = load_scenario(ladder / "ladder.sumocfg")
    for s, expect_traffic in ((scenario, True), (without_traffic(scenario), False)):
        with Simulation(s, seed=0) as sim:
            seen = max(len(sim.step()) for _ in range(40))
        assert (seen > 0) == expect_traffic
    assert [t.traffic for t in TASKS] == [False, False, False, True]


# --- tiny suites driven ----------------------------------------------------------------------------


def test_a_drive_that_stands_still_ends_stuck(ladder):
    scenario = load_scenario(ladder / "ladder.sumocfg")
    route = route_geometry(read_net(Path(scenario.net_path)), ["AB", "BC"])
    config = DriveConfig(warmup_s=0.0, stuck_s=5.0)
    standing = drive(without_traffic(scenario), route, ConstantPolicy(0.0, 0.0, 1.0), max_s=60.0, config=config)
    assert standing.metrics["end_reason"] == "stuck" and standing.log.t_s[-1] == pytest.approx(5.0)
    moving = drive(without_traffic(scenario), route, RoutePolicy(route), max_s=60.0, config=config)
    assert moving.metrics["end_reason"] == "completed"


@dataclass
class HardSteerDriver:
    """Full throttle with the hardest right steer class: must fail every task."""

    label: str = "hard steer"
    renders: bool = False

    def policy(self, route, net):
        return ConstantPolicy(0.5, 0.425, 0.0)

    def expert(self):
        return ExpertConfig()


SUITE = BenchConfig(tasks=("straight", "one_turn", "navigation"))


def test_reference_driver_scores_full_marks_and_hard_steer_fails(ladder, tmp_path):
    cfg = str(ladder / "ladder.sumocfg")
    summary = run_benchmark(None, tmp_path / "ref", episodes=2, towns=(cfg,), config=SUITE, seed=3)
    results = summary["results"]["ladder"]
    assert list(results) == ["straight", "one_turn", "navigation"]
    for task, r in results.items():
        assert r["episodes"] == 2, task
        assert r["success_rate"] == 1.0 and r["route_completion"] == 1.0 and r["driving_score"] == 1.0, task
        assert r["infractions_per_km"] == 0.0, task
    on_disk = json.loads((tmp_path / "ref" / "summary.json").read_text())
    assert on_disk["results"]["ladder"] == results and on_disk["driver"] == "reference"
    with open(tmp_path / "ref" / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3 and float(rows[0]["success_rate"]) == 1.0
    assert len(json.loads((tmp_path / "ref" / "episodes.json").read_text())) == 6
    assert (tmp_path / "ref" / "trajectories.png").stat().st_size > 10_000
    assert "| ladder | navigation | 2 | 100 % [34, 100] | 100 % |" in (tmp_path / "ref" / "results.md").read_text()
    for task, r in results.items():  # no signal on the ladder: every success is strict, every turn taken
        assert r["strict_success_rate"] == 1.0 and r["red_lights_per_km"] == 0.0, task
        turns = r["abilities"]["turn_at_junction"]
        assert turns["successes"] == turns["attempts"] and r["abilities"]["stop_at_red"]["attempts"] == 0, task
    assert results["one_turn"]["abilities"]["turn_at_junction"]["attempts"] >= 2

    bad = run_benchmark(None, tmp_path / "bad", episodes=2, towns=(cfg,), config=SUITE, seed=3,
                        driver=HardSteerDriver())
    for task, r in bad["results"]["ladder"].items():
        assert r["success_rate"] == 0.0 and r["driving_score"] < 0.5, task
        assert r["infractions"]["off_road_events"] >= 2, task
    episodes = json.loads((tmp_path / "bad" / "episodes.json").read_text())
    assert {e["end_reason"] for e in episodes} == {"left the route"}
    # SUMO's log of each episode lies in sumo-logs (these drives gave SUMO nothing to warn of)
    logs = sorted((tmp_path / "bad" / "sumo-logs").glob("*.log"))
    assert len(logs) == 6 and logs[0].name == "ladder-navigation-0.log" and bad["sumo_warnings"] == 0


def test_sumos_warnings_go_to_the_drives_log_not_the_console(ladder, tmp_path, capfd):
    # a vehicle of the flow moved about 190 m along its route in one step by TraCI: SUMO warns of the implied speed
    scenario = load_scenario(ladder / "ladder.sumocfg")
    capfd.readouterr()
    with Simulation(scenario, seed=1, extra_options=warnings_to(tmp_path / "logs" / "a.log")) as sim:
        frame = sim.step()
        while not len(frame.ids):
            frame = sim.step()
        sim.place_vehicle(str(frame.ids[0]), 190.0, -1.6, 0.0, 5.0)
        sim.step()
    assert sumo_warnings(tmp_path / "logs") >= 1 and "Warning:" not in capfd.readouterr().err
    assert warnings_to(None) == () and sumo_warnings(tmp_path / "none") == 0


def test_a_checkpoint_drives_the_benchmark_with_its_cameras_and_commands(ladder, tmp_path):
    from crchfl_sumo.learning.checkpoint import save_checkpoint
    from crchfl_sumo.learning.model import build_model
    from crchfl_sumo.learning.settings import ModelConfig

    model = build_model(ModelConfig(), seed=0)
    save_checkpoint(tmp_path / "untrained.pt", model.config, model.state_dict())
    config = BenchConfig(tasks=("one_turn",), drive=DriveConfig(stuck_s=3.0))
    summary = run_benchmark(tmp_path / "untrained.pt", tmp_path / "out", episodes=1,
                            towns=(str(ladder / "ladder.sumocfg"),), config=config)
    assert summary["driver"] == "untrained" and summary["model"] == str(tmp_path / "untrained.pt")
    (episode,) = json.loads((tmp_path / "out" / "episodes.json").read_text())
    # The wiring is what is tested (checkpoint, renderer, route commands raise when missing), not the
    # untrained model's driving: it drove some steps and ended by one of the loop's rules.
    assert episode["end_reason"] in ("stuck", "left the route", "completed", "time limit")
    assert episode["duration_s"] >= 3.0 or episode["end_reason"] == "left the route"
    assert summary["results"]["ladder"]["one_turn"]["episodes"] == 1


def test_parallel_episodes_give_the_serial_results(ladder, tmp_path):
    cfg = str(ladder / "ladder.sumocfg")
    config = BenchConfig(tasks=("straight", "one_turn"), group_episodes=1)
    serial = run_benchmark(None, tmp_path / "serial", episodes=1, towns=(cfg,), config=config, seed=5)
    parallel = run_benchmark(None, tmp_path / "parallel", episodes=1, jobs=2, towns=(cfg,), config=config, seed=5)
    assert parallel["results"] == serial["results"]
    assert (json.loads((tmp_path / "parallel" / "episodes.json").read_text())
            == json.loads((tmp_path / "serial" / "episodes.json").read_text()))


def test_bad_arguments_name_the_option(ladder, tmp_path):
    cfg = str(ladder / "ladder.sumocfg")
    with pytest.raises(CrchflError, match="--episodes must be >= 1"):
        run_benchmark(None, tmp_path, episodes=0, towns=(cfg,))
    with pytest.raises(CrchflError, match="--jobs must be >= 1"):
        run_benchmark(None, tmp_path, jobs=0, towns=(cfg,))
    with pytest.raises(CrchflError, match="--towns: town09"):
        run_benchmark(None, tmp_path, towns=("town09",))
    with pytest.raises(CrchflError, match="MODEL: no checkpoint at"):
        run_benchmark(tmp_path / "missing.pt", tmp_path, towns=(cfg,))
    with pytest.raises(CrchflError, match="--tasks: unknown task 'loops'"):
        BenchConfig(tasks=("loops",))
    with pytest.raises(CrchflError, match="--steer-decoding: use one of auto, argmax, expected"):
        BenchConfig(steer_decoding="mean")
    with pytest.raises(CrchflError, match="--brake-gain must be > 0"):
        BenchConfig(brake_gain=float("nan"))


def test_the_command_runs_a_suite_and_reports_bad_input_with_status_2(ladder, tmp_path, capsys):
    from crchfl_sumo.cli import main

    cfg = str(ladder / "ladder.sumocfg")
    assert main(["drive-bench", "reference", "--out", str(tmp_path / "b"), "--episodes", "1",
                 "--towns", cfg, "--tasks", "straight"]) == 0
    assert "| ladder | straight | 1 | 100 % [21, 100] | 100 % |" in capsys.readouterr().out
    assert json.loads((tmp_path / "b" / "summary.json").read_text())["results"]["ladder"]["straight"]["episodes"] == 1
    assert main(["drive-bench", "reference", "--out", str(tmp_path / "c"), "--episodes", "0", "--towns", cfg]) == 2
    err = capsys.readouterr().err
    assert "drive-bench --episodes: 0 is out of range; give a number of episodes in 1 .. 10000" in err
    for option, value, message in (("--navigation-turns", "2", "--navigation-turns: '2'; give FEWEST,MOST"),
                                   ("--navigation-turns", "1,5", "bench.navigation_turns"),
                                   ("--min-route-m", "900", "bench.min_route_m")):
        assert main(["drive-bench", "reference", "--out", str(tmp_path / "d"), "--towns", cfg, option, value]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_a_model_drives_with_the_cameras_of_its_training_data(ladder, tmp_path):
    from crchfl_sumo.core.config import to_mapping
    from crchfl_sumo.driving.drivers import ModelDriver
    from crchfl_sumo.learning.checkpoint import save_checkpoint
    from crchfl_sumo.learning.model import build_model
    from crchfl_sumo.learning.settings import ModelConfig
    from crchfl_sumo.vision.camera import CameraConfig
    from crchfl_sumo.vision.raster import RasterConfig
    from crchfl_sumo.vision.world import WorldConfig

    model = build_model(ModelConfig(image_height=48, image_width=64), seed=0)
    net = str(ladder / "ladder.net.xml")
    # A data set drawn with 1 px lamps and coarse ground: the manifest's camera block travels in the checkpoint.
    raster = RasterConfig(camera=CameraConfig(height_px=48, width_px=64), lamp_min_radius_px=1.0)
    world = WorldConfig(metres_per_pixel=0.2)
    camera = {"raster": to_mapping(raster), "world": to_mapping(world)}
    save_checkpoint(tmp_path / "with.pt", model.config, model.state_dict(), {"camera": camera})
    renderer = ModelDriver(str(tmp_path / "with.pt")).renderer(net)
    assert renderer.config == raster and renderer.world.config == world
    # Written without it: today's defaults at the model's image size, every head lit as when it was written.
    save_checkpoint(tmp_path / "without.pt", model.config, model.state_dict())
    renderer = ModelDriver(str(tmp_path / "without.pt")).renderer(net)
    assert renderer.config == RasterConfig(camera=CameraConfig(height_px=48, width_px=64), route_signal=False)
    assert renderer.world.config == WorldConfig()
    bad = {"camera": {"raster": {**to_mapping(raster), "lamp_size": 3}, "world": to_mapping(world)}}
    save_checkpoint(tmp_path / "bad.pt", model.config, model.state_dict(), bad)
    with pytest.raises(CrchflError, match="bad.pt: extra.camera.raster"):
        ModelDriver(str(tmp_path / "bad.pt")).renderer(net)


def test_a_model_drives_through_the_steering_rack_of_its_training_data(tmp_path):
    from crchfl_sumo.driving.drivers import ModelDriver
    from crchfl_sumo.driving.dynamics import curvature_from_steer
    from crchfl_sumo.learning.checkpoint import save_checkpoint
    from crchfl_sumo.learning.model import build_model
    from crchfl_sumo.learning.settings import ModelConfig

    model = build_model(ModelConfig(image_height=48, image_width=64), seed=0)
    rack = {"steer_knee": 0.275, "sharp_steer_gain": 2.0}
    save_checkpoint(tmp_path / "rack.pt", model.config, model.state_dict(), {"expert": rack})
    expert = ModelDriver(str(tmp_path / "rack.pt")).expert()
    # the sharpest class turns the wheels 23 deg (11 + 0.15 * 80), where a linear 40 deg rack gives 17
    assert curvature_from_steer(0.425, expert) == pytest.approx(-math.tan(math.radians(23.0)) / 2.9)
    # a checkpoint written before the rack travelled was labelled linearly, whatever today's default
    save_checkpoint(tmp_path / "old.pt", model.config, model.state_dict())
    old = ModelDriver(str(tmp_path / "old.pt")).expert()
    assert curvature_from_steer(0.425, old) == pytest.approx(-math.tan(math.radians(17.0)) / 2.9)
    save_checkpoint(tmp_path / "bad.pt", model.config, model.state_dict(), {"expert": {"steer_knee": 2.0}})
    with pytest.raises(CrchflError, match="bad.pt: extra.expert.steer_knee: 2 is out of range"):
        ModelDriver(str(tmp_path / "bad.pt")).model()
