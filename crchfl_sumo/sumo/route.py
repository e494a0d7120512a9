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
    """

    s_start_m: float
    s_end_m: float
    tls_id: str
    link_index: int
    direction: str


@dataclass(frozen=True)
class RouteGeometry:
    """The lane centre line a route's vehicle should drive, as one polyline.

    xy_m [N, 2] vertices, s_m [N] arc length at each, width_m [N-1] and
    in_junction [N-1] the lane width and kind of each segment.
    """

    edges: tuple[str, ...]
    xy_m: np.ndarray
    s_m: np.ndarray
    width_m: np.ndarray
    in_junction: np.ndarray
    crossings: tuple[Crossing, ...]

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])


@functools.lru_cache(maxsize=4)
def read_net(net_path: Path):
    """The sumolib network with internal lanes (read once per network)."""
    import sumolib

    try:
        return sumolib.net.readNet(str(net_path), withInternal=True)
    except Exception as exc:  # sumolib raises assorted errors on bad input
        raise CrchflError(f"{net_path}: could not read the network ({exc}); rebuild it with netconvert") from None


def route_geometry(net, edges: Sequence[str], lane_index: int = 0) -> RouteGeometry:
    """The centre line of ``edges`` through ``net`` (a sumolib net read with internal lanes).

    Between two edges the route takes the connection from the lane it is on
    (on the first edge: the rightmost lane that reaches the second edge), then
    the junction's internal lanes. A single edge is driven on ``lane_index``.
    Routes that would need a lane change are refused.
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
    lanes: list[tuple[Any, bool]] = []  # (sumolib lane, inside a junction)
    # Per crossing: positions in ``lanes`` of its first and last internal lane, and the connection.
    links: list[tuple[int, int, Any]] = []
    lane = None
    for i, edge in enumerate(objects):
        if i == len(objects) - 1:
            if lane is None:
                if not 0 <= lane_index < edge.getLaneNumber():
                    raise CrchflError(f"route: edge '{edge.getID()}' has no lane {lane_index}")
                lane = edge.getLanes()[lane_index]
            lanes.append((lane, False))
            break
        connections = edge.getConnections(objects[i + 1])
        if not connections:
            raise CrchflError(
                f"route: edge '{edge.getID()}' does not lead to '{objects[i + 1].getID()}'; list edges that connect"
            )
        if lane is None:
            lane = min((c.getFromLane() for c in connections), key=lambda l: l.getIndex())
        ours = [c for c in connections if c.getFromLane() is lane]
        if not ours:
            raise CrchflError(
                f"route: from lane '{lane.getID()}' no connection leads to '{objects[i + 1].getID()}' "
                "(the route needs a lane change); drive routes must keep to connected lanes"
            )
        connection = ours[0]
        lanes.append((lane, False))
        first = len(lanes)
        via = connection.getViaLaneID()
        while via:  # an internal lane may continue into another (internal junctions)
            internal = net.getLane(via)
            lanes.append((internal, True))
            outgoing = internal.getOutgoing()
            via = outgoing[0].getViaLaneID() if outgoing else ""
        links.append((first, len(lanes) - 1, connection))
        lane = connection.getToLane()
    points: list[np.ndarray] = []
    widths: list[float] = []
    junction: list[bool] = []
    lane_end_vertex: list[int] = []  # index of each lane's last vertex in the joined polyline
    for lane_obj, inside in lanes:
        shape = np.asarray(lane_obj.getShape(), dtype=np.float64)
        if points and np.hypot(*(shape[0] - points[-1])) < 1e-3:
            shape = shape[1:]
        for p in shape:
            if points:
                widths.append(float(lane_obj.getWidth()))
                junction.append(inside)
            points.append(p)
        lane_end_vertex.append(len(points) - 1)
    xy = np.array(points)
    keep = np.concatenate([[True], np.hypot(*np.diff(xy, axis=0).T) > 1e-9])
    if not keep.all():  # drop repeated vertices (and their zero-length segments)
        seg_keep = keep[1:]
        xy, widths, junction = xy[keep], np.asarray(widths)[seg_keep], np.asarray(junction)[seg_keep]
        lane_end_vertex = [int(np.count_nonzero(keep[: v + 1]) - 1) for v in lane_end_vertex]
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
            )
        )
    return RouteGeometry(
        edges=edges,
        xy_m=xy,
        s_m=s,
        width_m=np.asarray(widths, dtype=np.float64),
        in_junction=np.asarray(junction, dtype=bool),
        crossings=tuple(crossings),
    )


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
    """All lanes (internal ones too) and junction shapes of a sumolib network."""
    a, b, half = [], [], []
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            shape = np.asarray(lane.getShape(), dtype=np.float64)
            if len(shape) < 2:
                continue
            a.append(shape[:-1])
            b.append(shape[1:])
            half.append(np.full(len(shape) - 1, lane.getWidth() / 2.0))
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


def inside_crossing(crossings: Sequence[Crossing], centre_s_m: float, length_m: float) -> bool:
    """Has a vehicle's front bumper passed a stop line on its route, with its centre not yet out of that junction?"""
    front_s_m = centre_s_m + length_m / 2.0
    return any(c.s_start_m < front_s_m and centre_s_m < c.s_end_m for c in crossings)


def next_crossing(crossings: Sequence[Crossing], front_s_m: float) -> int:
    """Index of the first crossing whose stop line lies at or ahead of the front bumper (-1 if none)."""
    for index, crossing in enumerate(crossings):
        if crossing.s_start_m >= front_s_m:
            return index
    return -1
