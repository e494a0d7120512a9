"""Build the built-in SUMO scenarios from the hand-written town descriptions.

    python tools/build_nets.py            # rewrites scenarios/*
    python tools/build_nets.py --out DIR  # writes DIR/<scenario>/ instead
    python tools/build_nets.py --scale-clients 1000 --out DIR  # only DIR/scale1000/ (20 copies of Town01)

Reads scenarios/town01/town01.{nod,edg}.xml,
town02/town02.{nod,edg}.xml and street.typ.xml, and writes, for each of the
scenarios town01, town02, paper (both towns in one network, no road between
them), paper_linked (the same plus a two-way road from Town01 to Town02) and
scale200 (four copies of Town01 with 200 data vehicles and eight edge sites):

    <name>.net.xml      netconvert's network
    vtypes.add.xml      vehicle types
    <name>.bg.rou.xml   background vehicles (randomTrips.py + duarouter, fixed seed)
    <name>.ego.rou.xml  named data / test / link vehicles on closed loops (paper scenarios: data walks)
    <name>.sumocfg      SUMO configuration (step length 0.25 s, fixed seed)
    scenario.toml       edge sites and towns, read by crchfl_sumo.sumo.scenario

Every output is written to a temporary file and renamed into place, and the
same inputs give byte-identical outputs (SUMO's header comments, which carry
a date and temporary paths, are replaced). The binaries and randomTrips.py
come from the eclipse-sumo package (sumo.SUMO_HOME), else from PATH.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import sumolib

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.installation import sumo_binary as scenario_sumo_binary
from crchfl_sumo.sumo.installation import sumo_tool_script

SCENARIOS_DIR = Path(__file__).resolve().parents[1] / "scenarios"
TYPE_FILE = SCENARIOS_DIR / "street.typ.xml"

SEED = 42
STEP_LENGTH_S = 0.25
SPEED_LIMIT_MPS = 13.89
# Named vehicles repeat their loop long enough to drive this long at the speed limit.
EGO_DRIVE_S = 7200.0
# Background routes are at least this long, so no background vehicle leaves
# within this many seconds even at 1.2 x the speed limit (its top speed factor).
BACKGROUND_MIN_S = 3600.0
BACKGROUND_MAX_SPEED_FACTOR = 1.2

NETCONVERT_OPTIONS = {
    "no-turnarounds": "true",  # the towns have no dead ends, so no U-turns anywhere
    "offset.disable-normalization": "true",  # keep the coordinates as written
    "junctions.corner-detail": "5",  # smooth kerbs at corners and T-junctions
    "tls.default-type": "static",  # fixed 90 s cycle, as the reference
    "tls.allred.time": "2",  # 40 s green, 3 s yellow, 2 s all-red per phase: the junction clears
}
SIGNAL_CYCLE_S = 90  # two phases of 40 s green + 3 s yellow + 2 s all-red


@dataclass(frozen=True)
class Town:
    """One hand-described town and how the named vehicles loop through it.

    loops: vehicle id -> closed node sequence (first node == last node).
    paper_walks: data vehicle id -> the closed walk it drives in the paper scenarios
        instead of its loop (first node == last node, nodes may repeat). The loops turn
        left and right at signals but cross most T-junctions only along their turns; a
        walk is the vehicle's loop and one more cycle through one of its nodes, chosen
        so that the town's data vehicles together take nearly every turn and every
        straight pass the town's signals offer (33 of Town01's 36, all 24 of Town02's;
        docs/measurements.md, "2026-12-07, eighth"). The single-town scenarios keep the
        loops: their named vehicles are the benchmarks' traffic.
    background_vehicles: how many randomTrips vehicles roam the town.
    intermediate: randomTrips' intermediate waypoints per background trip.
    link_node: where the connecting road of paper_linked meets this town:
        (node id, x, y, road end a, road end b) splitting road a-b.
    """

    name: str
    prefix: str
    loops: dict[str, list[str]]
    data_vehicles: list[str]
    test_vehicles: list[str]
    background_vehicles: int
    intermediate: int
    link_node: tuple[str, float, float, str, str]
    paper_walks: dict[str, list[str]] = field(default_factory=dict)


TOWN01 = Town(
    name="town01",
    prefix="t01",
    loops={
        # west zone: right at W1, lefts at E1/E2/M3/N2/S1, rights at W2/W3
        "t01_data_0": ["S1", "W1", "E1", "E2", "W2", "W3", "M3", "N2", "N1", "NW", "SW", "S1"],
        # east zone: lefts at N3/W2/W1/S2, rights at E2/E1
        "t01_data_1": ["S2", "SE", "NE", "N3", "E3", "E2", "W2", "W1", "E1", "S2"],
        # north-west start: rights at N2/N3/S1/N1, lefts at M3/E3
        "t01_test_0": ["N1", "N2", "M3", "E3", "N3", "NE", "SE", "S2", "S1", "W1", "W2", "W3", "N1"],
    },
    data_vehicles=["t01_data_0", "t01_data_1"],
    test_vehicles=["t01_test_0"],
    background_vehicles=30,
    intermediate=160,
    link_node=("L", 394.4, 164.3, "SE", "NE"),
    paper_walks={
        # adds straight at E1, E2, M3, N1, N2, N3, W1, W2; left at E3, W3; right at S1, S2
        "t01_data_0": ["S1", "W1", "E1", "E2", "E3", "M3", "W3", "W2", "W1", "S1", "SW", "NW", "N1", "N2", "N3",
                       "NE", "SE", "S2", "E1", "E2", "W2", "W3", "M3", "N2", "N1", "NW", "SW", "S1"],
        # adds straight at E2, N3, S1, S2, W2, W3; left at E1, E3; right at M3, N1, N2
        "t01_data_1": ["S2", "SE", "NE", "N3", "E3", "E2", "W2", "W1", "E1", "E2", "E3", "M3", "N2", "N3", "NE",
                       "SE", "S2", "S1", "SW", "NW", "N1", "W3", "W2", "W1", "E1", "S2"],
    },
)

TOWN02 = Town(
    name="town02",
    prefix="t02",
    loops={
        # north zone: right at D/F/G/A, lefts at C/B
        "t02_data_0": ["NW", "NE", "D", "C", "F", "G", "B", "A", "NW"],
        # south-east zone: lefts at D/C/G/H, right at F
        "t02_data_1": ["H", "SE", "E", "D", "C", "F", "G", "H"],
        # centre: lefts at F/C/A/H, right at G
        "t02_data_2": ["G", "F", "C", "B", "A", "SW", "H", "G"],
        # east start: rights at E/G/A, left at B
        "t02_test_0": ["D", "E", "F", "G", "B", "A", "NW", "NE", "D"],
    },
    data_vehicles=["t02_data_0", "t02_data_1", "t02_data_2"],
    test_vehicles=["t02_test_0"],
    background_vehicles=15,
    intermediate=260,
    link_node=("L", 0.0, 57.3, "SW", "A"),
    paper_walks={
        # each adds movements its loop lacks, e.g. straight at A, D, G (data_0), B, C, F (data_1), A, C, F, H (data_2)
        "t02_data_0": ["NW", "NE", "D", "C", "F", "G", "B", "C", "F", "E", "D", "NE", "NW", "A", "SW", "H", "G",
                       "B", "A", "NW"],
        "t02_data_1": ["H", "SE", "E", "D", "C", "F", "G", "H", "SW", "A", "B", "C", "D", "E", "F", "G", "H"],
        "t02_data_2": ["G", "F", "C", "B", "G", "F", "E", "SE", "H", "SW", "A", "NW", "NE", "D", "C", "B", "A",
                       "SW", "H", "G"],
    },
)

# Placement of the towns in the two-town networks: Town02 sits 205.6 m east of
# Town01's east edge, shifted north so the link road runs straight east-west.
PAPER_OFFSETS_M = {"town01": (0.0, 0.0), "town02": (600.0, 107.0)}

# paper_linked's cross-town vehicles: one loop through both towns, driven by
# one vehicle starting in Town01 and one starting in Town02. Nodes carry
# their town prefix; "t01_L"/"t02_L" are the link road's ends.
LINK_LOOP = [
    "t01_SE", "t01_L", "t02_L", "t02_A", "t02_B", "t02_G", "t02_H", "t02_SW", "t02_L",
    "t01_L", "t01_SE", "t01_S2", "t01_E1", "t01_W1", "t01_S1", "t01_S2", "t01_SE",
]
LINK_VEHICLES = {"link_data_0": ("town01", 0), "link_data_1": ("town02", 3)}  # (home town, start index)


@dataclass
class Plain:
    """A plain-XML network description: node and edge elements (ElementTree)."""

    nodes: list[ET.Element] = field(default_factory=list)
    edges: list[ET.Element] = field(default_factory=list)


# ---------------------------------------------------------------- descriptions


def read_town(town: Town) -> Plain:
    folder = SCENARIOS_DIR / town.name
    nodes = ET.parse(folder / f"{town.name}.nod.xml").getroot().findall("node")
    edges = ET.parse(folder / f"{town.name}.edg.xml").getroot().findall("edge")
    return Plain(nodes=list(nodes), edges=list(edges))


def placed(plain: Plain, prefix: str, dx_m: float, dy_m: float) -> Plain:
    """Copy of `plain` with ids prefixed by `prefix`_ and nodes shifted by (dx, dy)."""
    out = Plain()
    for node in plain.nodes:
        new = ET.Element("node", dict(node.attrib))
        new.set("id", f"{prefix}_{node.get('id')}")
        new.set("x", f"{float(node.get('x')) + dx_m:.2f}")
        new.set("y", f"{float(node.get('y')) + dy_m:.2f}")
        out.nodes.append(new)
    for edge in plain.edges:
        new = ET.Element("edge", dict(edge.attrib))
        for key in ("id", "from", "to"):
            new.set(key, f"{prefix}_{edge.get(key)}")
        out.edges.append(new)
    return out


def merged(*plains: Plain) -> Plain:
    return Plain(nodes=[n for p in plains for n in p.nodes], edges=[e for p in plains for e in p.edges])


def split_road(plain: Plain, a: str, b: str, mid: str, x_m: float, y_m: float) -> Plain:
    """Copy of `plain` where the two-way road a-b passes through a new signalised node `mid`."""
    out = Plain(nodes=list(plain.nodes), edges=[])
    out.nodes.append(ET.Element("node", {"id": mid, "x": f"{x_m:.2f}", "y": f"{y_m:.2f}", "type": "traffic_light"}))
    for edge in plain.edges:
        ends = (edge.get("from"), edge.get("to"))
        if ends in ((a, b), (b, a)):
            for start, end in ((ends[0], mid), (mid, ends[1])):
                out.edges.append(ET.Element("edge", {**edge.attrib, "id": edge_id(start, end), "from": start, "to": end}))
        else:
            out.edges.append(edge)
    return out


def edge_id(from_node: str, to_node: str) -> str:
    """Edge ids are FROM_TO; prefixed towns give t01_A_t01_B, shortened to t01_A_B."""
    prefix, sep, rest = to_node.partition("_")
    if sep and from_node.startswith(prefix + "_"):
        return f"{from_node}_{rest}"
    return f"{from_node}_{to_node}"


def with_link_road(plain: Plain) -> Plain:
    """paper_linked: split one outer road in each town and join the two new nodes."""
    out = plain
    for town in (TOWN01, TOWN02):
        dx_m, dy_m = PAPER_OFFSETS_M[town.name]
        mid, x_m, y_m, a, b = town.link_node
        p = town.prefix
        out = split_road(out, f"{p}_{a}", f"{p}_{b}", f"{p}_{mid}", x_m + dx_m, y_m + dy_m)
    a, b = f"{TOWN01.prefix}_{TOWN01.link_node[0]}", f"{TOWN02.prefix}_{TOWN02.link_node[0]}"
    out.edges.append(ET.Element("edge", {"id": f"link_{a}_{b}", "from": a, "to": b, "type": "street"}))
    out.edges.append(ET.Element("edge", {"id": f"link_{b}_{a}", "from": b, "to": a, "type": "street"}))
    return out


def arc(centre: tuple[float, float], radius_m: float, start: tuple[float, float], end: tuple[float, float],
        points: int) -> list[tuple[float, float]]:
    """`points` points on the shorter circular arc around `centre` from direction `start` to `end`."""
    a0, a1 = math.atan2(start[1], start[0]), math.atan2(end[1], end[0])
    sweep = (a1 - a0 + math.pi) % (2 * math.pi) - math.pi
    return [(centre[0] + radius_m * math.cos(a0 + sweep * k / (points - 1)),
             centre[1] + radius_m * math.sin(a0 + sweep * k / (points - 1))) for k in range(points)]


def corner_shape(corner: tuple[float, float], arm1: tuple[float, float], arm2: tuple[float, float],
                 radius_m: float, half_width_m: float) -> list[tuple[float, float]]:
    """Outline of a rounded 90-degree corner: the roads leave it `radius_m` from
    the node along unit directions arm1/arm2; the kerbs are arcs around the
    centre of the turn."""
    cx, cy = corner[0] + radius_m * (arm1[0] + arm2[0]), corner[1] + radius_m * (arm1[1] + arm2[1])
    # directions from the turn's centre to where the roads leave the corner: -arm2 and -arm1
    d1, d2 = (-arm2[0], -arm2[1]), (-arm1[0], -arm1[1])
    outer = arc((cx, cy), radius_m + half_width_m, d1, d2, 7)
    inner = arc((cx, cy), radius_m - half_width_m, d2, d1, 5)
    return outer + inner


def with_corner_shapes(plain: Plain, half_width_m: float) -> Plain:
    """Give every 2-way node with a `radius` an explicit rounded outline
    (half_width_m: half the road's width, i.e. one lane).

    netconvert ignores a node's radius where only two roads meet and would
    cut the roads 4 m from a corner (a 2 to 6 m turn); CARLA's corners turn
    on about 10 m. An explicit outline makes netconvert cut the roads where
    the curve starts and draw the internal lanes as the curve.
    """
    coords = {n.get("id"): (float(n.get("x")), float(n.get("y"))) for n in plain.nodes}
    arms: dict[str, set[str]] = {n: set() for n in coords}
    for edge in plain.edges:
        arms[edge.get("from")].add(edge.get("to"))
        arms[edge.get("to")].add(edge.get("from"))
    nodes = []
    for node in plain.nodes:
        nid = node.get("id")
        if node.get("radius") is None or len(arms[nid]) != 2:
            nodes.append(node)
            continue
        units = []
        for other in sorted(arms[nid]):
            dx, dy = coords[other][0] - coords[nid][0], coords[other][1] - coords[nid][1]
            units.append((dx / math.hypot(dx, dy), dy / math.hypot(dx, dy)))
        shape = corner_shape(coords[nid], units[0], units[1], float(node.get("radius")), half_width_m)
        new = ET.Element("node", dict(node.attrib))
        new.set("shape", " ".join(f"{x:.2f},{y:.2f}" for x, y in shape))
        nodes.append(new)
    return Plain(nodes=nodes, edges=list(plain.edges))


def lane_width_m() -> float:
    return float(ET.parse(TYPE_FILE).getroot().find("type").get("width"))


def write_plain(plain: Plain, folder: Path, stem: str) -> tuple[Path, Path]:
    nod, edg = folder / f"{stem}.nod.xml", folder / f"{stem}.edg.xml"
    for path, tag, elements in ((nod, "nodes", plain.nodes), (edg, "edges", plain.edges)):
        root = ET.Element(tag)
        root.extend(elements)
        ET.indent(root)
        ET.ElementTree(root).write(path, encoding="UTF-8", xml_declaration=True)
    return nod, edg


# ---------------------------------------------------------------- tools


def sumo_binary(name: str) -> str:
    """A SUMO binary (the package's lookup), or exit with the install hint."""
    try:
        return scenario_sumo_binary(name)
    except CrchflError as exc:
        sys.exit(str(exc))


def sumo_tool(name: str) -> str:
    """A script of SUMO's tools folder (the package's lookup), or exit with the install hint."""
    try:
        return sumo_tool_script(name)
    except CrchflError as exc:
        sys.exit(str(exc))


def run(cmd: list[str]) -> None:
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def replace_into(tmp: Path, dest: Path, note: str) -> None:
    """Move a finished SUMO output into place (temp file, then rename).

    SUMO's header comment (date, temporary paths) is replaced by `note`, so
    that the same inputs give byte-identical files.
    """
    text = tmp.read_text(encoding="utf-8")
    text = re.sub(r"<!-- generated on .*?-->", f"<!-- {note} -->", text, count=1, flags=re.DOTALL)
    write_text(dest, text)


def write_text(dest: Path, text: str) -> None:
    staging = dest.with_name(f".{dest.name}.tmp")
    staging.write_text(text, encoding="utf-8")
    os.replace(staging, dest)


def netconvert(nod: Path, edg: Path, out: Path) -> None:
    run([sumo_binary("netconvert"), "--node-files", str(nod), "--edge-files", str(edg),
         "--type-files", str(TYPE_FILE), "--no-warnings", "true", "--output-file", str(out),
         *(arg for key, value in NETCONVERT_OPTIONS.items() for arg in (f"--{key}", value))])


# ---------------------------------------------------------------- traffic

VTYPES_XML = f"""<?xml version="1.0" encoding="UTF-8"?>
<!-- Written by tools/build_nets.py. -->
<additional>
    <!-- background traffic: speeds spread around the limit, SUMO's default dawdling -->
    <vType id="background" vClass="passenger" speedFactor="normc(1.0,0.1,0.8,{BACKGROUND_MAX_SPEED_FACTOR})" color="0.6,0.6,0.6"/>
    <!-- named data / test vehicles: an expert driver that keeps to the limit, no dawdling -->
    <vType id="ego" vClass="passenger" speedFactor="1.0" sigma="0.0" color="1,0,0"/>
</additional>
"""


def loop_edges(net: sumolib.net.Net, nodes: list[str]) -> list[str]:
    """Edge ids along a closed node sequence (consecutive nodes share an edge)."""
    edges = []
    for a, b in zip(nodes, nodes[1:]):
        out = [e for e in net.getNode(a).getOutgoing() if e.getToNode().getID() == b]
        if len(out) != 1:
            raise ValueError(f"no single edge {a} -> {b}")
        edges.append(out[0].getID())
    return edges


def expand_splits(nodes: list[str], town: Town) -> list[str]:
    """Insert the link node where a loop drives along the road paper_linked splits."""
    mid, _, _, a, b = town.link_node
    p = town.prefix
    out = [nodes[0]]
    for u, v in zip(nodes, nodes[1:]):
        if {u, v} == {f"{p}_{a}", f"{p}_{b}"}:
            out.append(f"{p}_{mid}")
        out.append(v)
    return out


def ego_routes_xml(net: sumolib.net.Net, loops: dict[str, list[str]],
                   depart_pos_m: dict[str, float] | None = None) -> str:
    """Named vehicles, each on its own loop route repeated for EGO_DRIVE_S at the limit.

    depart_pos_m: where on its first edge a vehicle starts [m] (SUMO's default: its start).
    """
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<!-- Written by tools/build_nets.py. -->", "<routes>"]
    for vid, nodes in loops.items():
        edges = loop_edges(net, nodes)
        length_m = sum(net.getEdge(e).getLength() for e in edges)
        repeat = math.ceil(EGO_DRIVE_S * SPEED_LIMIT_MPS / length_m)
        lines.append(f'    <route id="{vid}_loop" edges="{" ".join(edges)}" repeat="{repeat}"/>')
    for vid in loops:
        pos = "" if depart_pos_m is None else f' departPos="{depart_pos_m[vid]:.2f}"'
        lines.append(f'    <vehicle id="{vid}" type="ego" route="{vid}_loop" depart="0.00"{pos} departSpeed="0"/>')
    lines.append("</routes>")
    return "\n".join(lines) + "\n"


def town_trips(town: Town, net_file: Path, vtypes: Path, work: Path) -> list[ET.Element]:
    """Background trips in the town's own frame (randomTrips.py, fixed seed)."""
    trips = work / f"{town.name}.trips.xml"
    period_s = 1.0
    # -r: with --intermediate randomTrips also routes the trips, by default into the current folder.
    run([sys.executable, sumo_tool("randomTrips.py"), "-n", str(net_file), "-a", str(vtypes), "-o", str(trips),
         "-r", str(work / f"{town.name}.unused.rou.xml"), "--seed", str(SEED), "--begin", "0", "--end", str(town.background_vehicles * period_s),
         "--period", str(period_s), "--length", "--intermediate", str(town.intermediate),
         "--prefix", f"{town.prefix}_bg_", "--random-departpos",
         "--trip-attributes", 'type="background" departSpeed="0"'])
    return ET.parse(trips).getroot().findall("trip")


def mapped_trips(trips: list[ET.Element], map_edge, prefix: str) -> list[ET.Element]:
    """Town-frame trips moved into a two-town network by `map_edge`."""
    out = []
    for trip in trips:
        new = ET.Element("trip", dict(trip.attrib))
        new.set("from", map_edge(trip.get("from"), "first"))
        if new.get("from") != f"{prefix}_{trip.get('from')}":
            new.set("departPos", "random")  # the start edge was split: the old position may not fit
        new.set("to", map_edge(trip.get("to"), "last"))
        if trip.get("via"):
            new.set("via", " ".join(map_edge(e, "first") for e in trip.get("via").split()))
        out.append(new)
    return out


def duarouter(net_file: Path, trips: list[ET.Element], vtypes: Path, out: Path, work: Path) -> None:
    trips_file = work / f"{out.stem}.trips.xml"
    root = ET.Element("routes")
    root.extend(sorted(trips, key=lambda t: float(t.get("depart"))))
    ET.indent(root)
    ET.ElementTree(root).write(trips_file, encoding="UTF-8", xml_declaration=True)
    run([sumo_binary("duarouter"), "-n", str(net_file), "--route-files", str(trips_file),
         "--additional-files", str(vtypes), "--vtype-output", str(work / "unused.vtypes.xml"),
         "--alternatives-output", str(work / "unused.alt.xml"), "--seed", str(SEED),
         "--no-step-log", "true", "--no-warnings", "true", "--output-file", str(out)])


def check_background_lengths(net_file: Path, routes: Path) -> None:
    net = sumolib.net.readNet(str(net_file))
    min_m = BACKGROUND_MIN_S * SPEED_LIMIT_MPS * BACKGROUND_MAX_SPEED_FACTOR
    for route in ET.parse(routes).getroot().iter("route"):
        length_m = sum(net.getEdge(e).getLength() for e in route.get("edges").split())
        if length_m < min_m:
            sys.exit(f"{routes}: a background route is {length_m:.0f} m < {min_m:.0f} m; raise 'intermediate'")


# ---------------------------------------------------------------- configuration


def sumocfg_xml(name: str) -> str:
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<!-- Written by tools/build_nets.py. Paths are relative to this file. -->
<configuration>
    <input>
        <net-file value="{name}.net.xml"/>
        <route-files value="{name}.ego.rou.xml,{name}.bg.rou.xml"/>
        <additional-files value="vtypes.add.xml"/>
    </input>
    <time>
        <step-length value="{STEP_LENGTH_S}"/>
    </time>
    <random_number>
        <seed value="{SEED}"/>
    </random_number>
</configuration>
"""


@dataclass(frozen=True)
class TownEntry:
    town: Town
    dx_m: float
    dy_m: float
    data_vehicles: list[str]
    test_vehicles: list[str]


def bbox_m(net: sumolib.net.Net, prefix: str | None) -> tuple[float, float, float, float]:
    xs, ys = [], []
    for node in net.getNodes():
        if prefix is None or node.getID().startswith(prefix + "_"):
            xs.append(node.getCoord()[0])
            ys.append(node.getCoord()[1])
    return min(xs), min(ys), max(xs), max(ys)


def scenario_toml(description: str, name: str, net: sumolib.net.Net, entries: list[TownEntry], prefixed: bool,
                  site_fractions: dict[str, tuple[tuple[str, float, float], ...]] | None = None) -> str:
    """scenario.toml: edge sites and towns.

    site_fractions: per town, (name suffix, x, y) of each of its sites as
    fractions of the town's box; default: one site at the town's centre.
    """
    def qlist(items: list[str]) -> str:
        return "[" + ", ".join(f'"{i}"' for i in items) + "]"

    lines = [
        "# Written by tools/build_nets.py. Coordinates in metres, in the network's frame.",
        f'description = "{description}"',
        f'sumocfg = "{name}.sumocfg"',
    ]
    boxes = [bbox_m(net, e.town.prefix if prefixed else None) for e in entries]
    for entry, box in zip(entries, boxes):
        # The paper's names: Edge01 serves Town01, Edge02 Town02.
        site = f'edge{entry.town.name.removeprefix("town")}'
        for suffix, fx, fy in (site_fractions or {}).get(entry.town.name, (("", 0.5, 0.5),)):
            lines += ["", "[[edge_sites]]", f'name = "{site}{suffix}"',
                      f"x_m = {box[0] + fx * (box[2] - box[0]):.2f}", f"y_m = {box[1] + fy * (box[3] - box[1]):.2f}",
                      "height_m = 10.0"]
    for entry, box in zip(entries, boxes):
        lines += ["", "[[towns]]", f'name = "{entry.town.name}"',
                  f"xmin_m = {box[0]:.2f}", f"ymin_m = {box[1]:.2f}", f"xmax_m = {box[2]:.2f}", f"ymax_m = {box[3]:.2f}",
                  f"data_vehicles = {qlist(entry.data_vehicles)}", f"test_vehicles = {qlist(entry.test_vehicles)}"]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- scale200

# scale200: 200 data vehicles, the federated clients of one run. One Town01
# holds about 80 vehicles before its short northern blocks lock up (measured
# on paper_linked's network: 80 data vehicles in Town01 drove 30 min without
# a teleport, 100 did not; docs/scenarios.md), so the scenario holds four
# copies of Town01 (2 x 2, 205.6 m apart as paper's towns, no
# roads between them), each with 50 data vehicles, its test vehicle and 10
# background vehicles: about 83 m of lane per vehicle.
SCALE_CLIENTS = 200  # the built-in scale scenario; --scale-clients builds a larger one elsewhere
SCALE_DESCRIPTION = "Four copies of Town01, 200 data vehicles (federated clients), eight edge sites"
SCALE_DATA_PER_TOWN = 50
SCALE_PITCH_M = (600.0, 534.2)  # between neighbouring copies, x and y
SCALE_BACKGROUND_PER_TOWN = 10  # the first 10 of Town01's background trips
# Two edge sites per town, at the centres of its west and east halves ((name
# suffix, x, y) as fractions of the town's box): the clients spread over 8
# cells and hand over between the halves.
SCALE_SITES = (("_w", 0.25, 0.5), ("_e", 0.75, 0.5))
START_GAP_M = 12.0  # named vehicles start at least this far apart on an edge (5 m car, 2.5 m gap, slack)
START_MIN_POS_M = 6.0  # and at least one car length from the edge's start
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0  # start offsets i * GOLDEN (mod 1) spread evenly along a loop


def scale_copies(clients: int) -> tuple[tuple[str, str, float, float], ...]:
    """(town name, id prefix, x offset, y offset [m]) of the Town01 copies that hold ``clients`` data
    vehicles, SCALE_DATA_PER_TOWN each, row by row on a near-square grid (scale200: 2 x 2)."""
    copies = math.ceil(clients / SCALE_DATA_PER_TOWN)
    if not 1 <= copies <= 26 or clients % SCALE_DATA_PER_TOWN:
        raise CrchflError(f"build_nets: --scale-clients {clients}: give a multiple of {SCALE_DATA_PER_TOWN} "
                          f"from {SCALE_DATA_PER_TOWN} to {26 * SCALE_DATA_PER_TOWN} (one to 26 copies of Town01)")
    columns = math.ceil(math.sqrt(copies))
    letters = "abcdefghijklmnopqrstuvwxyz"
    return tuple((f"town01{letters[i]}", f"t1{letters[i]}", SCALE_PITCH_M[0] * (i % columns),
                  SCALE_PITCH_M[1] * (i // columns)) for i in range(copies))


def scale_towns(copies: tuple[tuple[str, str, float, float], ...]) -> list[Town]:
    """The Town01 copies of a scale scenario, each with its data and test vehicles."""
    return [dataclasses.replace(TOWN01, name=name, prefix=prefix, loops={},
                                data_vehicles=[f"{prefix}_data_{i:02d}" for i in range(SCALE_DATA_PER_TOWN)],
                                test_vehicles=[f"{prefix}_test_0"])
            for name, prefix, _, _ in copies]


def simple_cycles(plain: Plain) -> list[list[str]]:
    """Every simple cycle of three or more nodes of a two-way road graph, in both
    directions, as closed node lists starting at their smallest node id; sorted."""
    adjacent: dict[str, set[str]] = {n.get("id"): set() for n in plain.nodes}
    for edge in plain.edges:
        adjacent[edge.get("from")].add(edge.get("to"))
    found = []

    def walk(path: list[str]) -> None:
        for nxt in sorted(adjacent[path[-1]]):
            if nxt == path[0] and len(path) >= 3:
                found.append(path + [nxt])
            elif nxt > path[0] and nxt not in path:
                walk(path + [nxt])

    for start in sorted(adjacent):
        walk([start])
    return sorted(found, key=lambda c: (len(c), c))


def signal_turns(net: sumolib.net.Net, edges: list[str]) -> set[str]:
    """Turn directions ('l', 'r', 's') a closed loop of edges takes at signalised junctions."""
    out = set()
    for a, b in zip(edges, edges[1:] + edges[:1]):
        if net.getEdge(a).getToNode().getType() == "traffic_light":
            (conn,) = net.getEdge(a).getConnections(net.getEdge(b))
            out.add(conn.getDirection())
    return out


def town_loops(net: sumolib.net.Net, prefix: str, plain: Plain) -> list[list[str]]:
    """The town's simple loops (node ids prefixed) that turn both left and right at signals."""
    loops = []
    for nodes in simple_cycles(plain):
        nodes = [f"{prefix}_{n}" for n in nodes]
        if {"l", "r"} <= signal_turns(net, loop_edges(net, nodes)):
            loops.append(nodes)
    return loops


def evenly(items: list, n: int) -> list:
    """n items spread evenly over the list (each about n / len(items) times when n is larger)."""
    return [items[i * len(items) // n] for i in range(n)]


def started_at(loop: list[str], start: int) -> list[str]:
    """A closed node list rotated to start at its node `start` (index into the open list)."""
    body = loop[:-1]
    return body[start:] + body[:start] + [body[start]]


def start_on_loop(net: sumolib.net.Net, loop: list[str], fraction: float,
                  occupied: dict[str, list[float]]) -> tuple[list[str], float]:
    """Where a vehicle starts on a closed loop: the first free point at or after
    `fraction` of the loop's length.

    Returns the loop rotated to start with that point's edge and the position
    on it [m]; `occupied` (edge -> start positions) receives it.
    """
    edges = loop_edges(net, loop)
    lengths = [net.getEdge(e).getLength() for e in edges]
    total_m = sum(lengths)
    offset_m = fraction * total_m
    for _ in range(math.ceil(total_m)):
        k, pos = 0, offset_m % total_m
        while pos > lengths[k]:
            pos -= lengths[k]
            k += 1
        if (START_MIN_POS_M <= pos <= lengths[k] - 1.0
                and all(abs(pos - other) >= START_GAP_M for other in occupied.get(edges[k], []))):
            occupied.setdefault(edges[k], []).append(pos)
            return started_at(loop, k), pos
        offset_m += 1.0
    raise ValueError(f"no free start on the loop {loop}")


def copied_trips(trips: list[ET.Element], prefix: str) -> list[ET.Element]:
    """Town01 trips (ids t01_bg_N) moved into the copy whose ids start with `prefix`_."""
    out = mapped_trips(trips, lambda edge, _: f"{prefix}_{edge}", prefix)
    for trip in out:
        trip.set("id", f"{prefix}_{trip.get('id').removeprefix(TOWN01.prefix + '_')}")
    return out


def scale_routes_xml(net: sumolib.net.Net, plain: Plain, towns: list[Town]) -> str:
    """scale200's named vehicles, all starting at once: in each town its test
    vehicle on Town01's test loop, and each data vehicle on one of the town's
    loops, spread along it (start offsets by the golden ratio).

    The data vehicles of all towns together take every loop shape: the shapes
    are spread evenly over all of them, and town k takes every len(towns)-th
    from the k-th on.
    """
    routes: dict[str, list[str]] = {}
    depart_pos_m: dict[str, float] = {}
    occupied: dict[str, list[float]] = {}
    count = len(town_loops(net, towns[0].prefix, plain))
    shapes = evenly(list(range(count)), sum(len(t.data_vehicles) for t in towns))
    i = 0  # vehicle number across towns: its start offset
    for k, town in enumerate(towns):
        (vid,) = town.test_vehicles
        test_loop = [f"{town.prefix}_{n}" for n in TOWN01.loops["t01_test_0"]]
        routes[vid], depart_pos_m[vid] = start_on_loop(net, test_loop, 0.0, occupied)
        own = town_loops(net, town.prefix, plain)
        loops = [own[j] for j in shapes[k::len(towns)]]
        for vid, loop in zip(town.data_vehicles, loops):
            routes[vid], depart_pos_m[vid] = start_on_loop(net, loop, (i * GOLDEN) % 1.0, occupied)
            i += 1
    return ego_routes_xml(net, routes, depart_pos_m)


# ---------------------------------------------------------------- scenarios


# ---------------------------------------------------------------- signal offsets


# Each signalised junction's offset into the 90 s cycle [s], by town and junction id. Chosen by
# tools/signal_offsets.py (a seeded random search refined by coordinate descent, scored by how long the
# named vehicles of `paper` stand on SUMO seeds 1 and 2): with every offset 0 they stood in 43 % (Town01)
# and 33 % (Town02) of their samples on seed 0, with these offsets in 20 % and 18 % (docs/scenarios.md).
# paper_linked's link junctions (L), which no data set vehicle of `paper` passes, keep offset 0.
SIGNAL_OFFSETS_S = {
    "town01": {"E1": 5, "E2": 70, "E3": 55, "M3": 35, "N1": 37, "N2": 55, "N3": 85, "S1": 56, "S2": 77,
               "W1": 0, "W2": 54, "W3": 71},
    "town02": {"A": 40, "B": 5, "C": 35, "D": 8, "E": 0, "F": 60, "G": 13, "H": 30},
}


def signal_offset_s(tls_id: str) -> int:
    """Offset of a built network's signal: by its town (from the id prefix) and its junction id there."""
    prefix, sep, node = tls_id.partition("_")
    copies = scale_copies(26 * SCALE_DATA_PER_TOWN)  # every prefix a scale scenario may use
    towns = {TOWN01.prefix: TOWN01, TOWN02.prefix: TOWN02, **{p: TOWN01 for _, p, _, _ in copies}}
    if sep and prefix in towns:
        town = towns[prefix]
        offsets = {**SIGNAL_OFFSETS_S[town.name], town.link_node[0]: 0}
    else:  # a single town's network: junction ids unprefixed, unique across the two towns
        node = tls_id
        offsets = {k: v for table in SIGNAL_OFFSETS_S.values() for k, v in table.items()}
    if node not in offsets:
        raise CrchflError(f"build_nets: no signal offset for traffic light '{tls_id}'; add it to SIGNAL_OFFSETS_S")
    return offsets[node]


def with_signal_offsets(net_xml: str) -> str:
    """netconvert's network with each static signal program's offset set by ``signal_offset_s``."""
    def offset(match: re.Match) -> str:
        return f'{match.group(1)}offset="{signal_offset_s(match.group(2))}"'

    pattern = r'(<tlLogic id="([^"]+)" type="static" programID="0" )offset="0"'
    text, count = re.subn(pattern, offset, net_xml)
    if count != net_xml.count("<tlLogic "):
        raise CrchflError("build_nets: a signal program is not netconvert's static program 0 with offset 0")
    return text


def build_scenario(name: str, description: str, plain: Plain, named_routes: Callable[[sumolib.net.Net], str],
                   trips: list[ET.Element], entries: list[TownEntry], prefixed: bool, work: Path, out_root: Path,
                   site_fractions: dict[str, tuple[tuple[str, float, float], ...]] | None = None) -> None:
    """Build one scenario folder; named_routes(net) gives the named vehicles' route file."""
    folder = out_root / name
    folder.mkdir(parents=True, exist_ok=True)
    nod, edg = write_plain(with_corner_shapes(plain, lane_width_m()), work, name)
    net_tmp = work / f"{name}.net.xml"
    netconvert(nod, edg, net_tmp)
    net_tmp.write_text(with_signal_offsets(net_tmp.read_text(encoding="utf-8")), encoding="utf-8")
    net = sumolib.net.readNet(str(net_tmp))

    vtypes = folder / "vtypes.add.xml"
    write_text(vtypes, VTYPES_XML)
    ego_tmp = work / f"{name}.ego.rou.xml"
    ego_tmp.write_text(named_routes(net), encoding="utf-8")
    bg_tmp = work / f"{name}.bg.rou.xml"
    duarouter(net_tmp, trips, vtypes, bg_tmp, work)
    check_background_lengths(net_tmp, bg_tmp)

    replace_into(net_tmp, folder / f"{name}.net.xml",
                 "Written by tools/build_nets.py: netconvert with "
                 + ", ".join(f"{key}={value}" for key, value in NETCONVERT_OPTIONS.items()))
    replace_into(ego_tmp, folder / f"{name}.ego.rou.xml", "Written by tools/build_nets.py")
    replace_into(bg_tmp, folder / f"{name}.bg.rou.xml",
                 f"Written by tools/build_nets.py: randomTrips.py with seed {SEED}, then duarouter")
    write_text(folder / f"{name}.sumocfg", sumocfg_xml(name))
    write_text(folder / "scenario.toml", scenario_toml(description, name, net, entries, prefixed, site_fractions))


def build_all(out_root: Path = SCENARIOS_DIR) -> None:
    """Build every built-in scenario into out_root/<name>/ (the package's folder by default)."""
    with tempfile.TemporaryDirectory(prefix="build_nets_") as tmp:
        work = Path(tmp)
        towns = (TOWN01, TOWN02)
        plains = {t.name: read_town(t) for t in towns}
        trips: dict[str, list[ET.Element]] = {}
        vtypes = work / "vtypes.add.xml"
        vtypes.write_text(VTYPES_XML, encoding="utf-8")

        for town in towns:
            net_file = work / f"{town.name}.plain.net.xml"
            netconvert(*write_plain(with_corner_shapes(plains[town.name], lane_width_m()), work, f"{town.name}.plain"),
                       net_file)
            trips[town.name] = town_trips(town, net_file, vtypes, work)
            entry = TownEntry(town, 0.0, 0.0, town.data_vehicles, town.test_vehicles)
            build_scenario(town.name, f"CARLA {town.name.capitalize()} modelled in SUMO, one edge server at its centre",
                           plains[town.name], lambda net, loops=town.loops: ego_routes_xml(net, loops), trips[town.name],
                           [entry], prefixed=False, work=work, out_root=out_root)

        def prefixed_routes(town: Town, linked: bool) -> dict[str, list[str]]:
            """Each named vehicle's node sequence in the paper scenarios: its walk, else its loop."""
            out = {}
            for vid, nodes in town.loops.items():
                nodes = [f"{town.prefix}_{n}" for n in town.paper_walks.get(vid, nodes)]
                out[vid] = expand_splits(nodes, town) if linked else nodes
            return out

        def edge_mapper(town: Town, linked: bool):
            mid, _, _, a, b = town.link_node

            def map_edge(edge: str, role: str) -> str:
                u, v = edge.split("_")
                if linked and {u, v} == {a, b}:
                    # the road is split: a trip may start on its first half and end on its last
                    u, v = (u, mid) if role == "first" else (mid, v)
                return f"{town.prefix}_{u}_{v}"

            return map_edge

        for name, linked in (("paper", False), ("paper_linked", True)):
            placed_towns = [placed(plains[t.name], t.prefix, *PAPER_OFFSETS_M[t.name]) for t in towns]
            plain = merged(*placed_towns)
            loops = {vid: nodes for t in towns for vid, nodes in prefixed_routes(t, linked).items()}
            all_trips = [trip for t in towns for trip in mapped_trips(trips[t.name], edge_mapper(t, linked), t.prefix)]
            data = {t.name: list(t.data_vehicles) for t in towns}
            if linked:
                plain = with_link_road(plain)
                for vid, (home, start) in LINK_VEHICLES.items():
                    rotated = LINK_LOOP[start:-1] + LINK_LOOP[:start] + [LINK_LOOP[start]]
                    loops[vid] = rotated
                    data[home].append(vid)
                description = "Town01 and Town02 joined by a two-way road; link vehicles drive between them"
            else:
                description = "Town01 and Town02 side by side in one network, no road between them"
            entries = [TownEntry(t, *PAPER_OFFSETS_M[t.name], data[t.name], t.test_vehicles) for t in towns]
            build_scenario(name, description, plain, lambda net, loops=loops: ego_routes_xml(net, loops), all_trips,
                           entries, prefixed=True, work=work, out_root=out_root)

        build_scale(SCALE_CLIENTS, plains["town01"], trips["town01"], work, out_root)


def build_scale(clients: int, town01: Plain, town01_trips: list[ET.Element], work: Path, out_root: Path) -> None:
    """The scale scenario of ``clients`` data vehicles, scale<clients>, into out_root."""
    layout = scale_copies(clients)
    towns01 = scale_towns(layout)
    copies = [placed(town01, t.prefix, dx, dy) for t, (_, _, dx, dy) in zip(towns01, layout)]
    background = town01_trips[:SCALE_BACKGROUND_PER_TOWN]
    copy_trips = [trip for t in towns01 for trip in copied_trips(background, t.prefix)]
    entries = [TownEntry(t, dx, dy, t.data_vehicles, t.test_vehicles) for t, (_, _, dx, dy) in zip(towns01, layout)]
    description = SCALE_DESCRIPTION if clients == SCALE_CLIENTS else (
        f"{len(layout)} copies of Town01, {clients} data vehicles (federated clients), {2 * len(layout)} edge sites")
    build_scenario(f"scale{clients}", description, merged(*copies),
                   lambda net: scale_routes_xml(net, town01, towns01), copy_trips,
                   entries, prefixed=True, work=work, out_root=out_root,
                   site_fractions={t.name: SCALE_SITES for t in towns01})


def build_scale_only(clients: int, out_root: Path) -> None:
    """Only the scale scenario of ``clients`` data vehicles (a benchmark's larger federation)."""
    with tempfile.TemporaryDirectory(prefix="build_nets_") as tmp:
        work = Path(tmp)
        (work / "vtypes.add.xml").write_text(VTYPES_XML, encoding="utf-8")
        plain = read_town(TOWN01)
        net_file = work / "town01.plain.net.xml"
        netconvert(*write_plain(with_corner_shapes(plain, lane_width_m()), work, "town01.plain"), net_file)
        build_scale(clients, plain, town_trips(TOWN01, net_file, work / "vtypes.add.xml", work), work, out_root)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=SCENARIOS_DIR,
                        help="folder to write the scenario folders into (default: the repository's scenarios/)")
    parser.add_argument("--scale-clients", type=int, metavar="N",
                        help=f"build only scale<N>: N data vehicles in N/{SCALE_DATA_PER_TOWN} copies of Town01")
    args = parser.parse_args(argv)
    if args.scale_clients is not None:
        build_scale_only(args.scale_clients, args.out)
    else:
        build_all(args.out)


if __name__ == "__main__":
    main()
