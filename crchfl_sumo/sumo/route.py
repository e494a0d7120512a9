"""A planned route as geometry: the lane centre line through its junctions, the crossings
with their signals, and where the road surface is. Read from the network with sumolib.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError

RED_LETTERS = ("r", "u")  # SUMO red and red-yellow: crossing the stop line on either is a violation
YELLOW_LETTERS = ("y", "Y")
GREEN_LETTERS = ("g", "G")


# --- the planned route as geometry ---------------------------------------------------------


@dataclass(frozen=True)
class Crossing:
    """One junction on the route: its stop line, its end, and the link driven through it.

    s_start_m  arc position of the stop line (end of the incoming lane) on the route
    s_end_m    arc position where the route leaves the junction
    tls_id     signal controlling the link ('' at an unsignalised junction)
    link_index index of the link in the signal's state string (-1 if none)
    direction  SUMO link direction: s straight, l left, r right, t turn (L/R partly)
    s_internal_stop_m  arc position where the link waits inside the junction for the traffic it crosses
               (the end of its first internal lane, SUMO's internal junction: left turns at the towns'
               T junctions, 5.2 m past the stop line); nan where the link has none
    """

    s_start_m: float
    s_end_m: float
    tls_id: str
    link_index: int
    direction: str
    s_internal_stop_m: float = math.nan


@dataclass(frozen=True)
class LaneChange:
    """A planned lane change on a route: the sideways move from arc position s_start_m to s_end_m, to the
    neighbouring lane on the left (side +1) or on the right (side -1)."""

    s_start_m: float
    s_end_m: float
    side: int


@dataclass(frozen=True)
class RouteGeometry:
    """The lane centre line a route's vehicle should drive, as one polyline.

    xy_m [N, 2] vertices, s_m [N] arc length at each, width_m [N-1] and
    in_junction [N-1] the lane width and kind of each segment; lane_ids [N-1] the SUMO lane each
    segment lies on (during a planned lane change: the lane it starts on, then, from halfway, the
    one it ends on), or () for a geometry made by hand; lane_changes the planned lane changes in driving order.
    """

    edges: tuple[str, ...]
    xy_m: np.ndarray
    s_m: np.ndarray
    width_m: np.ndarray
    in_junction: np.ndarray
    crossings: tuple[Crossing, ...]
    lane_ids: tuple[str, ...] = ()
    lane_changes: tuple[LaneChange, ...] = ()

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])

    def lane_at(self, s_m: float) -> str | None:
        """The SUMO lane the route plans at arc length ``s_m`` (None without lane_ids)."""
        if not self.lane_ids:
            return None
        segment = int(np.clip(np.searchsorted(self.s_m, s_m, side="right") - 1, 0, len(self.lane_ids) - 1))
        return self.lane_ids[segment]


@functools.lru_cache(maxsize=4)
def read_net(net_path: Path):
    """The sumolib network with internal lanes (read once per network)."""
    import sumolib

    try:
        return sumolib.net.readNet(str(net_path), withInternal=True)
    except Exception as exc:  # sumolib raises assorted errors on bad input
        raise CrchflError(f"{net_path}: could not read the network ({exc}); rebuild it with netconvert") from None


# A planned lane change: a smooth lateral move (smoothstep in the arc length) of this length, finished this far
# before the edge's end, the stop line; on a shorter edge it takes what the edge has.
LANE_CHANGE_M = 30.0
LANE_CHANGE_END_M = 10.0
LANE_CHANGE_STEP_M = 1.0  # the blended centre line's vertex spacing


def route_geometry(net, edges: Sequence[str], lane_index: int = 0) -> RouteGeometry:
    """The centre line of ``edges`` through ``net`` (a sumolib net read with internal lanes).

    Lane-level: ``plan_lanes`` takes, on each edge, a lane with a connection to the next edge, with the
    fewest lane changes (ties: the connection listed first from the lane the vehicle is on), starting on
    the lane SUMO inserts the ego on (``start_lane``). Where an edge's exit lane differs from the lane the
    route entered it on, the centre line moves over smoothly (``lane_change_shape``), finished
    LANE_CHANGE_END_M before the stop line. Between two edges it follows the connection's internal lanes. A single edge is
    driven on ``lane_index``.
    """
    edges = tuple(edges)
    if not edges:
        raise CrchflError("route: no edges; name at least one edge id")
    objects = []
    for edge_id in edges:
        if not net.hasEdge(edge_id):
            raise CrchflError(
                f"route: edge '{edge_id}' is not in the network; check the edge ids (sumo-gui shows them)"
            )
        objects.append(net.getEdge(edge_id))
    if len(objects) == 1 and not 0 <= lane_index < objects[0].getLaneNumber():
        raise CrchflError(f"route: edge '{objects[0].getID()}' has no lane {lane_index}")
    plan = plan_lanes(objects, lane_index)
    pieces: list[tuple[np.ndarray, float, bool, list[str]]] = []  # (shape, lane width, inside a junction, lane ids)
    moves: dict[int, tuple[int, int, int]] = {}  # piece -> its lane change: (first, last vertex of the move, side)
    # Per crossing: positions in ``pieces`` of its first and last internal lane, and the connection.
    links: list[tuple[int, int, Any]] = []
    for (entry, exit_lane, connection) in plan:
        if entry is exit_lane:
            shape = np.asarray(entry.getShape(), dtype=np.float64)
            pieces.append((shape, float(exit_lane.getWidth()), False, [entry.getID()] * len(shape)))
        else:
            shape, weight = lane_change_shape(entry, exit_lane)
            lanes = [entry.getID() if w < 0.5 else exit_lane.getID() for w in weight]
            starts = max(int(np.flatnonzero(weight > 0)[0]) - 1, 0)  # the last vertex still on the entry lane
            moves[len(pieces)] = (starts, int(np.flatnonzero(weight >= 1.0)[0]), lane_side(entry, exit_lane))
            pieces.append((shape, float(exit_lane.getWidth()), False, lanes))
        if connection is None:
            break
        first = len(pieces)
        via = connection.getViaLaneID()
        while via:  # an internal lane may continue into another (internal junctions)
            internal = net.getLane(via)
            shape = np.asarray(internal.getShape(), dtype=np.float64)
            pieces.append((shape, float(internal.getWidth()), True, [via] * len(shape)))
            outgoing = internal.getOutgoing()
            via = outgoing[0].getViaLaneID() if outgoing else ""
        links.append((first, len(pieces) - 1, connection))
    points: list[np.ndarray] = []
    widths: list[float] = []
    junction: list[bool] = []
    segment_lanes: list[str] = []  # a segment's lane: the one of the vertex it ends at
    lane_end_vertex: list[int] = []  # index of each lane's last vertex in the joined polyline
    move_vertices: list[tuple[int, int, int]] = []  # per lane change: its first and last vertex there, its side
    for number, (shape, width, inside, lanes) in enumerate(pieces):
        dropped = 1 if points and np.hypot(*(shape[0] - points[-1])) < 1e-3 else 0
        if number in moves:  # a dropped first vertex lies where the previous piece's last one does
            starts, ends, side = moves[number]
            move_vertices.append((len(points) + starts - dropped, len(points) + ends - dropped, side))
        shape, lanes = shape[dropped:], lanes[dropped:]
        for p, lane in zip(shape, lanes):
            if points:
                widths.append(width)
                junction.append(inside)
                segment_lanes.append(lane)
            points.append(p)
        lane_end_vertex.append(len(points) - 1)
    xy = np.array(points)
    keep = np.concatenate([[True], np.hypot(*np.diff(xy, axis=0).T) > 1e-9])
    if not keep.all():  # drop repeated vertices (and their zero-length segments)
        seg_keep = keep[1:]
        xy, widths, junction = xy[keep], np.asarray(widths)[seg_keep], np.asarray(junction)[seg_keep]
        segment_lanes = [lane for lane, kept in zip(segment_lanes, seg_keep) if kept]
        lane_end_vertex = [int(np.count_nonzero(keep[: v + 1]) - 1) for v in lane_end_vertex]
        move_vertices = [(int(np.count_nonzero(keep[: a + 1]) - 1), int(np.count_nonzero(keep[: b + 1]) - 1), side)
                         for a, b, side in move_vertices]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    crossings = []
    for first, last, connection in links:
        tls = connection.getTLSID() or ""
        crossings.append(
            Crossing(
                s_start_m=float(s[lane_end_vertex[first - 1]]),
                s_end_m=float(s[lane_end_vertex[last]]) if last >= first else float(s[lane_end_vertex[first - 1]]),
                tls_id=tls,
                link_index=int(connection.getTLLinkIndex()) if tls else -1,
                direction=str(connection.getDirection()),
                s_internal_stop_m=float(s[lane_end_vertex[first]]) if last > first else math.nan,
            )
        )
    return RouteGeometry(
        edges=edges,
        xy_m=xy,
        s_m=s,
        width_m=np.asarray(widths, dtype=np.float64),
        in_junction=np.asarray(junction, dtype=bool),
        crossings=tuple(crossings),
        lane_ids=tuple(segment_lanes),
        lane_changes=tuple(LaneChange(float(s[a]), float(s[b]), side) for a, b, side in move_vertices),
    )


def start_lane(edge, vclass: str = "passenger"):
    """The lane SUMO inserts a vehicle on at the start of ``edge`` (its default departLane "first"): the rightmost
    lane that allows ``vclass``, else the rightmost."""
    return next((lane for lane in edge.getLanes() if lane.allows(vclass)), edge.getLanes()[0])


def plan_lanes(objects: Sequence[Any], lane_index: int = 0) -> list[tuple[Any, Any, Any]]:
    """Per edge of a route (sumolib edges): (the lane it is entered on, the lane it is left from, the connection
    to the next edge; None on the last), with the fewest lane changes (a change of k lanes counts k).

    The first edge is entered on ``start_lane``, where SUMO inserts the ego: a route that leaves it from another
    lane changes lanes on it (planned from the rightmost lane, the ego started one lane width or two off its
    centre line on A10KW). Ties go to the connection listed first, so a route that needs no change keeps the
    lanes it always had. A route whose edges do not connect is refused.
    """
    n = len(objects)
    options = []
    for i in range(n - 1):
        connections = objects[i].getConnections(objects[i + 1])
        if not connections:
            raise CrchflError(
                f"route: edge '{objects[i].getID()}' does not lead to '{objects[i + 1].getID()}'; list edges that connect"
            )
        options.append(connections)
    # cost[i][lane id]: fewest changes from entering edge i on that lane to the route's end (backwards)
    cost: list[dict[str, int]] = [dict() for _ in range(n)]
    cost[n - 1] = {lane.getID(): 0 for lane in objects[n - 1].getLanes()}

    def best(i: int, entry_index: int):
        """Edge i's best connection for a vehicle on lane ``entry_index``."""
        ranked = []
        for order, c in enumerate(options[i]):
            change = abs(c.getFromLane().getIndex() - entry_index)
            ranked.append((change + cost[i + 1][c.getToLane().getID()], change, order, c))
        return min(ranked, key=lambda r: r[:3])

    for i in range(n - 2, -1, -1):
        cost[i] = {lane.getID(): best(i, lane.getIndex())[0] for lane in objects[i].getLanes()}
    if n == 1:
        lane = objects[0].getLanes()[lane_index]
        return [(lane, lane, None)]
    plan = []
    entry = start_lane(objects[0])
    for i in range(n - 1):
        connection = best(i, entry.getIndex())[3]
        plan.append((entry, connection.getFromLane(), connection))
        entry = connection.getToLane()
    plan.append((entry, entry, None))
    return plan


def lane_change_shape(entry, exit_lane) -> tuple[np.ndarray, np.ndarray]:
    """An edge's centre line that starts on lane ``entry`` and ends on ``exit_lane`` (two lanes of one edge): the
    two lanes' centre lines blended by a smoothstep over LANE_CHANGE_M, finished LANE_CHANGE_END_M before the end
    (an edge too short for that changes over all it has but the last LANE_CHANGE_END_M, or over all of it);
    with each vertex's blend weight (0 on ``entry``, 1 on ``exit_lane``)."""
    a, b = np.asarray(entry.getShape(), np.float64), np.asarray(exit_lane.getShape(), np.float64)
    length = min(_polyline_length(a), _polyline_length(b))
    end = length - LANE_CHANGE_END_M if length > LANE_CHANGE_END_M + 2.0 else length
    start = max(0.0, end - LANE_CHANGE_M)
    s = np.unique(np.concatenate([np.arange(0.0, length, LANE_CHANGE_STEP_M), [start, end, length]]))
    t = np.clip((s - start) / max(end - start, 1e-9), 0.0, 1.0)
    weight = t * t * (3.0 - 2.0 * t)  # smoothstep: no kink where the move begins or ends
    shape = (1.0 - weight)[:, None] * _along(a, s / length) + weight[:, None] * _along(b, s / length)
    return shape, weight


def lane_side(lane, other) -> int:
    """+1 if lane ``other`` lies left of ``lane`` (two lanes of one edge, sumolib), else -1: the side of the
    other's midpoint from the lane's centre line, in driving direction (``project_points``). Geometry, not lane
    indices, which count from the outer edge of the road and so run the other way in left-hand networks."""
    shape = np.asarray(lane.getShape(), np.float64)
    s_m = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(shape, axis=0).T))])
    segments = len(shape) - 1
    centre = RouteGeometry((), shape, s_m, np.zeros(segments), np.zeros(segments, dtype=bool), ())
    x, y = _along(np.asarray(other.getShape(), np.float64), np.array([0.5]))[0]
    _, offset, _ = project_points(centre, x, y)
    return 1 if offset[0] > 0 else -1


def _polyline_length(xy: np.ndarray) -> float:
    return float(np.hypot(*np.diff(xy, axis=0).T).sum())


def _along(xy: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Points at these fractions of a polyline's length."""
    cumulative = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    at = fraction * cumulative[-1]
    return np.stack([np.interp(at, cumulative, xy[:, 0]), np.interp(at, cumulative, xy[:, 1])], axis=1)


def project_points(
    route: RouteGeometry, x_m, y_m, s_min_m: float = -math.inf, s_max_m: float = math.inf
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest route point of each (x, y) among segments within [s_min_m, s_max_m].

    Returns (s_m, offset_m, lane_width_m) per point: arc position of the
    nearest point, signed distance to it (positive LEFT of the direction of
    travel) and the lane width there. The window keeps a route that passes a
    place twice from matching the wrong pass.
    """
    x_m, y_m = np.atleast_1d(np.asarray(x_m, np.float64)), np.atleast_1d(np.asarray(y_m, np.float64))
    s = route.s_m
    window = np.flatnonzero((s[1:] >= s_min_m) & (s[:-1] <= s_max_m))
    if len(window) == 0:
        window = np.array([len(s) - 2 if s_min_m > s[-1] else 0])
    a = route.xy_m[window]
    d = route.xy_m[window + 1] - a
    length2 = np.einsum("kd,kd->k", d, d)
    p = np.stack([x_m, y_m], axis=1)
    rel = p[:, None, :] - a[None, :, :]  # [P, K, 2]
    t = np.clip(np.einsum("pkd,kd->pk", rel, d) / length2, 0.0, 1.0)
    gap = rel - t[..., None] * d
    dist2 = np.einsum("pkd,pkd->pk", gap, gap)
    k = dist2.argmin(axis=1)
    rows = np.arange(len(p))
    seg = window[k]
    t_best = t[rows, k]
    cross = d[k, 0] * rel[rows, k, 1] - d[k, 1] * rel[rows, k, 0]
    offset = np.sqrt(dist2[rows, k]) * np.where(cross >= 0, 1.0, -1.0)
    return s[seg] + t_best * (s[seg + 1] - s[seg]), offset, route.width_m[seg]


def point_at(route: RouteGeometry, s_m: float) -> tuple[float, float, float]:
    """(x, y, heading) of the centre line at arc position ``s_m`` (extended straight past either end)."""
    s = route.s_m
    seg = int(np.clip(np.searchsorted(s, s_m, side="right") - 1, 0, len(s) - 2))
    a, b = route.xy_m[seg], route.xy_m[seg + 1]
    heading = math.atan2(b[1] - a[1], b[0] - a[0])
    along = s_m - s[seg]
    return float(a[0] + along * math.cos(heading)), float(a[1] + along * math.sin(heading)), heading


# --- where the road is -----------------------------------------------------------------------


@dataclass(frozen=True)
class RoadArea:
    """The drivable surface: every lane as segments with a half width, and the junction polygons."""

    a_m: np.ndarray  # [M, 2] segment starts
    b_m: np.ndarray  # [M, 2] segment ends
    half_width_m: np.ndarray  # [M]
    junctions: tuple[np.ndarray, ...]  # polygons [K, 2]


def road_area(net) -> RoadArea:
    """All lanes (internal ones too) and junction shapes of a sumolib network, and the strips between neighbouring
    lanes of an edge: their centre lines may lie further apart than their widths (bs3d: 3.3 m apart, 3.2 m wide),
    and a lane change crossed the 0.1 m crack between them as off the road."""
    a, b, half = [], [], []

    def add(shape: np.ndarray, half_width_m: float) -> None:
        if len(shape) >= 2:
            a.append(shape[:-1])
            b.append(shape[1:])
            half.append(np.full(len(shape) - 1, half_width_m))

    for edge in net.getEdges(withInternal=True):
        lanes = edge.getLanes()
        shapes = [np.asarray(lane.getShape(), dtype=np.float64) for lane in lanes]
        for lane, shape in zip(lanes, shapes):
            add(shape, lane.getWidth() / 2.0)
        for (right, left), (shape_r, shape_l) in zip(zip(lanes, lanes[1:]), zip(shapes, shapes[1:])):
            if len(shape_r) == len(shape_l):  # netconvert offsets an edge's lanes from one shape, point for point
                # the midway line, as wide as the narrower lane: it covers no more than the lanes' two centre lines
                add((shape_r + shape_l) / 2.0, min(right.getWidth(), left.getWidth()) / 2.0)
    junctions = tuple(
        np.asarray(node.getShape(), dtype=np.float64) for node in net.getNodes() if len(node.getShape()) >= 3
    )
    return RoadArea(np.concatenate(a), np.concatenate(b), np.concatenate(half), junctions)


def _inside_polygon(polygon: np.ndarray, x_m: float, y_m: float) -> bool:
    """Even-odd rule: does a ray from (x, y) towards +x cross the outline an odd number of times?"""
    xa, ya = polygon[:, 0], polygon[:, 1]
    xb, yb = np.roll(xa, -1), np.roll(ya, -1)
    straddles = (ya > y_m) != (yb > y_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = xa + (y_m - ya) * (xb - xa) / (yb - ya)
    return bool(np.count_nonzero(straddles & (x_cross > x_m)) % 2)


def on_road(area: RoadArea, x_m: float, y_m: float, margin_m: float = 0.0) -> bool:
    """True where (x, y) lies on a lane (within its half width + ``margin_m``) or inside a junction."""
    d = area.b_m - area.a_m
    rel = np.array([x_m, y_m]) - area.a_m
    t = np.clip(np.einsum("kd,kd->k", rel, d) / np.maximum(np.einsum("kd,kd->k", d, d), 1e-12), 0.0, 1.0)
    gap = rel - t[:, None] * d
    if np.any(np.einsum("kd,kd->k", gap, gap) <= (area.half_width_m + margin_m) ** 2):
        return True
    return any(
        polygon[:, 0].min() <= x_m <= polygon[:, 0].max()
        and polygon[:, 1].min() <= y_m <= polygon[:, 1].max()
        and _inside_polygon(polygon, x_m, y_m)
        for polygon in area.junctions
    )


# --- rules of the road -------------------------------------------------------------------------


def signal_letter(crossing: Crossing, tls_states: Mapping[str, str]) -> str:
    """The signal letter of a crossing's link ('' at an unsignalised junction or an unknown signal)."""
    state = tls_states.get(crossing.tls_id, "") if crossing.tls_id else ""
    return state[crossing.link_index] if 0 <= crossing.link_index < len(state) else ""


def next_signal(crossings: Sequence[Crossing], front_s_m: float, tls_states: Mapping[str, str]) -> tuple[str, float]:
    """The letter of the first signalised stop line at or ahead of the front bumper, and its distance
    ('' and inf if none): SUMO's next signal of a vehicle (Frame.tls_ahead_*), which passes over
    unsignalised junctions, unlike ``next_crossing``."""
    for crossing in crossings:
        if crossing.tls_id and crossing.s_start_m >= front_s_m:
            return signal_letter(crossing, tls_states), crossing.s_start_m - front_s_m
    return "", math.inf


def inside_crossing(crossings: Sequence[Crossing], centre_s_m: float, length_m: float) -> bool:
    """Has a vehicle's front bumper passed a stop line on its route, with its centre not yet out of that junction?"""
    front_s_m = centre_s_m + length_m / 2.0
    return any(c.s_start_m < front_s_m and centre_s_m < c.s_end_m for c in crossings)


def internal_stop_ahead(crossings: Sequence[Crossing], front_s_m: float) -> int:
    """Index of the crossing whose stop line the front bumper has passed and whose internal stop
    (Crossing.s_internal_stop_m) it has not yet reached (-1 if none)."""
    for index, crossing in enumerate(crossings):
        if crossing.s_start_m < front_s_m < crossing.s_internal_stop_m:  # False for nan: no internal stop
            return index
    return -1


def next_crossing(crossings: Sequence[Crossing], front_s_m: float) -> int:
    """Index of the first crossing whose stop line lies at or ahead of the front bumper (-1 if none)."""
    for index, crossing in enumerate(crossings):
        if crossing.s_start_m >= front_s_m:
            return index
    return -1
