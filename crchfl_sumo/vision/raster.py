"""Per-frame camera images: the static world's ground, other vehicles, traffic lights, sky.

``Renderer(world, config).render(frame, vehicle_ids)`` -> uint8 RGB array
[vehicles, 4, H, W, 3], cameras in labels.CAMERA_NAMES order. It reads a Frame
only; it never talks to the simulator.

Method (docs/raster.md has the reasoning and figures):
  ground   A camera is fixed on its vehicle, so the ground point each pixel
           sees is fixed in the VEHICLE frame; it is computed once
           (camera.ground_rays). Per ego only the rigid 2-D transform
           vehicle -> world changes: one cv2.transform per texture level maps
           the fixed ground points of all four cameras to texture pixels, and
           one cv2.remap per run of rows sharing a level samples the world
           texture (far rows: coarse levels, so lines do not break up). Pixels
           whose ray misses the ground within ``max_ground_distance_m`` are sky.
  objects  Other vehicles (boxes 0..vehicle_height_m) and the signal heads
           (pole + housing boxes at each stop line) are projected for all
           (ego, object) pairs in range at once; faces turned away from the
           camera are dropped, the rest are filled far to near (painter's
           order by distance to the box centre), after clipping at the near
           plane. A head's lit lamp is a disc on the face towards the traffic,
           never smaller than ``lamp_min_radius_px``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Sequence

import cv2
import numpy as np

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.vision.camera import (
    CAMERA_NAMES,
    MAX_WIDTH_PX,
    CameraConfig,
    camera_from_vehicle,
    ground_rays,
)
from crchfl_sumo.vision.camera_reach import CameraReach
from crchfl_sumo.vision.objects import (
    FACE_SHADE,
    FACES,
    HEAD_BOTTOM_M,
    HEAD_DEPTH_M,
    HEAD_HEIGHT_M,
    HEAD_WIDTH_M,
    HOUSING_RGB,
    LAMP_HEIGHTS_M,
    LAMP_PLACE,
    LAMP_RADIUS_M,
    LAMP_RGB,
    POLE_RGB,
    POLE_SIZE_M,
    REAR_FACE,
    box_corners,
    lit_lamps,
    vehicle_rgb,
)
from crchfl_sumo.vision.world import SKY_RGB, World, WorldConfig

_SHIFT = 4  # fixed-point bits for cv2 polygon filling
_FAR_AWAY_M = 1.0e7


# At 64 x 128 a vehicle 300 m off is under a pixel; a kilometre bounds what any image size shows.
MAX_DRAW_DISTANCE_M = 1000.0
MAX_VEHICLE_HEIGHT_M = 10.0  # the tallest road vehicles stand about 4.5 m


@dataclass(frozen=True)
class RasterConfig:
    """Per-frame rendering settings.

    camera                 image size, FOV and poses (camera.CameraConfig)
    max_ground_distance_m  ground farther than this (horizontally) is drawn as sky [m];
                           at 64 x 128, 40 m is 1.4 px below CamH's horizon
    max_object_distance_m  vehicles and signal heads farther than this are not drawn [m]
    vehicle_height_m       height of the vehicle boxes [m]
    lamp_min_radius_px     a lit lamp is never drawn smaller, so that a signal
                           30 m away still covers pixels at the default size (2.5 px:
                           a 5 px disc at 64 x 128 that the pedal branch can tell
                           red from green by; docs/model.md)
    interpolation          ground texture sampling, "nearest" (fast) or "linear"
    mark_permissive        a permissive green (SUMO 'g': go but yield, e.g. a left
                           turn across oncoming traffic) lights in its own colour
                           (objects.LAMP_PERMISSIVE_RGB) instead of green; off by
                           default: measured, it did not help (docs/raster.md)
    route_signal           of the heads of the lane a camera's vehicle approaches its next
                           signal on, only the one of the link its route takes lights (an
                           ideal reader of arrow lamps: side by side, a lane's heads are too
                           close to tell apart at 64 x 128, so a red and a green one merged);
                           the vehicle's link is SUMO's (Frame.tls_ahead_link). On by default
                           since 2026-12-06 (with the stop head, about 7 times fewer red lights;
                           docs/model.md); a camera block written before has no key and drew
                           every head (camera_settings reads it so)
    """

    camera: CameraConfig = field(default_factory=CameraConfig)
    max_ground_distance_m: float = 40.0
    max_object_distance_m: float = 60.0
    vehicle_height_m: float = 1.5
    lamp_min_radius_px: float = 2.5
    interpolation: Literal["nearest", "linear"] = "nearest"
    mark_permissive: bool = False
    route_signal: bool = True

    def __post_init__(self):
        for name in ("max_ground_distance_m", "max_object_distance_m"):
            check_range(getattr(self, name), f"raster.{name}", 0, MAX_DRAW_DISTANCE_M, "metres", lo_open=True)
        check_range(self.vehicle_height_m, "raster.vehicle_height_m", 0, MAX_VEHICLE_HEIGHT_M, "metres", lo_open=True)
        check_range(self.lamp_min_radius_px, "raster.lamp_min_radius_px", 0, MAX_WIDTH_PX, "pixels")
        if self.interpolation not in ("nearest", "linear"):
            raise CrchflError(f"raster.interpolation: {self.interpolation!r} is not 'nearest' or 'linear'")


def _clip_near(polygon: np.ndarray, near_m: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon [N, 3] to z >= near_m."""
    out = []
    for i in range(len(polygon)):
        a, b = polygon[i], polygon[(i + 1) % len(polygon)]
        a_in, b_in = a[2] >= near_m, b[2] >= near_m
        if a_in:
            out.append(a)
        if a_in != b_in:
            t = (near_m - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out).reshape(-1, 3)


# A vehicle is drawn when its centre lies within max_object_distance_m plus its half diagonal of the
# ego's centre; SUMO measures between front bumpers, which adds up to half of each length. 40 m covers
# vehicles up to 26 m long (a longer one at the very edge of the view could be missed).
NEIGHBOURHOOD_MARGIN_M = 40.0


def neighbourhood_m(config: RasterConfig) -> float:
    """Radius around a rendered vehicle (front bumper) that holds every vehicle its cameras may draw."""
    return config.max_object_distance_m + NEIGHBOURHOOD_MARGIN_M


class Renderer:
    """Renders frames of one world with one camera rig; holds only precomputed tables."""

    def __init__(self, world: World, config: RasterConfig | None = None):
        self.world = world
        self.config = config or RasterConfig()
        cam = self.config.camera
        reach_m = self.config.max_ground_distance_m + max(math.hypot(p.x_m, p.y_m) for p in cam.poses)
        if world.config.margin_m < reach_m:
            raise CrchflError(
                f"world.margin_m: {world.config.margin_m} m of ground around the network is less than "
                f"raster.max_ground_distance_m plus the camera offset ({reach_m:.1f} m); cameras near the "
                "network's edge would see sky on the ground. Raise world.margin_m or lower max_ground_distance_m"
            )
        self.shape = (len(CAMERA_NAMES), cam.height_px, cam.width_px, 3)
        self._intrinsics = cam.intrinsics()
        self._cam_from_vehicle = np.stack([camera_from_vehicle(p)[:3] for p in cam.poses])  # [4, 3, 4]
        self._interp = cv2.INTER_NEAREST if self.config.interpolation == "nearest" else cv2.INTER_LINEAR
        self._prepare_ground()
        self._prepare_heads()
        self._reach = CameraReach.of(cam, self.config.max_object_distance_m)
        self._vehicle_face_rgb: dict[str, list] = {}  # vehicle id -> shaded colour of each face

    # -- precomputation -------------------------------------------------------------
    def _prepare_ground(self) -> None:
        """Fixed ground points of every pixel, grouped into runs of rows that share a texture level."""
        cam = self.config.camera
        world_cfg = self.world.config
        points_by_level: list[list[np.ndarray]] = [[] for _ in range(world_cfg.levels)]
        counts = [0] * world_cfg.levels
        self._first_row, self._runs = [], []  # run: (camera, first row, end row, level, slice)
        for c in range(len(CAMERA_NAMES)):
            ground, hits = ground_rays(cam, c, self.config.max_ground_distance_m)
            rows_with_ground = np.flatnonzero(hits.any(axis=1))
            first = int(rows_with_ground[0]) if len(rows_with_ground) else cam.height_px
            self._first_row.append(first)
            # A ray that misses the ground is sent 10,000 km away: off the texture,
            # where the border colour is the sky, whatever the ego's pose.
            points = np.where(hits[:, :, None], ground, _FAR_AWAY_M)
            levels = _row_levels(ground, hits, world_cfg)
            row = first
            while row < cam.height_px:
                end = row + 1
                while end < cam.height_px and levels[end] == levels[row]:
                    end += 1
                level = int(levels[row])
                block = points[row:end].reshape(-1, 2)
                points_by_level[level].append(block)
                self._runs.append((c, row, end, level, slice(counts[level], counts[level] + len(block))))
                counts[level] += len(block)
                row = end
        self._ground_points = [
            np.concatenate(blocks).astype(np.float32).reshape(-1, 1, 2) if blocks else None
            for blocks in points_by_level
        ]

    def _prepare_heads(self) -> None:
        heads = self.world.heads
        n = len(heads)
        x = np.array([h.x_m for h in heads], dtype=np.float64)
        y = np.array([h.y_m for h in heads], dtype=np.float64)
        heading = np.array([h.heading_rad for h in heads], dtype=np.float64)
        poles = box_corners(x, y, heading, POLE_SIZE_M, POLE_SIZE_M, 0.0, HEAD_BOTTOM_M)
        housings = box_corners(
            x, y, heading, HEAD_DEPTH_M, HEAD_WIDTH_M, HEAD_BOTTOM_M, HEAD_BOTTOM_M + HEAD_HEIGHT_M
        )
        self._static_corners = np.concatenate([poles, housings]).reshape(-1, 8, 3)
        self._static_radius = np.concatenate(
            [np.full(n, POLE_SIZE_M / math.sqrt(2)), np.full(n, 0.5 * math.hypot(HEAD_DEPTH_M, HEAD_WIDTH_M))]
        )
        self._static_centres = np.concatenate([np.stack([x, y], 1), np.stack([x, y], 1)]).reshape(-1, 2)
        self._static_rgb = [POLE_RGB] * n + [HOUSING_RGB] * n
        self._static_head = np.concatenate([np.full(n, -1), np.arange(n)])  # housing -> head index
        self._static_face_rgb = [
            [tuple(int(v * shade) for v in colour) for shade in FACE_SHADE] for colour in self._static_rgb
        ]
        # Lamp centres [n, 3 lamps, 3]: on the housing's rear face, towards the traffic.
        face_offset = HEAD_DEPTH_M / 2.0 + 0.01
        lamps = np.empty((n, 3, 3))
        for k, z in enumerate(LAMP_HEIGHTS_M):
            lamps[:, k, 0] = x - np.cos(heading) * face_offset
            lamps[:, k, 1] = y - np.sin(heading) * face_offset
            lamps[:, k, 2] = z
        self._lamp_world = lamps
        # route_signal: per (signal, link), the other heads of its lane, which a vehicle taking that link
        # sees dark (none for a head that names no lane, as a hand-built RoadGeometry's may not)
        lane_heads: dict[tuple[str, str], set[int]] = {}
        for i, h in enumerate(heads):
            if h.lane_id:
                lane_heads.setdefault((h.tls_id, h.lane_id), set()).add(i)
        self._dark_for_link = {
            (h.tls_id, h.link_index): frozenset(lane_heads[(h.tls_id, h.lane_id)] - {i})
            for i, h in enumerate(heads) if h.lane_id
        }

    def _unlit_heads(self, frame: Frame, ego_rows: np.ndarray) -> list[frozenset[int]]:
        """Per ego, the heads route_signal leaves dark: the other links' heads of the lane of its next link."""
        return [self._dark_for_link.get((str(frame.tls_ahead_id[row]), int(frame.tls_ahead_link[row])), frozenset())
                for row in ego_rows.tolist()]

    # -- per frame ------------------------------------------------------------------
    def render(self, frame: Frame, vehicle_ids: Sequence[str], poses: np.ndarray | None = None) -> np.ndarray:
        """Camera images of each vehicle in ``vehicle_ids``: uint8 RGB [V, 4, H, W, 3].

        ``poses`` [V, 3] (x_m, y_m, heading_rad), when given, puts each
        vehicle's cameras there instead of at its pose in the frame (a recovery
        sample's perturbed pose); the other vehicles' cameras still see it
        where the frame has it. Rendering a frame's vehicles in one call shares
        the frame's set-up among them.
        """
        row_of = {vid: i for i, vid in enumerate(frame.ids.tolist())}
        missing = [vid for vid in vehicle_ids if vid not in row_of]
        if missing:
            raise KeyError(f"vehicles not in the frame at t={frame.t_s}: {missing[:5]}")
        ego_rows = np.array([row_of[vid] for vid in vehicle_ids], dtype=np.int64)
        out = np.empty((len(ego_rows),) + self.shape, np.uint8)
        if len(ego_rows) == 0:
            return out
        if poses is None:
            poses = np.stack([frame.x_m[ego_rows], frame.y_m[ego_rows], frame.heading_rad[ego_rows]], 1)
        poses = np.asarray(poses, dtype=np.float64).reshape(len(ego_rows), 3)
        vehicle_from_world = _vehicle_from_world_2d(poses)  # [E, 2, 3]
        texture_from_vehicle = _texture_from_vehicle(self.world.raster_from_world, poses)
        for e in range(len(ego_rows)):
            self._draw_ground(out[e], texture_from_vehicle[e])
        self._draw_objects(out, frame, ego_rows, poses[:, :2], vehicle_from_world)
        return out

    def _draw_ground(self, images: np.ndarray, texture_from_vehicle: np.ndarray) -> None:
        maps = [
            None if points is None else cv2.transform(points, texture_from_vehicle / 2**level)
            for level, points in enumerate(self._ground_points)
        ]
        width = self.config.camera.width_px
        for c, first in enumerate(self._first_row):
            images[c, :first] = SKY_RGB
        textures = self.world.textures
        for c, row, end, level, part in self._runs:
            cv2.remap(
                textures[level], maps[level][part].reshape(-1, width, 2), None, self._interp,
                dst=images[c, row:end], borderMode=cv2.BORDER_CONSTANT, borderValue=SKY_RGB,
            )

    def _draw_objects(self, out, frame, ego_rows, ego_xy, vehicle_from_world) -> None:
        cfg, cam = self.config, self.config.camera
        n_vehicles = len(frame)
        vehicle_corners = box_corners(
            frame.x_m, frame.y_m, frame.heading_rad, frame.length_m, frame.width_m, 0.0, cfg.vehicle_height_m
        )
        corners = np.concatenate([vehicle_corners, self._static_corners])
        centres = np.concatenate([np.stack([frame.x_m, frame.y_m], 1), self._static_centres])
        head_of_box = np.concatenate([np.full(n_vehicles, -1), self._static_head])

        # (ego, box) pairs some camera may see, the ego's own box excluded: a cheap
        # 2-D test first, so that the 3-D projection runs on few pairs.
        radii = np.concatenate([0.5 * np.hypot(frame.length_m, frame.width_m), self._static_radius])
        dist = np.hypot(centres[None, :, 0] - ego_xy[:, None, 0], centres[None, :, 1] - ego_xy[:, None, 1])
        near = dist <= cfg.max_object_distance_m + radii
        near[np.arange(len(ego_rows)), ego_rows] = False
        pair_ego, pair_box = np.nonzero(near)
        transforms = vehicle_from_world[pair_ego]
        rel = np.einsum("pij,pj->pi", transforms[:, :, :2], centres[pair_box]) + transforms[:, :, 2]
        seen = self._reach.may_see(rel, radii[pair_box])  # [P, 4]
        keep = seen.any(axis=1)
        pair_ego, pair_box, seen = pair_ego[keep], pair_box[keep], seen[keep]
        if len(pair_ego) == 0:
            return

        # camera_from_world for each ego and camera: [E, 4, 3, 4].
        rot = np.zeros((len(ego_rows), 3, 3))
        rot[:, :2, :2] = vehicle_from_world[:, :, :2]
        rot[:, 2, 2] = 1.0
        trans = np.zeros((len(ego_rows), 3))
        trans[:, :2] = vehicle_from_world[:, :, 2]
        cam_rot, cam_trans = self._cam_from_vehicle[:, :, :3], self._cam_from_vehicle[:, :, 3]
        cfw_rot = np.matmul(cam_rot[None], rot[:, None])  # [E, 4, 3, 3]
        cfw_trans = np.matmul(cam_rot[None], trans[:, None, :, None])[..., 0] + cam_trans  # [E, 4, 3]
        pts = (
            np.matmul(corners[pair_box][:, None], cfw_rot[pair_ego].transpose(0, 1, 3, 2))
            + cfw_trans[pair_ego][:, :, None, :]
        )  # [P, 4 cams, 8 corners, 3]
        x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
        k = self._intrinsics
        tan_x = (k[0, 2] + 0.5) / k[0, 0]
        tan_y = (k[1, 2] + 0.5) / k[1, 1]
        outside = (
            ~seen
            | (z < cam.near_m).all(-1)
            | (x > tan_x * z).all(-1) | (x < -tan_x * z).all(-1)
            | (y > tan_y * z).all(-1) | (y < -tan_y * z).all(-1)
        )
        face_centres = pts[:, :, FACES].mean(axis=3)  # [P, 4, 6, 3]
        box_centres = pts.mean(axis=2)  # [P, 4, 3]
        facing = ((face_centres - box_centres[:, :, None]) * face_centres).sum(-1) < 0  # [P, 4, 6]
        depth = np.sqrt((box_centres**2).sum(-1))
        behind = z < cam.near_m  # [P, 4, 8]
        clip = behind[:, :, FACES].any(-1)  # [P, 4, 6]
        uv = pts[..., :2] / np.maximum(z, cam.near_m)[..., None] * k[[0, 1], [0, 1]] + k[:2, 2]
        uv_int = np.round(uv * (1 << _SHIFT)).astype(np.int32)
        uv_fixed = np.ascontiguousarray(uv_int[:, :, FACES])  # [P, 4, 6, 4, 2]

        # Draw list: visible faces of boxes in view, per (ego, camera) far to near.
        p_idx, c_idx, f_idx = np.nonzero(facing & ~outside[:, :, None])
        if len(p_idx) == 0:
            return
        order = np.lexsort((f_idx, -depth[p_idx, c_idx], c_idx, pair_ego[p_idx]))
        p_idx, c_idx, f_idx = p_idx[order], c_idx[order], f_idx[order]
        polygons = uv_fixed[p_idx, c_idx, f_idx]  # [N, 4, 2], contiguous
        box_idx = pair_box[p_idx].tolist()
        face_rgb = self._face_rgb(frame)
        images = [[out[e, c] for c in range(len(CAMERA_NAMES))] for e in range(len(ego_rows))]
        lamps = lit_lamps(self.world, frame.tls_states, self.config.mark_permissive) if len(self.world.heads) else []
        head_of = head_of_box.tolist()
        dark = self._unlit_heads(frame, ego_rows) if cfg.route_signal else [frozenset()] * len(ego_rows)
        rows = zip(p_idx.tolist(), pair_ego[p_idx].tolist(), c_idx.tolist(), f_idx.tolist(), box_idx,
                   clip[p_idx, c_idx, f_idx].tolist())
        for i, (p, e, c, f, b, needs_clip) in enumerate(rows):
            image = images[e][c]
            if needs_clip:
                self._fill_clipped(image, pts[p, c, FACES[f]], face_rgb[b][f])
            else:
                cv2.fillConvexPoly(image, polygons[i], face_rgb[b][f], cv2.LINE_8, _SHIFT)
            if f == REAR_FACE and head_of[b] >= 0 and lamps[head_of[b]] and head_of[b] not in dark[e]:
                camera_from_world = np.hstack([cfw_rot[e, c], cfw_trans[e, c][:, None]])
                self._draw_lamps(image, camera_from_world, head_of[b], lamps[head_of[b]])

    def _face_rgb(self, frame: Frame) -> list:
        """Shaded colour of every face of every box: [box][face] -> (r, g, b).

        A vehicle's colours follow from its id alone, so they are worked out once per id.
        """
        known = self._vehicle_face_rgb
        ids = frame.ids.tolist()
        for vid in ids:
            if vid not in known:
                known[vid] = [tuple(int(v * shade) for v in vehicle_rgb(vid)) for shade in FACE_SHADE]
        return [known[vid] for vid in ids] + self._static_face_rgb

    def _fill_clipped(self, image: np.ndarray, polygon_cam: np.ndarray, rgb) -> None:
        clipped = _clip_near(polygon_cam, self.config.camera.near_m)
        if len(clipped) < 3:
            return
        k = self._intrinsics
        uv = clipped[:, :2] / clipped[:, 2:3] * k[[0, 1], [0, 1]] + k[:2, 2]
        # Points just past the near plane project far away; cv2 needs them within int range.
        uv = np.clip(uv, -1e5, 1e5)
        cv2.fillConvexPoly(image, np.round(uv * (1 << _SHIFT)).astype(np.int32), rgb, cv2.LINE_8, _SHIFT)

    def _draw_lamps(
        self, image: np.ndarray, camera_from_world: np.ndarray, head: int, lamps: tuple[int, ...]
    ) -> None:
        k = self._intrinsics
        places = [LAMP_PLACE[lamp] for lamp in lamps]
        centres = self._lamp_world[head, places] @ camera_from_world[:, :3].T + camera_from_world[:, 3]
        for lamp, centre in zip(lamps, centres):
            if centre[2] < self.config.camera.near_m:
                continue
            u = k[0, 0] * centre[0] / centre[2] + k[0, 2]
            v = k[1, 1] * centre[1] / centre[2] + k[1, 2]
            radius = max(self.config.lamp_min_radius_px, k[0, 0] * LAMP_RADIUS_M / centre[2])
            scale = 1 << _SHIFT
            cv2.circle(
                image, (int(round(u * scale)), int(round(v * scale))), int(round(radius * scale)),
                LAMP_RGB[lamp], -1, cv2.LINE_8, _SHIFT,
            )


def _vehicle_from_world_2d(poses: np.ndarray) -> np.ndarray:
    """[E, 2, 3] affine maps world (x, y) -> vehicle (forward, left) for poses [E, 3] (x, y, heading)."""
    x, y, heading = (np.ascontiguousarray(column) for column in poses.T)
    c, s = np.cos(heading), np.sin(heading)
    out = np.empty((len(poses), 2, 3))
    out[:, 0] = np.stack([c, s, -(c * x + s * y)], 1)
    out[:, 1] = np.stack([-s, c, s * x - c * y], 1)
    return out


def _row_levels(ground: np.ndarray, hits: np.ndarray, config) -> np.ndarray:
    """Texture level for each image row: the finest whose lines are as wide as the pixel spacing.

    A pixel's spacing is the distance between its ground point and its
    neighbours', the smaller of across and along the row (a line is missed only
    when pixels straddle it both ways); a row's spacing is the largest over its
    middle half, where lane lines mostly are. Level k lines are
    max(marking width, texel) wide.
    """
    height, width = hits.shape
    across = np.full((height, width), np.inf)
    across[:, 1:] = np.linalg.norm(np.diff(ground, axis=1), axis=-1)
    along = np.full((height, width), np.inf)
    along[:-1] = np.linalg.norm(np.diff(ground, axis=0), axis=-1)
    valid = hits.copy()
    valid[:, 1:] &= hits[:, :-1]
    spacing = np.where(valid, np.minimum(across, along), np.nan)[:, width // 4 : (3 * width) // 4 + 1]
    all_nan = np.isnan(spacing).all(axis=1)
    row_spacing = np.where(all_nan, np.inf, np.nanmax(np.where(all_nan[:, None], 0.0, spacing), axis=1))
    texel = config.metres_per_pixel * 2.0 ** np.arange(config.levels)
    line_width = np.maximum(config.marking_width_m, texel)
    # finest level whose line width covers the spacing; the coarsest when none does
    covered = line_width[None, :] >= row_spacing[:, None]
    return np.where(covered.any(axis=1), covered.argmax(axis=1), config.levels - 1)


def _texture_from_vehicle(raster_from_world: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """[E, 2, 3] affine maps vehicle (forward, left) metres -> world texture pixels, for poses [E, 3]."""
    x, y, heading = (np.ascontiguousarray(column) for column in poses.T)
    c, s = np.cos(heading), np.sin(heading)
    world_from_vehicle = np.empty((len(poses), 3, 3))
    world_from_vehicle[:, 0] = np.stack([c, -s, x], 1)
    world_from_vehicle[:, 1] = np.stack([s, c, y], 1)
    world_from_vehicle[:, 2] = (0.0, 0.0, 1.0)
    return raster_from_world @ world_from_vehicle


def render_frame(world: World, config: RasterConfig, frame: Frame, vehicle_ids: Sequence[str]) -> np.ndarray:
    """One-off convenience: build a Renderer and render (reuse a Renderer for many frames)."""
    return Renderer(world, config).render(frame, vehicle_ids)


def camera_settings(camera: dict, where: str) -> tuple[RasterConfig, WorldConfig]:
    """(RasterConfig, WorldConfig) of a data set's camera block (Manifest.camera, or a checkpoint's copy of it)."""
    if not isinstance(camera, dict):
        raise CrchflError(f"{where}: expected a table of raster and world settings, got {type(camera).__name__}")
    raster = camera.get("raster", {})
    if isinstance(raster, dict):  # written before route_signal (or at its old default, left out): every head lit
        raster = {"route_signal": False, **raster}
    raster = from_mapping(RasterConfig, raster, f"{where}.raster")
    world = from_mapping(WorldConfig, camera.get("world", {}), f"{where}.world")
    return raster, world

