"""The built-in scenarios: Town01/Town02 topology against the CARLA reference,
routes, scenario.toml files, and SUMO runs without teleports or collisions."""

from __future__ import annotations

import importlib.util
import math
import re
import sys
import xml.etree.ElementTree as ET
from functools import lru_cache
from pathlib import Path

import pytest
import sumolib

from helpers import half_hour_statistics

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[2]
SCENARIOS_DIR = REPO / "scenarios"
SCENARIOS = ("town01", "town02", "paper", "paper_linked")

# Extent (width x height, metres) of the reference networks converted from
# CARLA's OpenDRIVE maps, /work/shared/reference/carla-towns/Town0{1,2}.net.xml,
# read with sumolib.net.readNet(...).getBBoxXY():
# Town01 [(0.03, 0.00), (394.44, 328.63)], Town02 [(0.09, 0.00), (197.20, 197.14)].
REFERENCE_SIZE_M = {"town01": (394.41, 328.63), "town02": (197.11, 197.14)}
REFERENCE_T_JUNCTIONS = {"town01": 12, "town02": 8}
LANE_WIDTH_M = 4.0
SPEED_LIMIT_MPS = 13.89


@lru_cache(maxsize=None)
def net(name: str) -> sumolib.net.Net:
    return sumolib.net.readNet(str(SCENARIOS_DIR / name / f"{name}.net.xml"))


@lru_cache(maxsize=None)
def scenario(name: str) -> dict:
    with open(SCENARIOS_DIR / name / "scenario.toml", "rb") as f:
        return tomllib.load(f)


def neighbours(node: sumolib.net.node.Node) -> set[str]:
    return {e.getFromNode().getID() for e in node.getIncoming()} | {e.getToNode().getID() for e in node.getOutgoing()}


def route_files(name: str) -> list[Path]:
    cfg = ET.parse(SCENARIOS_DIR / name / f"{name}.sumocfg").getroot()
    files = cfg.find("input/route-files").get("value").split(",")
    return [SCENARIOS_DIR / name / f for f in files]


def routes(name: str) -> dict[str, tuple[list[str], int]]:
    """Vehicle id -> (edges, repeat) for every vehicle of a scenario."""
    out = {}
    for path in route_files(name):
        root = ET.parse(path).getroot()
        named = {r.get("id"): r for r in root.findall("route")}
        for vehicle in root.findall("vehicle"):
            route = vehicle.find("route") if vehicle.get("route") is None else named[vehicle.get("route")]
            out[vehicle.get("id")] = (route.get("edges").split(), int(route.get("repeat", "0")))
    return out


# ---------------------------------------------------------------- topology


@pytest.mark.parametrize("town", ["town01", "town02"])
def test_bounding_box_within_5_percent_of_reference(town):
    (xmin, ymin), (xmax, ymax) = net(town).getBBoxXY()
    ref_w, ref_h = REFERENCE_SIZE_M[town]
    assert abs((xmax - xmin) - ref_w) <= 0.05 * ref_w
    assert abs((ymax - ymin) - ref_h) <= 0.05 * ref_h
    assert (xmin, ymin) == pytest.approx((0.0, 0.0), abs=1e-6)


@pytest.mark.parametrize("town", ["town01", "town02"])
def test_t_junctions_are_signalised_and_the_rest_are_plain_corners(town):
    nodes = net(town).getNodes()
    t_junctions = [n for n in nodes if len(neighbours(n)) == 3]
    others = [n for n in nodes if len(neighbours(n)) != 3]
    assert len(t_junctions) == REFERENCE_T_JUNCTIONS[town]
    assert all(n.getType() == "traffic_light" for n in t_junctions)
    tls_ids = {tls.getID() for tls in net(town).getTrafficLights()}
    assert tls_ids == {n.getID() for n in t_junctions}
    assert len(others) == 4
    for node in others:
        assert len(neighbours(node)) == 2
        assert node.getType() == "priority"
        # a corner turns through 90 degrees
        (ax, ay), (bx, by) = (net(town).getNode(n).getCoord() for n in sorted(neighbours(node)))
        cx, cy = node.getCoord()
        assert (ax - cx) * (bx - cx) + (ay - cy) * (by - cy) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("town", ["town01", "town02"])
def test_corners_turn_on_a_10m_radius(town):
    """Roads stop 10 m before a corner node; the curve between them is the
    internal lane, whose speed SUMO limits by lateral acceleration
    (5.5 m/s^2: sqrt(5.5 * 8) = 6.6 m/s on the inner lane's 8 m radius)."""
    inner = sumolib.net.readNet(str(SCENARIOS_DIR / town / f"{town}.net.xml"), withInternal=True)
    for node in inner.getNodes():
        if node.getType() != "priority":
            continue
        cx, cy = node.getCoord()
        for edge in node.getIncoming():
            x, y = edge.getShape()[-1]  # lane end, where the curve starts
            # the roads are axis-aligned: the distance along the road is the larger offset
            assert max(abs(x - cx), abs(y - cy)) == pytest.approx(10.0, abs=0.01)
        vias = [c.getViaLaneID() for c in node.getConnections() if c.getViaLaneID()]
        assert len(vias) == 2
        for via in vias:
            assert inner.getLane(via).getSpeed() > 6.6


@pytest.mark.parametrize("name", SCENARIOS)
def test_every_road_has_one_4m_lane_each_way_at_50_kmh(name):
    edges = net(name).getEdges()
    ids = {e.getID() for e in edges}
    for edge in edges:
        assert edge.getLaneNumber() == 1
        assert edge.getLanes()[0].getWidth() == pytest.approx(LANE_WIDTH_M)
        assert edge.getSpeed() == pytest.approx(SPEED_LIMIT_MPS)
        reverse = [e for e in edge.getToNode().getOutgoing() if e.getToNode() == edge.getFromNode()]
        assert len(reverse) == 1 and reverse[0].getID() in ids


@pytest.mark.parametrize("name", SCENARIOS)
def test_left_turns_at_t_junctions_and_no_u_turns(name):
    for node in net(name).getNodes():
        directions = sorted(c.getDirection() for c in node.getConnections())
        if node.getType() == "traffic_light":
            # three arms, one lane each: two lefts, two rights, two straights
            assert directions == ["l", "l", "r", "r", "s", "s"], node.getID()
        else:
            assert len(directions) == 2 and "t" not in directions, node.getID()
    for edge in net(name).getEdges():
        for target in edge.getOutgoing():
            assert target.getToNode() != edge.getFromNode(), f"U-turn {edge.getID()} -> {target.getID()}"


def test_paper_holds_both_towns_with_no_road_between_them():
    paper = net("paper")
    for town in ("town01", "town02"):
        prefix = "t01_" if town == "town01" else "t02_"
        nodes = [n for n in paper.getNodes() if n.getID().startswith(prefix)]
        assert len(nodes) == len(net(town).getNodes())
        assert len([e for e in paper.getEdges() if e.getID().startswith(prefix)]) == len(net(town).getEdges())
    assert len(paper.getNodes()) == len(net("town01").getNodes()) + len(net("town02").getNodes())
    assert paper.getShortestPath(paper.getEdge("t01_S1_S2"), paper.getEdge("t02_H_SE"))[0] is None
    assert paper.getShortestPath(paper.getEdge("t02_H_SE"), paper.getEdge("t01_S1_S2"))[0] is None


def test_paper_linked_has_a_path_both_ways_between_the_towns():
    linked = net("paper_linked")
    there, _ = linked.getShortestPath(linked.getEdge("t01_S1_S2"), linked.getEdge("t02_H_SE"))
    back, _ = linked.getShortestPath(linked.getEdge("t02_H_SE"), linked.getEdge("t01_S1_S2"))
    assert there is not None and back is not None
    assert any(e.getID().startswith("link_") for e in there)
    assert any(e.getID().startswith("link_") for e in back)


def test_paper_towns_keep_their_shape():
    """Each town inside the two-town networks is the stand-alone town, shifted."""
    for name in ("paper", "paper_linked"):
        for entry in scenario(name)["towns"]:
            town = net(entry["name"])
            (txmin, tymin), (txmax, tymax) = town.getBBoxXY()
            assert entry["xmax_m"] - entry["xmin_m"] == pytest.approx(txmax - txmin, abs=0.01)
            assert entry["ymax_m"] - entry["ymin_m"] == pytest.approx(tymax - tymin, abs=0.01)


# ---------------------------------------------------------------- routes


@pytest.mark.parametrize("name", SCENARIOS)
def test_every_route_is_connected(name):
    n = net(name)
    for vid, (edges, repeat) in routes(name).items():
        hops = list(zip(edges, edges[1:])) + ([(edges[-1], edges[0])] if repeat else [])
        for a, b in hops:
            assert n.getEdge(b) in n.getEdge(a).getOutgoing(), f"{name}: {vid} cannot go {a} -> {b}"


@pytest.mark.parametrize("name", SCENARIOS)
def test_routes_outlast_half_an_hour(name):
    """No vehicle can finish its route within 30 minutes, even at 1.2 x the limit."""
    n = net(name)
    for vid, (edges, repeat) in routes(name).items():
        length_m = sum(n.getEdge(e).getLength() for e in edges) * (1 + repeat)
        assert length_m > 1800.0 * 1.2 * SPEED_LIMIT_MPS, vid


def turns_at_signals(n: sumolib.net.Net, edges: list[str]) -> set[str]:
    cyclic = edges + edges[:1]
    out = set()
    for a, b in zip(cyclic, cyclic[1:]):
        node = n.getEdge(a).getToNode()
        if node.getType() == "traffic_light":
            (conn,) = n.getEdge(a).getConnections(n.getEdge(b))
            out.add(conn.getDirection())
    return out


@pytest.mark.parametrize("name", SCENARIOS)
def test_named_vehicles_loop_through_left_and_right_turns(name):
    n, all_routes = net(name), routes(name)
    for town in scenario(name)["towns"]:
        named = town["data_vehicles"] + town["test_vehicles"]
        for vid in named:
            edges, repeat = all_routes[vid]
            assert repeat > 0, vid
            assert {"l", "r"} <= turns_at_signals(n, edges), vid
        # different start zones: start edges at least 50 m apart
        starts = [n.getEdge(all_routes[v][0][0]).getShape()[0] for v in named]
        for i, (ax, ay) in enumerate(starts):
            for bx, by in starts[i + 1:]:
                assert math.hypot(ax - bx, ay - by) > 50.0, town["name"]


def test_data_vehicle_names_and_counts():
    assert scenario("town01")["towns"][0]["data_vehicles"] == ["t01_data_0", "t01_data_1"]
    assert scenario("town02")["towns"][0]["data_vehicles"] == ["t02_data_0", "t02_data_1", "t02_data_2"]
    assert scenario("town01")["towns"][0]["test_vehicles"] == ["t01_test_0"]
    assert scenario("town02")["towns"][0]["test_vehicles"] == ["t02_test_0"]
    paper = {t["name"]: t for t in scenario("paper")["towns"]}
    assert len(paper["town01"]["data_vehicles"]) == 2 and len(paper["town02"]["data_vehicles"]) == 3
    linked = [v for t in scenario("paper_linked")["towns"] for v in t["data_vehicles"]]
    link_vehicles = [v for v in linked if v.startswith("link_data_")]
    assert len(link_vehicles) == 2
    for vid in link_vehicles:
        edges, _ = routes("paper_linked")[vid]
        assert any(e.startswith("t01_") for e in edges) and any(e.startswith("t02_") for e in edges)


# ---------------------------------------------------------------- scenario.toml


@pytest.mark.parametrize("name", SCENARIOS)
def test_scenario_toml_schema(name):
    sc = scenario(name)
    assert set(sc) == {"description", "sumocfg", "edge_sites", "towns"}
    assert (SCENARIOS_DIR / name / sc["sumocfg"]).is_file()
    assert len(sc["edge_sites"]) == len(sc["towns"]) == (1 if name.startswith("town") else 2)
    vehicle_ids = set(routes(name))
    for site, town in zip(sc["edge_sites"], sc["towns"]):
        assert set(site) == {"name", "x_m", "y_m", "height_m"}
        assert set(town) == {"name", "xmin_m", "ymin_m", "xmax_m", "ymax_m", "data_vehicles", "test_vehicles"}
        # the edge server stands at the centre of its town
        assert site["x_m"] == pytest.approx((town["xmin_m"] + town["xmax_m"]) / 2)
        assert site["y_m"] == pytest.approx((town["ymin_m"] + town["ymax_m"]) / 2)
        assert set(town["data_vehicles"]) | set(town["test_vehicles"]) <= vehicle_ids


@pytest.mark.parametrize("name", SCENARIOS)
def test_sumocfg_is_relative_with_fixed_seed_and_quarter_second_steps(name):
    cfg = ET.parse(SCENARIOS_DIR / name / f"{name}.sumocfg").getroot()
    assert float(cfg.find("time/step-length").get("value")) == 0.25
    assert cfg.find("random_number/seed").get("value") == "42"
    for entry in cfg.find("input"):
        for f in entry.get("value").split(","):
            assert not Path(f).is_absolute()
            assert (SCENARIOS_DIR / name / f).is_file()


# ---------------------------------------------------------------- build and run


@pytest.mark.slow
def test_build_reproduces_the_committed_files(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("build_nets", REPO / "tools" / "build_nets.py")
    build_nets = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "build_nets", build_nets)  # dataclasses look their module up
    spec.loader.exec_module(build_nets)
    build_nets.build_all(tmp_path)
    for name in (*SCENARIOS, "scale200"):
        built = sorted(p.name for p in (tmp_path / name).iterdir())
        assert built == sorted(p.name for p in (SCENARIOS_DIR / name).iterdir() if not p.name.startswith(f"{name}.nod")
                               and not p.name.startswith(f"{name}.edg"))
        for file_name in built:
            assert (tmp_path / name / file_name).read_bytes() == (SCENARIOS_DIR / name / file_name).read_bytes(), file_name


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENARIOS)
def test_half_an_hour_without_teleports_or_collisions(name, tmp_path):
    root = half_hour_statistics(SCENARIOS_DIR / name / f"{name}.sumocfg", tmp_path)
    vehicles = root.find("vehicles").attrib
    assert int(root.find("teleports").get("total")) == 0
    assert int(root.find("safety").get("collisions")) == 0
    assert int(vehicles["inserted"]) == int(vehicles["loaded"]) == int(vehicles["running"]) == len(routes(name))


def _build_nets_module(monkeypatch):
    spec = importlib.util.spec_from_file_location("build_nets", REPO / "tools" / "build_nets.py")
    build_nets = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "build_nets", build_nets)  # dataclasses look their module up
    spec.loader.exec_module(build_nets)
    return build_nets


def test_scale_copies_keep_scale200s_layout_and_refuse_counts_they_cannot_hold(monkeypatch):
    build_nets = _build_nets_module(monkeypatch)
    assert build_nets.scale_copies(200) == (("town01a", "t1a", 0.0, 0.0), ("town01b", "t1b", 600.0, 0.0),
                                            ("town01c", "t1c", 0.0, 534.2), ("town01d", "t1d", 600.0, 534.2))
    layout = build_nets.scale_copies(1000)  # 20 copies, 5 to a row
    assert len(layout) == 20 and layout[-1] == ("town01t", "t1t", 2400.0, 3 * 534.2)
    for bad in (0, 75, 1350):
        with pytest.raises(CrchflError, match="--scale-clients"):
            build_nets.scale_copies(bad)


def test_a_larger_scale_scenario_builds_and_loads_as_a_scenario_folder(tmp_path, monkeypatch):
    build_nets = _build_nets_module(monkeypatch)
    build_nets.build_scale_only(300, tmp_path)
    scenario = load_scenario(tmp_path / "scale300")
    assert scenario.name == "scale300" and len(scenario.towns) == 6 and len(scenario.edge_sites) == 12
    data = [v for town in scenario.towns for v in town.data_vehicles]
    assert len(data) == len(set(data)) == 300
    boxes = [(t.xmin_m, t.ymin_m, t.xmax_m, t.ymax_m) for t in scenario.towns]
    for i, a in enumerate(boxes):  # the copies lie apart
        for b in boxes[i + 1:]:
            assert a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1]
    # Every copy's signals keep Town01's offsets.
    net = (tmp_path / "scale300" / "scale300.net.xml").read_text()
    offsets = dict(re.findall(r'<tlLogic id="t1[a-f]_([^"]+)" type="static" programID="0" offset="(\d+)"', net))
    assert offsets and all(int(v) == build_nets.SIGNAL_OFFSETS_S["town01"][k] for k, v in offsets.items())
    with Simulation(scenario, seed=1) as sim:
        frames = [sim.step() for _ in range(8)]
    assert set(data) <= set(frames[-1].ids.tolist())  # the named vehicles all start at once
