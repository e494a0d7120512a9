"""Closed-loop driving: a policy (a trained model, or a script) drives an ego vehicle in SUMO.

Every step the ego's four cameras are rendered from the current Frame, the
policy predicts (throttle, steer, brake), and the ego moves by a kinematic
bicycle model that inverts the expert's label mappings (expert.py), so that an
action means in the loop what it meant in the data set:

    delta   = -steer * max_steer_angle            wheel angle, CCW + (positive steer = RIGHT)
    kappa   = tan(delta) / wheelbase              path curvature of the footprint centre
    a       = throttle * max_accel - brake * max_decel - resistance(v)
    v'      = max(0, v + a dt);  the centre moves (v + v') / 2 * dt along the arc of curvature kappa

The expert labelled the footprint centre's track with delta = atan(wheelbase *
kappa), so the loop moves the centre on arcs of curvature tan(delta) /
wheelbase: a steer label replayed gives back the curvature it was made from.
The new pose is placed in SUMO with moveToXY (free placement, front bumper,
libsumo via sim.py) and the ego's speed is set, so the other vehicles follow,
stop behind and yield to it as to any other vehicle.

Metrics are measured against the planned route's lane centre line (the lanes
of the route's edges joined by the junctions' internal lanes), read from the
network with sumolib. docs/drive.md defines each of them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .config import from_mapping, read_toml
from .errors import CrchflError
from .expert import ExpertConfig, pedals, resistance_mps2, steer_from_curvature
from .frame import Frame
from .scenario import Scenario, load_scenario
from .sim import Simulation

log = logging.getLogger(__name__)

ROUTES_PATH = Path(__file__).parent / "scenarios" / "drive_routes.toml"
RED_LETTERS = ("r", "u")  # SUMO red and red-yellow: crossing the stop line on either is a violation
YELLOW_LETTERS = ("y", "Y")
GREEN_LETTERS = ("g", "G")
DEFAULT_TYPE = "DEFAULT_VEHTYPE"  # SUMO's built-in type, for scenarios without an 'ego' type
# SUMO options of a drive: collisions are reported and nothing is removed (the run
# measures them), any physical overlap counts, and a standing ego is never teleported.
DRIVE_SUMO_OPTIONS = (
    "--collision.action=warn",
    "--collision.check-junctions=true",
    "--collision.mingap-factor=0",
    "--time-to-teleport=-1",
)
_SEARCH_BACK_M = 10.0  # the ego's progress is searched this far behind ...
_SEARCH_AHEAD_M = 25.0  # ... and this far ahead of the last step's (routes may cross themselves)

Action = tuple[float, float, float]  # (throttle, steer, brake), labels.py conventions


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


# --- vehicle motion: the inverse of the expert's mappings ----------------------------------


@dataclass(frozen=True)
class VehicleState:
    """Pose of the footprint centre (frame.py conventions) and speed."""

    x_m: float
    y_m: float
    heading_rad: float
    speed_mps: float


def wheel_angle_rad(steer: float, config: ExpertConfig = ExpertConfig()) -> float:
    """Steer in [-1, 1] (positive RIGHT) -> wheel angle [rad], CCW positive: the inverse of the expert's."""
    return -float(np.clip(steer, -1.0, 1.0)) * math.radians(config.max_steer_angle_deg)


def curvature_from_steer(steer: float, config: ExpertConfig = ExpertConfig()) -> float:
    """Path curvature [1/m] (CCW +) the bicycle model drives at ``steer``: tan(delta) / wheelbase."""
    return math.tan(wheel_angle_rad(steer, config)) / config.wheelbase_m


def acceleration_from_pedals(
    throttle: float,
    brake: float,
    speed_mps: float,
    max_accel_mps2: float,
    max_decel_mps2: float,
    config: ExpertConfig = ExpertConfig(),
) -> float:
    """Longitudinal acceleration [m/s^2] the pedals give: the inverse of expert.pedals.

    a = throttle * max_accel - brake * max_decel - resistance(speed). Pedals
    outside [0, 1] are clipped (a model's outputs are sigmoids, already inside).
    """
    throttle = float(np.clip(throttle, 0.0, 1.0))
    brake = float(np.clip(brake, 0.0, 1.0))
    return throttle * max_accel_mps2 - brake * max_decel_mps2 - float(resistance_mps2(speed_mps, config))


def bicycle_step(
    state: VehicleState, accel_mps2: float, steer: float, dt_s: float, config: ExpertConfig = ExpertConfig()
) -> VehicleState:
    """The state ``dt_s`` later: speed changes by accel (never below 0), the centre follows an exact arc."""
    v0 = state.speed_mps
    v1 = v0 + accel_mps2 * dt_s
    if v1 >= 0.0:
        distance_m = 0.5 * (v0 + v1) * dt_s
    else:  # stops within the step: it rolls v0^2 / 2|a| and stands
        v1 = 0.0
        distance_m = v0 * v0 / (2.0 * -accel_mps2)
    kappa = curvature_from_steer(steer, config)
    h0 = state.heading_rad
    turn = kappa * distance_m
    if abs(turn) < 1e-9:
        x = state.x_m + distance_m * math.cos(h0)
        y = state.y_m + distance_m * math.sin(h0)
    else:
        x = state.x_m + (math.sin(h0 + turn) - math.sin(h0)) / kappa
        y = state.y_m - (math.cos(h0 + turn) - math.cos(h0)) / kappa
    heading = math.atan2(math.sin(h0 + turn), math.cos(h0 + turn))
    return VehicleState(x, y, heading, v1)


# --- rules of the road -------------------------------------------------------------------------


def signal_letter(crossing: Crossing, tls_states: Mapping[str, str]) -> str:
    """The signal letter of a crossing's link ('' at an unsignalised junction or an unknown signal)."""
    state = tls_states.get(crossing.tls_id, "") if crossing.tls_id else ""
    return state[crossing.link_index] if 0 <= crossing.link_index < len(state) else ""


def next_crossing(crossings: Sequence[Crossing], front_s_m: float) -> int:
    """Index of the first crossing whose stop line lies at or ahead of the front bumper (-1 if none)."""
    for index, crossing in enumerate(crossings):
        if crossing.s_start_m >= front_s_m:
            return index
    return -1


def red_light_violations(
    crossings: Sequence[Crossing], front_before_m: float, front_after_m: float, tls_states: Mapping[str, str]
) -> list[Crossing]:
    """Crossings whose stop line the front bumper passed in this step while the link showed red."""
    return [
        c
        for c in crossings
        if front_before_m < c.s_start_m <= front_after_m and signal_letter(c, tls_states) in RED_LETTERS
    ]


def lane_departed(offset_m, lane_width_m, vehicle_width_m: float) -> np.ndarray:
    """True where a wheel is over the lane's edge: |offset| > lane_width / 2 - vehicle_width / 2."""
    return np.abs(np.asarray(offset_m)) > np.asarray(lane_width_m) / 2.0 - vehicle_width_m / 2.0


def count_onsets(mask) -> int:
    """Number of runs of True (events that last several steps count once)."""
    mask = np.asarray(mask, dtype=bool)
    return int(np.count_nonzero(mask[1:] & ~mask[:-1]) + (1 if len(mask) and mask[0] else 0))


# --- policies ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Observation:
    """What a policy sees at one step."""

    frame: Frame
    ego_id: str
    ego_row: int
    progress_m: float  # the ego centre's arc position on the route
    images: np.ndarray | None  # uint8 [4, H, W, 3] when the loop renders, else None


Policy = Callable[[Observation], Action]


@dataclass(frozen=True)
class ConstantPolicy:
    """The same action every step (a test of the loop: a hard steer must leave the lane)."""

    throttle: float = 0.3
    steer: float = 0.0
    brake: float = 0.0

    def __call__(self, observation: Observation) -> Action:
        return (self.throttle, self.steer, self.brake)


@dataclass(frozen=True)
class RoutePolicyConfig:
    """A scripted driver that knows the route (no images): the reference the models are compared to.

    target_speed_mps        cruise speed
    lookahead_min_m, lookahead_time_s  pure-pursuit look-ahead max(min, time * speed) on the centre line
    speed_gain_per_s        desired acceleration per m/s of speed error
    headway_s, standstill_gap_m  distance kept to a vehicle ahead in the lane: gap >= standstill + headway * v
    comfort_decel_mps2      deceleration planned for stopping at a light
    stop_gap_m              the front bumper stops this far before the stop line
    yield_radius_m          on a minor green ('g') it waits while a vehicle within this distance of
                            the junction's middle moves towards it (or any vehicle is inside it)
    """

    target_speed_mps: float = 8.0
    lookahead_min_m: float = 4.0
    lookahead_time_s: float = 0.5
    speed_gain_per_s: float = 1.5
    headway_s: float = 1.5
    standstill_gap_m: float = 3.0
    comfort_decel_mps2: float = 2.5
    stop_gap_m: float = 1.0
    yield_radius_m: float = 30.0

    def __post_init__(self) -> None:
        for name in ("target_speed_mps", "lookahead_min_m", "speed_gain_per_s", "comfort_decel_mps2"):
            if not getattr(self, name) > 0:
                raise CrchflError(f"route_policy.{name} must be > 0, got {getattr(self, name)}")
        for name in ("lookahead_time_s", "headway_s", "standstill_gap_m", "stop_gap_m", "yield_radius_m"):
            if getattr(self, name) < 0:
                raise CrchflError(f"route_policy.{name} must be >= 0, got {getattr(self, name)}")


class RoutePolicy:
    """Pure pursuit on the route's centre line, stops at red lights and behind vehicles in its lane.

    Its pedals come from the expert's own mapping (expert.pedals) of the
    acceleration it wants, its steer from the expert's curvature mapping, so
    the loop's inverse mappings return exactly what it planned.
    """

    def __init__(
        self,
        route: RouteGeometry,
        config: RoutePolicyConfig = RoutePolicyConfig(),
        expert: ExpertConfig = ExpertConfig(),
    ) -> None:
        self.route = route
        self.config = config
        self.expert = expert

    def steer(self, x_m: float, y_m: float, heading_rad: float, speed_mps: float, progress_m: float) -> float:
        cfg = self.config
        look = max(cfg.lookahead_min_m, cfg.lookahead_time_s * speed_mps)
        tx, ty, _ = point_at(self.route, progress_m + look)
        dx, dy = tx - x_m, ty - y_m
        chord = math.hypot(dx, dy)
        kappa = 2.0 * math.sin(math.atan2(dy, dx) - heading_rad) / chord if chord > 1e-6 else 0.0
        return float(steer_from_curvature(kappa, self.expert))

    def wanted_accel_mps2(self, observation: Observation) -> float:
        """Acceleration to cruise, to keep the gap to the vehicle ahead in the lane, and to stop at a light."""
        cfg = self.config
        frame, row = observation.frame, observation.ego_row
        v = float(frame.speed_mps[row])
        max_accel, max_decel = float(frame.max_accel_mps2[row]), float(frame.max_decel_mps2[row])
        half_length = float(frame.length_m[row]) / 2.0
        s = observation.progress_m
        wanted = cfg.target_speed_mps
        others = np.flatnonzero(
            (np.arange(len(frame)) != row) & (np.hypot(frame.x_m - frame.x_m[row], frame.y_m - frame.y_m[row]) < 60.0)
        )
        if len(others):
            s_o, off_o, width_o = project_points(self.route, frame.x_m[others], frame.y_m[others], s, s + 50.0)
            ahead = (s_o > s) & (np.abs(off_o) < width_o / 2.0 + frame.width_m[others] / 2.0 - 0.3)
            if ahead.any():
                gap = (s_o - s - frame.length_m[others] / 2.0 - half_length)[ahead].min()
                wanted = min(wanted, max(0.0, (gap - cfg.standstill_gap_m) / max(cfg.headway_s, 1e-3)))
        accel = cfg.speed_gain_per_s * (wanted - v)
        index = next_crossing(self.route.crossings, s + half_length)
        if index >= 0:
            crossing = self.route.crossings[index]
            letter = signal_letter(crossing, frame.tls_states)
            room = crossing.s_start_m - (s + half_length) - cfg.stop_gap_m
            needed = v * v / (2.0 * room) if room > 0.3 else math.inf
            # Stop for red; for yellow only when that takes no more than a comfortable deceleration;
            # on a minor green ('g': yield) while other traffic is in or heading into the junction.
            yield_now = letter == "g" and self._junction_busy(observation, crossing)
            if letter in RED_LETTERS or yield_now or (letter in YELLOW_LETTERS and needed <= cfg.comfort_decel_mps2):
                if room <= 0.3:
                    accel = -max_decel
                else:
                    creep = cfg.speed_gain_per_s * (math.sqrt(cfg.comfort_decel_mps2 * room) - v)
                    accel = min(accel, creep, -needed if needed >= 0.5 * cfg.comfort_decel_mps2 else math.inf)
        return float(np.clip(accel, -max_decel, max_accel))

    def _junction_busy(self, observation: Observation, crossing: Crossing) -> bool:
        """Is another vehicle inside the junction, or moving towards it, other than those in the ego's lane?"""
        frame, row = observation.frame, observation.ego_row
        cx, cy, _ = point_at(self.route, 0.5 * (crossing.s_start_m + crossing.s_end_m))
        dx, dy = cx - frame.x_m, cy - frame.y_m
        distance = np.hypot(dx, dy)
        closing = (np.cos(frame.heading_rad) * dx + np.sin(frame.heading_rad) * dy) > 0
        near = (np.arange(len(frame)) != row) & (
            (distance < 8.0) | ((distance < self.config.yield_radius_m) & closing & (frame.speed_mps > 0.5))
        )
        rows = np.flatnonzero(near)
        if len(rows) == 0:
            return False
        s = observation.progress_m
        s_o, off_o, width_o = project_points(self.route, frame.x_m[rows], frame.y_m[rows], s - 30.0, s + 30.0)
        in_my_lane = np.abs(off_o) < width_o / 2.0
        behind = in_my_lane & (s_o < s)
        return bool(np.any(~behind & ~(in_my_lane & (s_o > crossing.s_end_m))))

    def __call__(self, observation: Observation) -> Action:
        frame, row = observation.frame, observation.ego_row
        v = float(frame.speed_mps[row])
        steer = self.steer(
            float(frame.x_m[row]), float(frame.y_m[row]), float(frame.heading_rad[row]), v, observation.progress_m
        )
        accel = self.wanted_accel_mps2(observation)
        if v < self.expert.stop_speed_mps and accel < 0:
            accel, steer = 0.0, 0.0  # standing: pedals() holds the brake; wheels straight like the expert's
        max_accel, max_decel = float(frame.max_accel_mps2[row]), float(frame.max_decel_mps2[row])
        # The expert's pedal mapping adds what holding speed costs.
        throttle, brake = pedals(
            np.array([v]), np.array([accel]), np.array([max_accel]), np.array([max_decel]), self.expert
        )
        return (float(throttle[0]), steer, float(brake[0]))


class ModelPolicy:
    """A DrivingModel: the ego's four camera images -> (throttle, steer via the DAC, brake)."""

    def __init__(self, model) -> None:
        self.model = model

    def __call__(self, observation: Observation) -> Action:
        import torch

        from .model import predict_actions

        if observation.images is None:
            raise CrchflError("the model policy needs camera images; give drive() a renderer")
        images = torch.from_numpy(np.ascontiguousarray(observation.images))
        throttle, steer, brake = predict_actions(self.model, images)
        return (float(throttle), float(steer), float(brake))


# --- the loop ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DriveConfig:
    """Settings of a closed-loop drive.

    ego_id               id of the driven vehicle in SUMO
    type_id              its SUMO vehicle type (SUMO's default type if the scenario lacks it)
    warmup_s             traffic runs this long before the ego is added, so that it meets moving traffic
    insert_timeout_s     how long SUMO may wait for room to insert the ego at the route's start
    finish_before_end_m  the route counts as completed when the ego's centre is this close to its end
    lost_offset_m        the drive ends when the ego is farther than this from the route's centre line
    off_road_margin_m    the centre may be this far off a lane's edge before it counts as off the road
    """

    ego_id: str = "ego"
    type_id: str = "ego"
    warmup_s: float = 20.0
    insert_timeout_s: float = 60.0
    finish_before_end_m: float = 5.0
    lost_offset_m: float = 10.0
    off_road_margin_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("warmup_s", "finish_before_end_m", "off_road_margin_m"):
            if getattr(self, name) < 0:
                raise CrchflError(f"drive.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("insert_timeout_s", "lost_offset_m"):
            if not getattr(self, name) > 0:
                raise CrchflError(f"drive.{name} must be > 0, got {getattr(self, name)}")
        if not self.ego_id:
            raise CrchflError("drive.ego_id must not be empty")


@dataclass(frozen=True)
class DriveLog:
    """One row per step of the drive, the ego's state when the policy acted (arrays [T]).

    The last row is the state the drive ended in; its action is nan.
    signal_* describe the next stop line on the route ('' / inf / -1 if none);
    red_light marks the step whose move crossed a stop line on red.
    """

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    throttle: np.ndarray
    steer: np.ndarray
    brake: np.ndarray
    progress_m: np.ndarray
    offset_m: np.ndarray
    lane_width_m: np.ndarray
    on_road: np.ndarray
    colliding: np.ndarray
    red_light: np.ndarray
    signal_letter: np.ndarray
    signal_dist_m: np.ndarray
    crossing_ahead: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)

    def columns(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class DriveResult:
    """A finished drive: its log, metrics and the frames the policy saw (ego pose as driven)."""

    log: DriveLog
    metrics: dict[str, Any]
    frames: list[Frame]
    route: RouteGeometry
    ego_id: str
    vehicle_length_m: float
    vehicle_width_m: float


def with_ego_pose(frame: Frame, row: int, state: VehicleState) -> Frame:
    """The frame with the ego's row set to the bicycle model's state (what the cameras must show)."""
    columns = {}
    values = {"x_m": state.x_m, "y_m": state.y_m, "heading_rad": state.heading_rad, "speed_mps": state.speed_mps}
    for name, value in values.items():
        column = getattr(frame, name).copy()
        column[row] = value
        columns[name] = column
    return dataclasses.replace(frame, **columns)


def drive(
    scenario: Scenario,
    route: RouteGeometry,
    policy: Policy,
    seed: int = 0,
    max_s: float = 120.0,
    config: DriveConfig = DriveConfig(),
    renderer=None,
    expert: ExpertConfig = ExpertConfig(),
    keep_frames: bool = True,
) -> DriveResult:
    """Drive ``route`` in ``scenario`` with ``policy`` for at most ``max_s`` simulated seconds.

    ``renderer`` (raster.Renderer of the scenario's world) renders the ego's
    cameras for the policy every step; a policy without images passes None.
    """
    if not max_s > 0:
        raise CrchflError(f"--max-s must be > 0, got {max_s}")
    ego = config.ego_id
    dt = scenario.step_length_s
    area = road_area(read_net(Path(scenario.net_path)))
    rows: list[dict[str, Any]] = []
    frames: list[Frame] = []
    with Simulation(scenario, seed=seed, extra_options=DRIVE_SUMO_OPTIONS, watch=[ego]) as sim:
        for _ in range(int(round(config.warmup_s / dt))):
            sim.step()
        type_id = config.type_id if config.type_id in sim.vehicle_type_ids() else DEFAULT_TYPE
        sim.add_external_vehicle(ego, route.edges, type_id)
        for _ in range(max(1, int(round(config.insert_timeout_s / dt)))):
            frame = sim.step()
            if ego in frame.ids:
                break
        else:
            raise CrchflError(
                f"SUMO found no room to insert the ego at the start of edge '{route.edges[0]}' within "
                f"{config.insert_timeout_s} s; start the route on another edge or change drive.warmup_s"
            )
        row = frame.index_of(ego)
        length, width = float(frame.length_m[row]), float(frame.width_m[row])
        max_accel, max_decel = float(frame.max_accel_mps2[row]), float(frame.max_decel_mps2[row])
        state = VehicleState(float(frame.x_m[row]), float(frame.y_m[row]), float(frame.heading_rad[row]), 0.0)
        first_stop = route.crossings[0].s_start_m if route.crossings else route.length_m
        s, offset, lane_width = (
            float(v[0]) for v in project_points(route, state.x_m, state.y_m, -math.inf, first_stop)
        )
        start_s, goal_s = s, route.length_m - config.finish_before_end_m
        t_start = frame.t_s
        colliding, red, removed = False, False, False
        while True:
            row = frame.index_of(ego)
            frame = with_ego_pose(frame, row, state)
            index = next_crossing(route.crossings, s + length / 2.0)
            letter = signal_letter(route.crossings[index], frame.tls_states) if index >= 0 else ""
            record = {
                "t_s": frame.t_s - t_start, "x_m": state.x_m, "y_m": state.y_m, "heading_rad": state.heading_rad,
                "speed_mps": state.speed_mps, "progress_m": s, "offset_m": offset, "lane_width_m": lane_width,
                "on_road": on_road(area, state.x_m, state.y_m, config.off_road_margin_m),
                "colliding": colliding, "red_light": red, "signal_letter": letter,
                "signal_dist_m": route.crossings[index].s_start_m - (s + length / 2.0) if index >= 0 else math.inf,
                "crossing_ahead": index,
            }
            if removed:
                end = "removed by SUMO"
            elif s >= goal_s:
                end = "completed"
            elif abs(offset) > config.lost_offset_m:
                end = "left the route"
            elif frame.t_s - t_start >= max_s - 1e-9:
                end = "time limit"
            else:
                end = None
            if keep_frames:
                frames.append(frame)
            if end is not None:
                rows.append(record | {"throttle": math.nan, "steer": math.nan, "brake": math.nan})
                break
            images = renderer.render(frame, [ego])[0] if renderer is not None else None
            throttle, steer, brake = policy(Observation(frame, ego, row, s, images))
            rows.append(record | {"throttle": throttle, "steer": steer, "brake": brake})
            accel = acceleration_from_pedals(throttle, brake, state.speed_mps, max_accel, max_decel, expert)
            new_state = bicycle_step(state, accel, steer, dt, expert)
            sim.place_vehicle(
                ego,
                new_state.x_m + length / 2.0 * math.cos(new_state.heading_rad),
                new_state.y_m + length / 2.0 * math.sin(new_state.heading_rad),
                new_state.heading_rad,
                new_state.speed_mps,
            )
            seen = frame
            frame = sim.step()
            removed = ego not in frame.ids
            if removed:  # SUMO let it arrive or teleported it: end with the last picture of it
                log.warning("SUMO removed the ego '%s' at t=%.2f s; the drive ends there", ego, frame.t_s)
                frame = dataclasses.replace(seen, t_s=frame.t_s, tls_states=frame.tls_states)
            colliding = ego in sim.colliding_vehicles()
            new_s, offset, lane_width = (
                float(v[0])
                for v in project_points(route, new_state.x_m, new_state.y_m, s - _SEARCH_BACK_M, s + _SEARCH_AHEAD_M)
            )
            red = bool(red_light_violations(route.crossings, s + length / 2.0, new_s + length / 2.0, seen.tls_states))
            state, s = new_state, new_s
    drive_log = _log_from_rows(rows)
    metrics = drive_metrics(drive_log, start_s, goal_s, width, dt, end)
    log.info(
        "drive from %s ended (%s) after %.1f s: completion %.2f",
        route.edges[0], end, drive_log.t_s[-1], metrics["completion"],
    )
    return DriveResult(drive_log, metrics, frames, route, ego, length, width)


def _log_from_rows(rows: list[dict[str, Any]]) -> DriveLog:
    kinds = {"on_road": bool, "colliding": bool, "red_light": bool, "signal_letter": str, "crossing_ahead": np.int64}
    return DriveLog(
        **{
            f.name: np.array([r[f.name] for r in rows], dtype=kinds.get(f.name, np.float64))
            for f in dataclasses.fields(DriveLog)
        }
    )


def drive_metrics(
    drive_log: DriveLog, start_s_m: float, goal_s_m: float, vehicle_width_m: float, step_s: float, end_reason: str
) -> dict[str, Any]:
    """The per-route metrics of a drive (docs/drive.md defines each)."""
    departed = lane_departed(drive_log.offset_m, drive_log.lane_width_m, vehicle_width_m)
    off_road = ~drive_log.on_road
    span = max(goal_s_m - start_s_m, 1e-9)
    best = float(np.max(drive_log.progress_m)) if len(drive_log) else start_s_m
    path_m = float(np.sum(np.hypot(np.diff(drive_log.x_m), np.diff(drive_log.y_m))))
    duration_s = float(drive_log.t_s[-1]) if len(drive_log) else 0.0
    return {
        "end_reason": end_reason,
        "completion": float(np.clip((best - start_s_m) / span, 0.0, 1.0)),
        "duration_s": duration_s,
        "distance_m": path_m,
        "mean_speed_mps": path_m / duration_s if duration_s > 0 else 0.0,
        "collisions": count_onsets(drive_log.colliding),
        "lane_departures": count_onsets(departed),
        "lane_departure_s": float(np.count_nonzero(departed[:-1]) * step_s),
        "max_abs_offset_m": float(np.max(np.abs(drive_log.offset_m))) if len(drive_log) else 0.0,
        "off_road_events": count_onsets(off_road),
        "off_road_s": float(np.count_nonzero(off_road[:-1]) * step_s),
        "red_light_violations": int(np.count_nonzero(drive_log.red_light)),
    }


# --- named evaluation routes ---------------------------------------------------------------------


@dataclass(frozen=True)
class DriveRoute:
    """A named evaluation route of drive_routes.toml."""

    scenario: str
    edges: tuple[str, ...]
    description: str = ""


def load_drive_routes(path: str | Path = ROUTES_PATH) -> dict[str, DriveRoute]:
    """Route name -> DriveRoute from a routes TOML (``[routes.NAME]`` tables)."""
    data = read_toml(path)
    unknown = sorted(set(data) - {"routes"})
    if unknown:
        raise CrchflError(f"{path}: unknown top-level key(s) {unknown}; put routes under [routes.NAME]")
    return {
        name: from_mapping(DriveRoute, table, where=f"{path}: routes.{name}")
        for name, table in data.get("routes", {}).items()
    }


def resolve_route(route: str, scenario: str | None) -> tuple[str, tuple[str, ...]]:
    """(scenario, edges) for a route name of drive_routes.toml, or for edge ids separated by commas/spaces.

    A named route brings its scenario; a list of edges needs ``scenario``.
    """
    named = load_drive_routes()
    if route in named:
        entry = named[route]
        if scenario is not None and scenario != entry.scenario:
            raise CrchflError(
                f"route '{route}' runs in scenario '{entry.scenario}', not '{scenario}'; drop --scenario or match it"
            )
        return entry.scenario, entry.edges
    edges = tuple(e for e in route.replace(",", " ").split() if e)
    if scenario is None or not edges:
        raise CrchflError(
            f"route '{route}' is not a named route ({', '.join(sorted(named))}); "
            "name one, or give --scenario and the edge ids separated by commas"
        )
    return scenario, edges


def drive_command(
    model_path: str | Path | None,
    scenario: str | None,
    route: str,
    out_dir: str | Path,
    seed: int = 0,
    max_s: float = 120.0,
    config: DriveConfig = DriveConfig(),
    video: bool = True,
) -> dict[str, Any]:
    """The `crchfl-sumo drive` body: drive a route, write metrics, trajectory, pictures; return the metrics.

    ``model_path`` None drives with the scripted RoutePolicy (the reference).
    Writes OUT/metrics.json, OUT/trajectory.csv, OUT/trajectory.png,
    OUT/frames/{red_light,green_light,t_junction_turn}.png (those that occur)
    and OUT/drive.mp4.
    """
    from .drive_plots import write_drive_outputs
    from .raster import RasterConfig, Renderer
    from .raster_world import build_world
    from .camera import CameraConfig

    scenario_name, edges = resolve_route(route, scenario)
    loaded = load_scenario(scenario_name)
    geometry = route_geometry(read_net(Path(loaded.net_path)), edges)
    if model_path is None:
        policy: Policy = RoutePolicy(geometry)
        camera = CameraConfig()
        label = "route policy"
    else:
        from .checkpoint import load_model

        model = load_model(model_path)
        policy = ModelPolicy(model)
        camera = CameraConfig(height_px=model.config.image_height, width_px=model.config.image_width)
        label = Path(model_path).stem
    renderer = Renderer(build_world(loaded.net_path), RasterConfig(camera=camera))
    with _single_torch_thread(model_path is not None):
        result = drive(
            loaded, geometry, policy, seed=seed, max_s=max_s, config=config,
            renderer=renderer if model_path is not None else None,
        )
    metrics = {
        "route": route,
        "scenario": scenario_name,
        "edges": list(edges),
        "model": str(model_path) if model_path is not None else "",
        "seed": int(seed),
        "vehicle_length_m": result.vehicle_length_m,
        "vehicle_width_m": result.vehicle_width_m,
        **result.metrics,
    }
    write_drive_outputs(result, loaded, renderer, Path(out_dir), metrics, label, video=video)
    return metrics


@contextlib.contextmanager
def _single_torch_thread(active: bool):
    """One torch thread while a model drives: one sample a step gains nothing from more, and on a
    busy machine the threads' spinning made a step 100 times slower (docs/drive.md)."""
    if not active:
        yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
