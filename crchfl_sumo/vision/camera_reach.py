"""Where each camera of a rig can see anything: the renderer's cheap 2-D cull of (ego, box) pairs
before it projects them (vision/raster.py; docs/raster.md, "Cheap cull")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crchfl_sumo.vision.camera import CameraConfig, vehicle_from_camera_rotation


@dataclass(frozen=True)
class CameraReach:
    """Where on the ground plane each camera can see anything at or above the ground.

    A camera whose highest pixel ray points below the horizon sees no point
    (z >= 0) farther than its height over the tangent of that ray's depression;
    none sees beyond ``max_object_distance_m`` nor outside the azimuths its rays span.
    """

    xy_m: np.ndarray  # [4, 2] camera positions, vehicle frame
    yaw_rad: np.ndarray  # [4]
    half_azimuth_rad: np.ndarray  # [4]
    reach_m: np.ndarray  # [4]

    @staticmethod
    def of(camera: CameraConfig, max_distance_m: float) -> "CameraReach":
        k = camera.intrinsics()
        cols, rows = np.meshgrid(np.arange(camera.width_px), np.arange(camera.height_px))
        rays_cam = np.stack([(cols - k[0, 2]) / k[0, 0], (rows - k[1, 2]) / k[1, 1], np.ones(cols.shape)], -1)
        xy, yaw, half_az, reach = [], [], [], []
        for pose in camera.poses:
            rays = rays_cam.reshape(-1, 3) @ vehicle_from_camera_rotation(pose).T
            horizontal = np.hypot(rays[:, 0], rays[:, 1])
            top = np.max(np.arctan2(rays[:, 2], horizontal))
            yaw_rad = math.radians(pose.yaw_deg)
            azimuth = np.angle(np.exp(1j * (np.arctan2(rays[:, 1], rays[:, 0]) - yaw_rad)))
            xy.append((pose.x_m, pose.y_m))
            yaw.append(yaw_rad)
            half_az.append(np.max(np.abs(azimuth)))
            reach.append(max_distance_m if top >= 0 else min(max_distance_m, pose.z_m / math.tan(-top)))
        return CameraReach(np.array(xy), np.array(yaw), np.array(half_az), np.array(reach))

    def may_see(self, rel_xy: np.ndarray, radii_m: np.ndarray) -> np.ndarray:
        """[N, 4]: may camera c see some of box n? Boxes: footprint centre (vehicle frame) and radius.

        Conservative: False only where the camera certainly cannot see the box.
        """
        d = rel_xy[:, None, :] - self.xy_m  # [N, 4, 2]
        dist = np.hypot(d[..., 0], d[..., 1])
        radii = radii_m[:, None]
        cos_yaw, sin_yaw = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        along = d[..., 0] * cos_yaw + d[..., 1] * sin_yaw
        across = d[..., 1] * cos_yaw - d[..., 0] * sin_yaw
        azimuth = np.arctan2(np.abs(across), along)  # off the camera's yaw, 0..pi
        widening = np.arcsin(np.clip(radii / np.maximum(dist, 1e-9), 0.0, 1.0))
        return (dist <= self.reach_m + radii) & ((azimuth <= self.half_azimuth_rad + widening) | (dist <= radii))
