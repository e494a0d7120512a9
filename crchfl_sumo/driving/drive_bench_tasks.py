"""The benchmark's tasks: suites of start/goal routes drawn from a network, as in CARLA's CoRL2017 benchmark.

Every ordered pair of edges (start, goal) of the network is joined by its
shortest path (sumolib, by length; on a network of more than
ALL_PAIRS_MAX_EDGES edges, bounded searches from sampled starts); the route is classified by its number of
turns (junctions passed with SUMO link direction left or right, the towns'
rounded ring corners included: CoRL2017 calls its task "one curve"). Routes
that the data vehicles drove are left out (``data_routes``), so the benchmark
never replays a stretch of road exactly as the training data saw it. Each
suite then draws its episodes by seed from its candidates.

docs/drive.md describes the suites, the exclusion and the time limit.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import logging
import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import sumolib

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.route import GREEN_LETTERS, Crossing, RouteGeometry, point_at, read_net, route_geometry
from crchfl_sumo.sumo.scenario import Scenario
from crchfl_sumo.sumo.turns import HEADING_CHORD_M

log = logging.getLogger(__name__)

DEFAULT_TOWNS = ("town01", "town02")  # where the benchmark drives unless told otherwise

TURN_DIRECTIONS = ("l", "r", "L", "R")  # SUMO link directions that need the wheel turned
U_TURN_DIRECTIONS = ("t", "T")  # routes with a U-turn are not drawn (the towns have none)
# Nor are routes that turn back through a junction SUMO does not call a U-turn: the end of a dual carriageway,
# where one carriageway's edge meets the other's (A10KW: links 's', 'l' and 'R' that turn 146 to 179 degrees,
# tighter than the car's lock). The towns turn at most 90 degrees, A10KW's and DRT's other links at most 127.
U_TURN_MIN_RAD = math.radians(135.0)
# A signal that holds a link red for longer than a drive may stand still (drive_bench.STUCK_S) ends a drive that
# obeys it stuck: such routes are not drawn. A10KW's signals are the SUMO game's, switched by its player: their
# phases last 10000 s. The towns' longest red is 50 s.
MAX_RED_S = 90.0
# CoRL2017's time budget (CARLA driving-benchmarks, calculate_time_out): the route at
# 10 km/h plus 10 s. Added here: each signal on the route may hold the ego for its
# longest red, which the towns' in-phase signals make up to 47 s.
TIME_BUDGET_SPEED_MPS = 10.0 / 3.6
TIME_BUDGET_EXTRA_S = 10.0


@dataclass(frozen=True)
class Task:
    """One suite: which routes it draws (by number of turns) and whether the town's traffic runs."""

    name: str
    min_turns: int
    max_turns: int  # inclusive; a large number for "several"
    traffic: bool
    routes_of: str = ""  # draw the same routes as this task (CoRL2017: navigation with and without traffic)


TASKS = (
    Task("straight", 0, 0, traffic=False),
    Task("one_turn", 1, 1, traffic=False),
    Task("navigation", 2, 1_000, traffic=False),
    Task("navigation_traffic", 2, 1_000, traffic=True, routes_of="navigation"),
)
TASK_NAMES = tuple(t.name for t in TASKS)


@dataclass(frozen=True)
class TaskConfig:
    """How routes are drawn.

    max_route_m      longest route drawn [m] (keeps an episode within a few simulated minutes)
    min_route_m      shortest route drawn [m] (0: any; a city's short links make trivial episodes)
    navigation_turns the turns a navigation route has, (fewest, most); straight routes have none,
                     one-turn routes one (CoRL2017's suites)
    warmup_range_s   each episode's warm-up is drawn from this range: traffic gets moving, and
                     a range wider than a signal cycle (90 s in the towns) lets the ego meet
                     every phase of the lights
    """

    max_route_m: float = 600.0
    min_route_m: float = 0.0
    navigation_turns: tuple[int, int] = (2, 1_000)
    warmup_range_s: tuple[float, float] = (20.0, 110.0)

    def __post_init__(self) -> None:
        if not self.max_route_m > 0:
            raise CrchflError(f"bench.max_route_m must be > 0, got {self.max_route_m}")
        if not 0 <= self.min_route_m < self.max_route_m:
            raise CrchflError(
                f"bench.min_route_m must lie in [0, max_route_m = {self.max_route_m:g}), got {self.min_route_m}"
            )
        fewest, most = self.navigation_turns
        if not 2 <= fewest <= most:
            raise CrchflError(
                f"bench.navigation_turns must be (fewest, most) with 2 <= fewest <= most, got {self.navigation_turns}"
            )
        low, high = self.warmup_range_s
        if not 0 <= low <= high:
            raise CrchflError(f"bench.warmup_range_s must be (low, high) with 0 <= low <= high, got {self.warmup_range_s}")

    def turns(self, task: Task) -> tuple[int, int]:
        """(fewest, most) turns of ``task``'s routes: its own, the navigation suites' from this config."""
        if task.name in ("navigation", "navigation_traffic"):
            return self.navigation_turns
        return task.min_turns, task.max_turns


@dataclass(frozen=True)
class Candidate:
    """A route between two edges of the network."""

    edges: tuple[str, ...]
    length_m: float
    turns: int
    time_limit_s: float


@dataclass(frozen=True)
class Episode:
    """One drive of the benchmark: the route, its time limit and the episode's own random draws."""

    town: str
    task: str
    index: int
    edges: tuple[str, ...]
    length_m: float
    turns: int
    time_limit_s: float
    sumo_seed: int
    warmup_s: float


def task_by_name(name: str) -> Task:
    for task in TASKS:
        if task.name == name:
            return task
    raise CrchflError(f"--tasks: unknown task '{name}'; choose from {', '.join(TASK_NAMES)}")


def count_turns(route: RouteGeometry) -> int:
    """Junctions the route passes turning left or right."""
    return sum(c.direction in TURN_DIRECTIONS for c in route.crossings)


# --- the routes of the training data ---------------------------------------------------------------


def listed_files(scenario: Scenario, option: str) -> list[Path]:
    """The files of a file-list ``option`` (--route-files, --additional-files) a scenario's SUMO loads."""
    files = []
    for given in scenario.sumo_options:
        if given.startswith(option + "="):
            files += [Path(f) for f in given.split("=", 1)[1].split(",") if f]
    return files


def route_files(scenario: Scenario) -> list[Path]:
    """The route files a scenario's SUMO loads."""
    return listed_files(scenario, "--route-files")


def data_routes(scenario: Scenario) -> list[tuple[str, ...]]:
    """The edge lists of the scenario's data vehicles (scenario.toml ``data_vehicles``) in its route files."""
    wanted = {v for town in scenario.towns for v in town.data_vehicles}
    found: dict[str, tuple[str, ...]] = {}
    for path in route_files(scenario):
        named = {r.id: tuple(r.edges.split()) for r in _elements(path, "route") if r.hasAttribute("id")}
        for vehicle in _elements(path, "vehicle"):
            if vehicle.id not in wanted:
                continue
            if vehicle.hasChild("route"):  # its own route, inside it
                found[vehicle.id] = tuple(vehicle.getChild("route")[0].getAttributeSecure("edges", "").split())
            else:
                found[vehicle.id] = named.get(vehicle.getAttributeSecure("route", ""), ())
    return [found[v] for v in sorted(found)]


def _elements(path: Path, name: str):
    """The ``name`` elements of a SUMO XML file, plain or gzipped, as sumolib's compound objects."""
    with sumolib.openz(str(path), "rb") as source:
        yield from sumolib.xml.parse(source, name)


def drives_stretch_of(edges: Sequence[str], data_route: Sequence[str]) -> bool:
    """Whether ``edges`` is a contiguous stretch of ``data_route`` driven round and round (the data loops repeat)."""
    n, k = len(data_route), len(edges)
    if n == 0 or k == 0:
        return False
    lap = list(data_route) * (k // n + 2)
    return any(lap[i : i + k] == list(edges) for i in range(n))


def apart_from_data(edges: Sequence[str], routes: Sequence[Sequence[str]]) -> bool:
    """A route is apart from the training data when no data vehicle started on its first edge or drove it whole."""
    return all(edges[0] != r[0] and not drives_stretch_of(edges, r) for r in routes if r)


# --- signals and the time limit ---------------------------------------------------------------------


def longest_waits_s(net_path: Path, additional_files: Sequence[Path] = ()) -> dict[tuple[str, int], float]:
    """(signal id, link index) -> the longest time the link's signal is not green in its cycle [s].

    Read from the program each signal runs: SUMO starts the last tlLogic it loads for a signal, from the network
    and then the additional files in order (bs3d's net holds four programs of its game signal; the first gives
    green to links that the fourth, the one SUMO runs, holds red for 1006 s). The cycle wraps round, so a red at
    the end joins one at the start.
    """
    programs = {}
    for path in (net_path, *additional_files):
        programs.update((element.id, element) for element in _elements(path, "tlLogic"))
    waits: dict[tuple[str, int], float] = {}
    for element in programs.values():
        children = element.getChild("phase") if element.hasChild("phase") else []
        phases = [(float(p.duration), p.getAttributeSecure("state", "")) for p in children]
        links = max((len(state) for _, state in phases), default=0)
        cycle = sum(d for d, _ in phases)
        for link in range(links):
            stopped = [(d, link < len(s) and s[link] not in GREEN_LETTERS) for d, s in phases]
            if all(stop for _, stop in stopped):
                waits[(element.id, link)] = cycle
                continue
            longest = run = 0.0
            for duration, stop in stopped + stopped:  # twice round: runs across the cycle's end
                run = run + duration if stop else 0.0
                longest = max(longest, run)
            waits[(element.id, link)] = min(longest, cycle)
    return waits


def crossing_turn_rad(route: RouteGeometry, crossing: Crossing) -> float:
    """How far the route turns through a crossing: its direction over HEADING_CHORD_M after the junction minus that
    over HEADING_CHORD_M before the stop line, wrapped to [-pi, pi], left positive."""
    def chord_rad(a_m: float, b_m: float) -> float:
        (xa, ya, _), (xb, yb, _) = point_at(route, a_m), point_at(route, b_m)
        return math.atan2(yb - ya, xb - xa)

    turn = chord_rad(crossing.s_end_m, crossing.s_end_m + HEADING_CHORD_M) - chord_rad(
        crossing.s_start_m - HEADING_CHORD_M, crossing.s_start_m
    )
    return math.remainder(turn, 2.0 * math.pi)


def queue_edges(net, waits: dict[tuple[str, int], float]) -> set[str]:
    """Edges from which every way on (for passenger cars) waits at a link red for longer than MAX_RED_S, at once or
    after more such edges, and edges each of whose lanes has such a link: the traffic queues there and the queue
    only grows (A10KW: the game's red spills back over 200 m of two edges a route may end on, and the ego waited
    in it until it ended stuck; bs3d: the cars for a red link stand at the head of a lane whose other link is
    green, and the ego stood behind them)."""
    def red(connection) -> bool:
        return waits.get((connection.getTLSID(), connection.getTLLinkIndex()), 0.0) > MAX_RED_S

    def blocked(edge) -> bool:
        ways = [(to, c) for to, connections in edge.getOutgoing().items() if to.allows("passenger") for c in connections]
        lanes = [lane for lane in edge.getLanes() if lane.allows("passenger")]
        return (bool(ways) and all(to.getID() in found or red(c) for to, c in ways)) or (
            bool(lanes) and all(any(red(c) for c in lane.getOutgoing() if c.getTo().allows("passenger")) for lane in lanes)
        )

    found: set[str] = set()
    pending = list(net.getEdges(withInternal=False))
    while pending:  # an edge found blocked may block the edges leading to it
        edge = pending.pop()
        if edge.getID() not in found and blocked(edge):
            found.add(edge.getID())
            pending += [e for e in edge.getIncoming() if e.getFunction() != "internal"]
    return found


def drawable(route: RouteGeometry, waits: dict[tuple[str, int], float], queues: set[str] = frozenset()) -> bool:
    """No U-turn (SUMO's, or a turn through a junction of more than U_TURN_MIN_RAD), no link red for longer
    than MAX_RED_S and no edge of ``queues`` (queue_edges)."""
    return not any(e in queues for e in route.edges) and not any(
        c.direction in U_TURN_DIRECTIONS
        or abs(crossing_turn_rad(route, c)) > U_TURN_MIN_RAD
        or waits.get((c.tls_id, c.link_index), 0.0) > MAX_RED_S
        for c in route.crossings
    )


def time_limit_s(route: RouteGeometry, waits: dict[tuple[str, int], float]) -> float:
    """CoRL2017's budget (the route at 10 km/h + 10 s) plus the longest red of each signal passed."""
    held = sum(waits.get((c.tls_id, c.link_index), 0.0) for c in route.crossings if c.tls_id)
    return route.length_m / TIME_BUDGET_SPEED_MPS + TIME_BUDGET_EXTRA_S + held


# --- drawing the episodes -----------------------------------------------------------------------------


# Up to this many edges every ordered pair is joined (the towns: their candidates exactly as before);
# a larger network's routes come from bounded searches from BOUNDED_STARTS sampled start edges, each
# keeping at most BOUNDED_GOALS goals: quadratic in the edges would take hours on a city.
ALL_PAIRS_MAX_EDGES = 400
BOUNDED_STARTS = 300
BOUNDED_GOALS = 12


def shortest_paths_from(start, max_length_m: float) -> dict[str, tuple]:
    """Shortest paths (by edge length, passenger class) from ``start`` to every edge whose path is at
    most ``max_length_m`` long, start included: goal id -> edges. Dijkstra cut at the bound."""
    best = {start.getID(): start.getLength()}
    previous: dict[str, Any] = {start.getID(): None}
    by_id = {start.getID(): start}
    heap = [(start.getLength(), start.getID())]
    while heap:
        length, edge_id = heapq.heappop(heap)
        if length > best[edge_id]:
            continue
        for after in sorted(by_id[edge_id].getOutgoing(), key=lambda e: e.getID()):
            if not after.allows("passenger"):
                continue
            total = length + after.getLength()
            if total <= max_length_m and total < best.get(after.getID(), float("inf")):
                best[after.getID()], previous[after.getID()], by_id[after.getID()] = total, edge_id, after
                heapq.heappush(heap, (total, after.getID()))
    paths = {}
    for goal in best:
        chain, at = [], goal
        while at is not None:
            chain.append(by_id[at])
            at = previous[at]
        paths[goal] = tuple(reversed(chain))
    return paths


def _pairs(edges: list, config: TaskConfig, town: str):
    """(start, goal, path) to try: every ordered pair of a small network, bounded searches on a large one."""
    if len(edges) <= ALL_PAIRS_MAX_EDGES:
        for start, goal in itertools.permutations(edges, 2):
            yield start, goal, None
        return
    rng = np.random.default_rng(zlib.crc32(town.encode()))  # the same candidates for the town whatever the draw
    for i in sorted(rng.choice(len(edges), size=min(BOUNDED_STARTS, len(edges)), replace=False)):
        paths = shortest_paths_from(edges[i], config.max_route_m)
        goals = sorted(g for g in paths if g != edges[i].getID())
        for g in sorted(rng.choice(len(goals), size=min(BOUNDED_GOALS, len(goals)), replace=False)):
            path = paths[goals[g]]
            yield path[0], path[-1], path


def candidate_routes(scenario: Scenario, config: TaskConfig = TaskConfig()) -> list[Candidate]:
    """Shortest routes between two edges of the network, apart from the data routes, up to the longest length:
    every ordered pair of a network of at most ALL_PAIRS_MAX_EDGES edges, else bounded searches from
    sampled starts (the same for a town whatever the benchmark's seed)."""
    net_path = Path(scenario.net_path)
    net = read_net(net_path)
    waits = longest_waits_s(net_path, listed_files(scenario, "--additional-files"))
    queues = queue_edges(net, waits)
    excluded = data_routes(scenario)
    candidates = []
    edges = sorted((e for e in net.getEdges(withInternal=False) if e.allows("passenger")), key=lambda e: e.getID())
    for start, goal, path in _pairs(edges, config, scenario.name):
        if path is None:
            path, _ = net.getShortestPath(start, goal, vClass="passenger")
        if path is None:
            continue
        ids = tuple(e.getID() for e in path)
        if not apart_from_data(ids, excluded):
            continue
        geometry = route_geometry(net, ids)  # a shortest path's edges connect; lane changes are planned
        if not config.min_route_m <= geometry.length_m <= config.max_route_m or not drawable(geometry, waits, queues):
            continue
        candidates.append(Candidate(ids, geometry.length_m, count_turns(geometry), time_limit_s(geometry, waits)))
    return candidates


def draw_episodes(
    scenario: Scenario,
    tasks: Sequence[Task],
    episodes: int,
    seed: int,
    config: TaskConfig = TaskConfig(),
) -> list[Episode]:
    """``episodes`` episodes per task, drawn from the candidates by ``seed`` (the same seed, the same episodes).

    Each task draws its routes without replacement (and round again when it
    needs more episodes than it has routes), and per episode a SUMO seed and a
    warm-up. The draws depend only on (seed, town, task), so a task with
    ``routes_of`` gets exactly that task's routes, seeds and warm-ups.
    """
    town = scenario.name
    candidates = candidate_routes(scenario, config)
    out = []
    for task in tasks:
        source = task_by_name(task.routes_of) if task.routes_of else task
        fewest, most = config.turns(source)
        pool = sorted((c for c in candidates if fewest <= c.turns <= most), key=lambda c: c.edges)
        if not pool:  # the rest of the benchmark runs; drive_bench.run_benchmark lists the task as skipped
            log.warning(
                "town '%s' has no route for task '%s' (%d to %d turns, at most %g m, apart from the data vehicles' "
                "routes): skipped", town, task.name, fewest, most, config.max_route_m,
            )
            continue
        rng = np.random.default_rng([seed, zlib.crc32(town.encode()), zlib.crc32(source.name.encode())])
        order = rng.permutation(len(pool))
        low, high = config.warmup_range_s
        for i in range(episodes):
            c = pool[order[i % len(pool)]]
            out.append(
                Episode(
                    town=town, task=task.name, index=i, edges=c.edges, length_m=c.length_m, turns=c.turns,
                    time_limit_s=c.time_limit_s, sumo_seed=int(rng.integers(0, 2**31 - 1)),
                    warmup_s=round(float(rng.uniform(low, high)), 2),
                )
            )
    return out


def without_traffic(scenario: Scenario) -> Scenario:
    """The scenario with none of its route files and none of the vehicles it adds itself: no vehicle but the ego
    (vehicle types stay in the additionals)."""
    options = tuple(o for o in scenario.sumo_options if not o.startswith("--route-files="))
    return dataclasses.replace(scenario, sumo_options=options, injected=())
