from __future__ import annotations

import math

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.vision.camera import (
    CameraConfig,
    CameraPose,
    camera_from_vehicle,
    ground_rays,
    project_vehicle_points,
    vehicle_from_camera_rotation,
    vehicle_from_world,
)

CAM_H, CAM_F, CAM_L, CAM_R = range(4)


def test_focal_length_from_fov():
    config = CameraConfig(height_px=64, width_px=128, fov_deg=120.0)
    # Half the width spans tan(60 deg) at unit depth.
    assert config.focal_px == pytest.approx(64 / math.tan(math.radians(60)))
    k = config.intrinsics()
    assert (k[0, 2], k[1, 2]) == (63.5, 31.5)


@pytest.mark.parametrize("pose", CameraConfig().poses)
def test_rotations_are_proper(pose):
    rot = vehicle_from_camera_rotation(pose)
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)


def test_optical_axes_of_the_paper_rig():
    poses = CameraConfig().poses
    axis = [vehicle_from_camera_rotation(p)[:, 2] for p in poses]
    c50, s50 = math.cos(math.radians(50)), math.sin(math.radians(50))
    np.testing.assert_allclose(axis[CAM_H], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(axis[CAM_F], [c50, 0, -s50], atol=1e-12)
    np.testing.assert_allclose(axis[CAM_L], [0, c50, -s50], atol=1e-12)  # y is left
    np.testing.assert_allclose(axis[CAM_R], [0, -c50, -s50], atol=1e-12)
    # Image "up" of an unrolled camera points up in the world.
    assert vehicle_from_camera_rotation(poses[CAM_F])[2, 1] < 0


def test_point_straight_ahead_hits_the_principal_point():
    config = CameraConfig()
    pixels, depth = project_vehicle_points(config, CAM_H, np.array([[11.5, 0.0, 1.5]]))
    np.testing.assert_allclose(pixels[0], config.intrinsics()[:2, 2])
    assert depth[0] == pytest.approx(10.0)


def test_point_to_the_left_projects_left_of_centre():
    config = CameraConfig()
    pixels, _ = project_vehicle_points(config, CAM_H, np.array([[11.5, 2.0, 1.5]]))
    assert pixels[0, 0] == pytest.approx(63.5 - config.focal_px * 0.2)


def test_camera_from_vehicle_puts_the_camera_at_its_origin():
    pose = CameraPose(1.0, 1.2, 0.5, pitch_deg=-50, yaw_deg=90)
    transform = camera_from_vehicle(pose)
    np.testing.assert_allclose(transform @ [1.0, 1.2, 0.5, 1.0], [0, 0, 0, 1], atol=1e-12)


def test_vehicle_from_world():
    # Heading north: 3 m further north is 3 m ahead; 2 m west is 2 m to the left.
    transform = vehicle_from_world(10.0, 5.0, math.pi / 2)
    np.testing.assert_allclose(transform @ [10.0, 8.0, 0.0, 1.0], [3, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(transform @ [8.0, 5.0, 0.0, 1.0], [0, 2, 0, 1], atol=1e-12)


def test_ground_rays_by_hand():
    config = CameraConfig(height_px=64, width_px=128)
    ground, hits = ground_rays(config, CAM_F, max_distance_m=40.0)
    # CamF's optical axis meets the ground 1.5 / tan(50 deg) ahead of the camera.
    centre = (ground[31, 63] + ground[32, 64]) / 2  # mean of the pixels around the principal point
    assert centre[0] == pytest.approx(2.5 + 1.5 / math.tan(math.radians(50)), abs=0.05)
    assert hits.all()  # CamF looks down 50 deg; its top row is still 9 deg below the horizon
    ground_h, hits_h = ground_rays(config, CAM_H, max_distance_m=40.0)
    assert not hits_h[:32].any()  # at and above the horizon
    assert hits_h[-1].all()
    # Bottom row centre: depression angle atan(32 / f).
    depression = math.atan2(63 - 31.5, config.focal_px)
    assert ground_h[63, 63][0] == pytest.approx(1.5 + 1.5 / math.tan(depression), rel=1e-3)


def test_config_from_mapping_and_validation():
    config = from_mapping(
        CameraConfig,
        {"height_px": 48, "poses": [{"x_m": 1, "y_m": 0, "z_m": 1.5}] * 4},
        "camera",
    )
    assert config.height_px == 48 and config.poses[0].z_m == 1.5
    with pytest.raises(CrchflError, match="camera.poses"):
        CameraConfig(poses=CameraConfig().poses[:3])
    with pytest.raises(CrchflError, match="fov_deg"):
        CameraConfig(fov_deg=180.0)
    # ground_rays holds several float64 [H, W] arrays per camera: 4096 x 8192 would take gigabytes
    with pytest.raises(CrchflError, match="4096x8192 is too large; use at most 1080x1920"):
        CameraConfig(height_px=4096, width_px=8192)
    assert CameraConfig(height_px=1080, width_px=1920).width_px == 1920  # full HD is the largest accepted
