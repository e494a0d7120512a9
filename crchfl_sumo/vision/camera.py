"""Pinhole cameras mounted on a vehicle: 6-D poses, intrinsics from the field of view.

Frames used here (all right-handed, metres):
  world    SUMO's network frame: x east, y north, z up.
  vehicle  origin at the vehicle's centre on the ground, x forward, y LEFT, z up.
           (CARLA's vehicle frame is left-handed with y to the right; a CARLA
           pose (x, y, z, pitch, yaw, roll) becomes (x, -y, z, pitch, -yaw, roll).)
  camera   OpenCV's optical frame: x right, y down, z along the optical axis.

A pose's pitch is the optical axis' elevation (negative = looking down), its
yaw the axis' azimuth in the vehicle frame (positive = towards the left) and
its roll a rotation about the axis (positive = right side down).

Pixel convention: OpenCV's. Pixel (row i, column j) has its centre at image
coordinates (u, v) = (j, i), so the principal point of a W x H image is
((W - 1) / 2, (H - 1) / 2), and cv2 drawing functions take these coordinates
directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range

# The paper's four cameras, in the order every image array stores them.
CAMERA_NAMES = ("CamH", "CamF", "CamL", "CamR")


@dataclass(frozen=True)
class CameraPose:
    """Mounting of one camera in the vehicle frame (metres, degrees; module doc)."""

    x_m: float
    y_m: float
    z_m: float
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0
    roll_deg: float = 0.0


# The paper's rig (FACTS.md), converted to our right-handed vehicle frame.
DEFAULT_POSES = (
    CameraPose(1.5, 0.0, 1.5, pitch_deg=0.0),  # CamH
    CameraPose(2.5, 0.0, 1.5, pitch_deg=-50.0),  # CamF
    CameraPose(1.0, 1.2, 0.5, pitch_deg=-50.0, yaw_deg=90.0),  # CamL
    CameraPose(1.0, -1.2, 0.5, pitch_deg=-50.0, yaw_deg=-90.0),  # CamR
)


# The largest image a camera, a model or a data set may have (full HD): ground_rays and the renderer
# hold several float64 arrays of this size per camera, a few hundred MB; 4096 x 8192 would need tens of GB.
MAX_HEIGHT_PX = 1080
MAX_WIDTH_PX = 1920
MAX_NEAR_M = 10.0  # a near plane farther out clips away the car ahead (camera offsets are 1-2 m)


@dataclass(frozen=True)
class CameraConfig:
    """The four cameras' image size, field of view and poses (order: labels.CAMERA_NAMES).

    height_px, width_px  image size; default 64 x 128, see docs/raster.md for why
    fov_deg              horizontal field of view, 120 as in the paper
    poses                one CameraPose per camera, CamH, CamF, CamL, CamR
    near_m               near clipping plane of the projected boxes [m]
    """

    height_px: int = 64
    width_px: int = 128
    fov_deg: float = 120.0
    poses: tuple[CameraPose, ...] = field(default=DEFAULT_POSES)
    near_m: float = 0.05

    def __post_init__(self):
        if self.height_px < 8 or self.width_px < 8:
            raise CrchflError(
                f"camera.height_px/width_px: {self.height_px}x{self.width_px} is too small; use at least 8x8"
            )
        if self.height_px > MAX_HEIGHT_PX or self.width_px > MAX_WIDTH_PX:
            raise CrchflError(
                f"camera.height_px/width_px: {self.height_px}x{self.width_px} is too large; "
                f"use at most {MAX_HEIGHT_PX}x{MAX_WIDTH_PX}"
            )
        if not 1.0 <= self.fov_deg <= 170.0:
            raise CrchflError(f"camera.fov_deg: {self.fov_deg} is outside 1..170; a pinhole needs a finite FOV")
        if len(self.poses) != len(CAMERA_NAMES):
            raise CrchflError(
                f"camera.poses: got {len(self.poses)} poses, need {len(CAMERA_NAMES)} ({', '.join(CAMERA_NAMES)})"
            )
        check_range(self.near_m, "camera.near_m", 0, MAX_NEAR_M, "metres", lo_open=True)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (same for both axes: square pixels)."""
        return (self.width_px / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)

    def intrinsics(self) -> np.ndarray:
        """3x3 camera matrix K (module doc's pixel convention)."""
        f = self.focal_px
        return np.array(
            [[f, 0.0, (self.width_px - 1) / 2.0], [0.0, f, (self.height_px - 1) / 2.0], [0.0, 0.0, 1.0]]
        )


def vehicle_from_camera_rotation(pose: CameraPose) -> np.ndarray:
    """3x3 rotation whose columns are the camera's x (right), y (down), z (optical axis) in the vehicle frame."""
    pitch, yaw, roll = (math.radians(a) for a in (pose.pitch_deg, pose.yaw_deg, pose.roll_deg))
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(forward, right)
    right, down = (
        math.cos(roll) * right + math.sin(roll) * down,
        math.cos(roll) * down - math.sin(roll) * right,
    )
    return np.stack([right, down, forward], axis=1)


def camera_from_vehicle(pose: CameraPose) -> np.ndarray:
    """4x4 rigid transform taking vehicle-frame points to this camera's frame."""
    rot = vehicle_from_camera_rotation(pose)
    out = np.eye(4)
    out[:3, :3] = rot.T
    out[:3, 3] = -rot.T @ np.array([pose.x_m, pose.y_m, pose.z_m])
    return out


def vehicle_from_world(x_m: float, y_m: float, heading_rad: float) -> np.ndarray:
    """4x4 rigid transform taking world points to the frame of a vehicle at (x, y, heading)."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    out = np.eye(4)
    out[:2, :2] = [[c, s], [-s, c]]
    out[:2, 3] = [-(c * x_m + s * y_m), s * x_m - c * y_m]
    return out


def project(points_cam: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Camera-frame points [..., 3] (z > 0) -> pixel coordinates [..., 2]."""
    z = points_cam[..., 2:3]
    return (points_cam[..., :2] / z) * intrinsics[[0, 1], [0, 1]] + intrinsics[:2, 2]


def project_vehicle_points(config: CameraConfig, camera_index: int, points_vehicle: np.ndarray) -> np.ndarray:
    """Vehicle-frame points [N, 3] -> (pixels [N, 2], depth [N]) in camera ``camera_index``.

    Depth is the camera-frame z; pixels of points with depth <= 0 are meaningless.
    """
    transform = camera_from_vehicle(config.poses[camera_index])
    points = np.asarray(points_vehicle, dtype=np.float64) @ transform[:3, :3].T + transform[:3, 3]
    depth = points[:, 2]
    safe = np.where(depth[:, None] > 1e-9, points, np.nan)
    return project(safe, config.intrinsics()), depth


def ground_rays(config: CameraConfig, camera_index: int, max_distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the ground (z = 0), in the vehicle frame.

    Returns (ground_xy [H, W, 2] float64, hits [H, W] bool). A pixel misses the
    ground when its ray points at or above the horizon or meets the ground
    farther than ``max_distance_m`` from the camera (horizontally).
    """
    pose = config.poses[camera_index]
    rot = vehicle_from_camera_rotation(pose)
    k = config.intrinsics()
    cols, rows = np.meshgrid(np.arange(config.width_px), np.arange(config.height_px))
    rays_cam = np.stack(
        [(cols - k[0, 2]) / k[0, 0], (rows - k[1, 2]) / k[1, 1], np.ones(cols.shape)], axis=-1
    )
    rays = rays_cam @ rot.T
    down = -rays[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(down > 1e-9, pose.z_m / down, np.inf)
    horizontal_m = t * np.hypot(rays[..., 0], rays[..., 1])
    hits = horizontal_m <= max_distance_m
    t = np.where(hits, t, 0.0)
    ground = np.stack([pose.x_m + t * rays[..., 0], pose.y_m + t * rays[..., 1]], axis=-1)
    return ground, hits
