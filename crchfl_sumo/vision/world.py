"""The static world of a SUMO network, painted once into top-down ground textures.

Two steps, so that tests can build worlds without SUMO:
  road_geometry_from_net(path)  .net.xml -> RoadGeometry (polygons, polylines,
                                signal heads; plain numpy, world metres)
  paint_world(geometry, config) RoadGeometry -> World (RGB textures at
                                ``metres_per_pixel`` x 1, 2, 4 ... + the signal heads)

Lane markings follow what SUMO's lane attributes imply (SUMO stores no paint):
  - right edge of the rightmost vehicle lane: solid white edge line (inset
    EDGE_LINE_INSET_M, so it stays apart from the light kerb);
  - between two lanes of one edge: dashed white when SUMO lets a passenger car
    change across it (``changeLeft``/``changeRight`` unset or listing it),
    solid white otherwise;
  - left edge of the leftmost lane: yellow centre line when an edge runs the
    other way alongside (dashed when the lane has an opposite-direction
    ``neigh`` lane, i.e. overtaking is allowed, else solid); else white edge line;
  - a solid white stop line across every signal-controlled lane at its end.
Kerb and sidewalk bands are painted around all road surface (many imported
networks, CARLA's towns among them, have no sidewalk lanes); pedestrian-only
lanes are painted as sidewalk too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import sumolib

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range

# RGB colours of the ground texture and the sky.
SKY_RGB = (135, 185, 235)
OFFROAD_RGB = (92, 118, 70)
SIDEWALK_RGB = (165, 165, 160)
KERB_RGB = (215, 215, 210)
ROAD_RGB = (68, 68, 72)
JUNCTION_RGB = (82, 82, 88)
WHITE_RGB = (235, 235, 235)
YELLOW_RGB = (230, 190, 40)

# Edge lines sit this far inside the road edge, so they do not merge into the kerb.
EDGE_LINE_INSET_M = 0.25


MAX_TEXTURE_MPX = 4000.0  # a texture of this many million pixels, at several levels, takes tens of GB
MAX_PAINT_M = 100.0  # no painted band, line or dash of a street is longer or wider
MAX_MARGIN_M = 1000.0  # off-road ground beyond the farthest a camera draws (raster: at most 1000 m)


@dataclass(frozen=True)
class WorldConfig:
    """How the static world is painted.

    metres_per_pixel  ground texture resolution [m/px]; 0.1 keeps a 0.15 m line >= 1 px
    margin_m          off-road ground painted around the network's bounding box [m];
                      must cover raster.max_ground_distance_m plus the camera offset
    sidewalk_width_m  sidewalk band around all road surface [m]
    kerb_width_m      kerb band between road and sidewalk [m]
    marking_width_m   lane and centre line width [m]
    stop_line_width_m stop line width [m]
    dash_length_m, dash_gap_m  dashed line pattern [m]
    levels            textures at metres_per_pixel * 1, 2, 4 ...: far pixels sample
                      coarse levels, whose lines are >= 1 texel wide (mip-mapping),
                      so that markings do not break up with distance
    max_texture_mpx   largest base texture [million pixels] painted; painting needs
                      about 11 bytes a pixel at its peak (scale200's 122 Mpx: 1.4 GB),
                      so a larger network is refused with the resolution that fits
    """

    metres_per_pixel: float = 0.1
    margin_m: float = 45.0
    sidewalk_width_m: float = 2.0
    kerb_width_m: float = 0.25
    marking_width_m: float = 0.15
    stop_line_width_m: float = 0.5
    dash_length_m: float = 3.0
    dash_gap_m: float = 6.0
    levels: int = 4
    max_texture_mpx: float = 400.0

    def __post_init__(self):
        if not 1 <= self.levels <= 8:
            raise CrchflError(f"world.levels: {self.levels} is outside 1..8; 4 is the default")
        if not 0.01 <= self.metres_per_pixel <= 1.0:
            raise CrchflError(
                f"world.metres_per_pixel: {self.metres_per_pixel} is outside 0.01..1.0; 0.1 is the default"
            )
        check_range(self.margin_m, "world.margin_m", 0, MAX_MARGIN_M, "metres")
        for name in ("sidewalk_width_m", "kerb_width_m"):
            check_range(getattr(self, name), f"world.{name}", 0, MAX_PAINT_M, "metres")
        for name in ("marking_width_m", "stop_line_width_m", "dash_length_m", "dash_gap_m"):
            check_range(getattr(self, name), f"world.{name}", 0, MAX_PAINT_M, "metres", lo_open=True)
        if self.max_texture_mpx <= 0.0:
            raise CrchflError(f"world.max_texture_mpx: {self.max_texture_mpx} must be > 0")
        if self.max_texture_mpx > MAX_TEXTURE_MPX:
            raise CrchflError(
                f"world.max_texture_mpx: {self.max_texture_mpx} is over {MAX_TEXTURE_MPX:g} million pixels, "
                "more than a machine's memory holds; 400 is the default"
            )


@dataclass(frozen=True)
class Marking:
    """A painted line along ``points`` [N, 2] (world metres)."""

    points: np.ndarray
    dashed: bool
    rgb: tuple[int, int, int]


@dataclass(frozen=True)
class SignalHead:
    """One traffic-light head at a stop line, for one link of one signal.

    (x_m, y_m) is the foot of its pole; heading_rad the travel direction of the
    lane it controls (its lamps face the other way, towards the traffic).
    """

    x_m: float
    y_m: float
    heading_rad: float
    tls_id: str
    link_index: int
    lane_id: str = ""  # the lane it controls: a lane with several links has a head for each


@dataclass(frozen=True)
class RoadGeometry:
    """Everything the painter needs, in world metres; no SUMO objects."""

    road_polygons: list[np.ndarray]
    junction_polygons: list[np.ndarray] = field(default_factory=list)
    sidewalk_polygons: list[np.ndarray] = field(default_factory=list)
    markings: list[Marking] = field(default_factory=list)
    stop_lines: list[np.ndarray] = field(default_factory=list)
    signal_heads: list[SignalHead] = field(default_factory=list)


@dataclass(frozen=True)
class World:
    """The painted ground textures and the signal heads: what per-frame rendering reads.

    textures           level k: [Ht / 2^k, Wt / 2^k, 3] uint8 RGB, north up, at
                       metres_per_pixel * 2^k (level 0 is the full resolution)
    raster_from_world  2x3 affine: world (x, y) metres -> level-0 texture (u, v) pixels
    heads              the signal heads, in a fixed order
    """

    textures: tuple[np.ndarray, ...]
    raster_from_world: np.ndarray
    heads: tuple[SignalHead, ...]
    config: WorldConfig

    @property
    def texture(self) -> np.ndarray:
        """The full-resolution texture (level 0)."""
        return self.textures[0]

    def raster_from_world_at(self, level: int) -> np.ndarray:
        """2x3 affine: world metres -> pixels of texture level ``level``."""
        return self.raster_from_world / 2**level


def offset_polyline(points: np.ndarray, offset_m: float) -> np.ndarray:
    """Shift a polyline sideways by ``offset_m`` (positive = to the left of travel)."""
    points = np.asarray(points, dtype=np.float64)
    seg = np.diff(points, axis=0)
    seg_len = np.linalg.norm(seg, axis=1, keepdims=True)
    seg_dir = seg / np.maximum(seg_len, 1e-9)
    seg_left = np.stack([-seg_dir[:, 1], seg_dir[:, 0]], axis=1)
    # Vertex normals: mean of the adjacent segments' normals, lengthened so the
    # offset lines stay parallel to both segments (miter), capped at 2x on sharp bends.
    normals = np.vstack([seg_left[:1], seg_left[:-1] + seg_left[1:], seg_left[-1:]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-9)
    cos_half = np.ones(len(points))
    cos_half[1:-1] = np.einsum("ij,ij->i", normals[1:-1], seg_left[:-1])
    scale = 1.0 / np.clip(cos_half, 0.5, 1.0)
    return points + normals * (offset_m * scale)[:, None]


def lane_polygon(centre: np.ndarray, width_m: float) -> np.ndarray:
    """Closed outline of a lane of ``width_m`` around its centre polyline."""
    return np.vstack([offset_polyline(centre, width_m / 2.0), offset_polyline(centre, -width_m / 2.0)[::-1]])


def dash_segments(points: np.ndarray, dash_m: float, gap_m: float) -> list[np.ndarray]:
    """Cut a polyline into dashes of ``dash_m`` separated by ``gap_m``, starting with a dash."""
    points = np.asarray(points, dtype=np.float64)
    cumulative = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    dashes = []
    start = 0.0
    while start < cumulative[-1]:
        end = min(start + dash_m, cumulative[-1])
        inner = cumulative[(cumulative > start) & (cumulative < end)]
        stations = np.concatenate([[start], inner, [end]])
        dashes.append(np.stack([np.interp(stations, cumulative, points[:, i]) for i in (0, 1)], axis=1))
        start = end + gap_m
    return dashes


def _change_allowed(attribute: str | None) -> bool:
    """SUMO's changeLeft/changeRight: unset means every class may change."""
    if attribute is None:
        return True
    classes = attribute.split()
    return "all" in classes or "passenger" in classes


def _read_lane_change_rules(net_path: Path) -> dict[str, tuple[bool, bool]]:
    """lane id -> (passenger may change left, may change right); sumolib does not keep these."""
    rules = {}
    with sumolib.openz(str(net_path), "rb") as source:  # plain or gzipped, as SUMO reads them
        for lane in sumolib.xml.parse(source, "lane"):
            rules[lane.id] = (
                _change_allowed(lane.getAttributeSecure("changeLeft", None)),
                _change_allowed(lane.getAttributeSecure("changeRight", None)),
            )
    return rules


def _is_vehicle_lane(lane) -> bool:
    return lane.allows("passenger")


def road_geometry_from_net(net_path: str | Path) -> RoadGeometry:
    """Read a SUMO .net.xml into a RoadGeometry (marking rules: module doc)."""
    import sumolib  # imported here: only this edge of the module needs it

    net_path = Path(net_path)
    if not net_path.is_file():
        raise CrchflError(f"{net_path}: network file not found; pass the path of a SUMO .net.xml")
    try:
        net = sumolib.net.readNet(str(net_path), withInternal=True, withPrograms=True)
    except Exception as exc:  # sumolib raises bare exceptions on malformed XML
        raise CrchflError(f"{net_path}: cannot read as a SUMO network ({exc}); check the file") from None
    change_rules = _read_lane_change_rules(net_path)

    road, sidewalks, markings = [], [], []
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            shape = np.asarray(lane.getShape(), dtype=np.float64)
            if len(shape) < 2:
                continue
            polygon = lane_polygon(shape, lane.getWidth())
            (road if _is_vehicle_lane(lane) else sidewalks).append(polygon)
        if edge.getFunction() == "":
            markings.extend(_edge_markings(edge, change_rules))
    junctions = [
        np.asarray(node.getShape(), dtype=np.float64)
        for node in net.getNodes()
        if len(node.getShape()) >= 3
    ]

    stop_lines, heads = [], []
    for tls in net.getTrafficLights():
        links_by_lane: dict[str, tuple[object, set[int]]] = {}
        for in_lane, _out_lane, link_index in tls.getConnections():
            links_by_lane.setdefault(in_lane.getID(), (in_lane, set()))[1].add(int(link_index))
        for lane_id in sorted(links_by_lane):
            lane, link_indices = links_by_lane[lane_id]
            shape = np.asarray(lane.getShape(), dtype=np.float64)
            end, before = shape[-1], shape[-2]
            direction = (end - before) / max(np.linalg.norm(end - before), 1e-9)
            left = np.array([-direction[1], direction[0]])
            half = lane.getWidth() / 2.0
            stop_lines.append(np.stack([end + left * half, end - left * half]))
            heading = math.atan2(direction[1], direction[0])
            # Heads stand just right of the lane, one per link, stepping outwards.
            for step, link_index in enumerate(sorted(link_indices)):
                foot = end - left * (half + 0.4 + 0.4 * step)
                heads.append(SignalHead(float(foot[0]), float(foot[1]), heading, tls.getID(), link_index, lane_id))
    return RoadGeometry(road, junctions, sidewalks, markings, stop_lines, heads)


def _edge_markings(edge, change_rules: dict[str, tuple[bool, bool]]) -> list[Marking]:
    lanes = sorted((lane for lane in edge.getLanes() if _is_vehicle_lane(lane)), key=lambda lane: lane.getIndex())
    if not lanes:
        return []
    shapes = [np.asarray(lane.getShape(), dtype=np.float64) for lane in lanes]
    if any(len(s) < 2 for s in shapes):
        return []
    inset = EDGE_LINE_INSET_M
    out = [Marking(offset_polyline(shapes[0], -lanes[0].getWidth() / 2.0 + inset), False, WHITE_RGB)]
    for i in range(len(lanes) - 1):
        may_left = change_rules.get(lanes[i].getID(), (True, True))[0]
        may_right = change_rules.get(lanes[i + 1].getID(), (True, True))[1]
        line = offset_polyline(shapes[i], lanes[i].getWidth() / 2.0)
        out.append(Marking(line, may_left or may_right, WHITE_RGB))
    left_line = offset_polyline(shapes[-1], lanes[-1].getWidth() / 2.0)
    if _has_opposite_alongside(edge, left_line):
        out.append(Marking(left_line, lanes[-1].getNeigh() is not None, YELLOW_RGB))
    else:
        out.append(Marking(offset_polyline(shapes[-1], lanes[-1].getWidth() / 2.0 - inset), False, WHITE_RGB))
    return out


def _has_opposite_alongside(edge, left_line: np.ndarray) -> bool:
    """True when an edge between the same nodes runs the other way with its left edge on ours."""
    middle = left_line[len(left_line) // 2]
    for other in edge.getToNode().getOutgoing():
        if other.getToNode() is not edge.getFromNode() or other.getFunction() != "":
            continue
        vehicle_lanes = [lane for lane in other.getLanes() if _is_vehicle_lane(lane)]
        if not vehicle_lanes:
            continue
        leftmost = max(vehicle_lanes, key=lambda lane: lane.getIndex())
        other_line = offset_polyline(np.asarray(leftmost.getShape()), leftmost.getWidth() / 2.0)
        if np.min(np.linalg.norm(other_line - middle, axis=1)) < 1.0:
            return True
    return False


def _bounds(geometry: RoadGeometry) -> tuple[float, float, float, float]:
    shapes = geometry.road_polygons + geometry.junction_polygons + geometry.sidewalk_polygons
    if not shapes:
        raise CrchflError("road geometry has no road surface; the network has no lanes a car may use")
    everything = np.vstack(shapes)
    return (*everything.min(axis=0), *everything.max(axis=0))


_SHIFT = 4  # fixed-point bits for cv2 drawing: sub-pixel accurate outlines


def paint_world(geometry: RoadGeometry, config: WorldConfig | None = None) -> World:
    """Paint a RoadGeometry into a World: the base texture and its coarser levels (module doc)."""
    config = config or WorldConfig()
    x_min, y_min, x_max, y_max = _bounds(geometry)
    mpp = config.metres_per_pixel
    x0, y1 = x_min - config.margin_m, y_max + config.margin_m
    width_m, height_m = x_max - x_min + 2 * config.margin_m, y_max - y_min + 2 * config.margin_m
    width_px = int(math.ceil(width_m / mpp)) + 1
    height_px = int(math.ceil(height_m / mpp)) + 1
    if width_px * height_px > config.max_texture_mpx * 1e6:
        raise CrchflError(
            f"world.metres_per_pixel: the network's ground ({width_m:.0f} x {height_m:.0f} m with the margin) at "
            f"{mpp:g} m/px is {width_px * height_px / 1e6:.3g} million pixels, over world.max_texture_mpx = "
            f"{config.max_texture_mpx:g} (painting needs about {width_px * height_px * 11 / 2**30:.2g} GB); set "
            f"[world] metres_per_pixel = {_fitting_mpp(width_m, height_m, config.max_texture_mpx):g} or more, "
            "or raise max_texture_mpx if the memory is there"
        )
    raster_from_world = np.array([[1.0 / mpp, 0.0, -x0 / mpp], [0.0, -1.0 / mpp, y1 / mpp]])
    textures = []
    for level in range(config.levels):
        shrink = 2**level
        size_px = (-(-height_px // shrink), -(-width_px // shrink))  # ceiling division
        textures.append(_paint_level(geometry, config, raster_from_world / shrink, *size_px))
    textures = tuple(textures)
    return World(textures, raster_from_world, tuple(geometry.signal_heads), config)


def _fitting_mpp(width_m: float, height_m: float, max_mpx: float) -> float:
    """The finest resolution (to 1 mm) whose texture, as paint_world sizes it, has at most ``max_mpx`` Mpx."""
    mpp = math.ceil(math.sqrt(width_m * height_m / (max_mpx * 1e6)) * 1000) / 1000
    while (math.ceil(width_m / mpp) + 1) * (math.ceil(height_m / mpp) + 1) > max_mpx * 1e6:
        mpp += 0.001
    return round(mpp, 3)


def _paint_level(
    geometry: RoadGeometry, config: WorldConfig, raster_from_world: np.ndarray, height_px: int, width_px: int
) -> np.ndarray:
    """One texture level. Kerbs and lines are at least one texel wide, so that coarse
    levels, sampled by far pixels, still show them."""
    mpp = 1.0 / raster_from_world[0, 0]

    def to_px(points: np.ndarray) -> np.ndarray:
        uv = np.asarray(points, dtype=np.float64) @ raster_from_world[:, :2].T + raster_from_world[:, 2]
        return np.round(uv * (1 << _SHIFT)).astype(np.int32)

    def fill(image: np.ndarray, polygons: list[np.ndarray], value) -> None:
        if polygons:
            cv2.fillPoly(image, [to_px(p) for p in polygons], value, cv2.LINE_8, _SHIFT)

    road_mask = np.zeros((height_px, width_px), np.uint8)
    fill(road_mask, geometry.road_polygons + geometry.junction_polygons, 255)
    # Distance from the road surface, in pixels, gives the kerb and sidewalk bands.
    distance_px = cv2.distanceTransform(cv2.bitwise_not(road_mask), cv2.DIST_L2, 5)
    kerb_px = max(config.kerb_width_m / mpp, 1.0) if config.kerb_width_m > 0 else 0.0
    texture = np.empty((height_px, width_px, 3), np.uint8)
    texture[:] = OFFROAD_RGB
    texture[distance_px <= kerb_px + config.sidewalk_width_m / mpp] = SIDEWALK_RGB
    texture[distance_px <= kerb_px] = KERB_RGB
    fill(texture, geometry.sidewalk_polygons, SIDEWALK_RGB)
    fill(texture, geometry.road_polygons, ROAD_RGB)
    fill(texture, geometry.junction_polygons, JUNCTION_RGB)

    def line(points: np.ndarray, width_m: float, rgb) -> None:
        # A filled outline, not cv2.polylines: its thickness is whole pixels and uneven.
        fill(texture, [lane_polygon(points, max(width_m, mpp))], rgb)

    for marking in geometry.markings:
        pieces = (
            dash_segments(marking.points, config.dash_length_m, config.dash_gap_m)
            if marking.dashed
            else [marking.points]
        )
        for piece in pieces:
            line(piece, config.marking_width_m, marking.rgb)
    for stop_line in geometry.stop_lines:
        line(stop_line, config.stop_line_width_m, WHITE_RGB)
    return texture


def build_world(net_path: str | Path, config: WorldConfig | None = None) -> World:
    """The static world of a SUMO network: read it, paint it (done once per network)."""
    return paint_world(road_geometry_from_net(net_path), config)
