import math

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.dataset import DatasetConfig
from crchfl_sumo.data.expert import ExpertConfig, Track, expert_actions
from crchfl_sumo.data.recovery import camera_pose, draw_perturbations, perturbed_pose, recovery_steer
from crchfl_sumo.sumo.frame import make_frame

WHEELBASE_M = 2.9


def track_along(x, y, heading, speed_mps):
    n = len(x)
    return Track(
        "v", np.arange(n) * 0.01, np.asarray(x, float), np.asarray(y, float), np.asarray(heading, float),
        np.full(n, speed_mps), np.zeros(n), np.full(n, 2.6), np.full(n, 4.5),
    )


def straight_track(speed_mps=5.0):
    x = np.arange(0.0, 60.0, 0.1)  # east along y = 0
    return track_along(x, np.zeros_like(x), np.zeros_like(x), speed_mps)


def test_straight_road_offset_left_steers_right_by_the_pure_pursuit_value():
    # At 5 m/s the look-ahead is max(5 m, 0.8 s * 5 m/s) = 5 m: the target is (5, 0).
    # From (0, 1), heading 0: alpha = atan2(-1, 5), chord = sqrt(26),
    # kappa = 2 sin(alpha) / chord = -2 / 26, delta = atan(2.9 * -1/13) = -0.21948 rad,
    # steer = -delta / 40 deg = +0.31439 (right).
    steer = recovery_steer(straight_track(), [0], [[1.0, 0.0]])
    assert steer[0] == pytest.approx(0.31439, abs=1e-4)
    assert recovery_steer(straight_track(), [0], [[-1.0, 0.0]])[0] == pytest.approx(-0.31439, abs=1e-4)
    # Unperturbed: the expert's own label (0 on a straight road).
    assert recovery_steer(straight_track(), [0], [[0.0, 0.0]])[0] == pytest.approx(0.0, abs=1e-12)


def test_straight_road_yawed_left_steers_right():
    # On the track, turned 10 deg left: alpha = -10 deg, chord = 5 m,
    # kappa = 2 sin(-10 deg) / 5 = -0.069459, steer = atan(2.9 * 0.069459) / 40 deg = +0.28472.
    steer = recovery_steer(straight_track(), [0], [[0.0, 10.0]])
    assert steer[0] == pytest.approx(0.28472, abs=1e-4)


def test_curve_offsets_steer_back_onto_the_arc():
    # A left-hand circle of radius 20 m around (0, 20), driven from (0, 0) heading east at 10 m/s:
    # look-ahead 8 m, target at 8/20 = 0.4 rad along the arc: (20 sin 0.4, 20 - 20 cos 0.4) = (7.78837, 1.57878).
    radius = 20.0
    phi = np.arange(0.0, 2.0, 0.1 / radius)
    track = track_along(radius * np.sin(phi), radius - radius * np.cos(phi), phi, 10.0)
    # On the arc: kappa = 1/R = 0.05, steer = -atan(2.9 * 0.05) / 40 deg = -0.20626 (left).
    assert recovery_steer(track, [0], [[0.0, 0.0]])[0] == pytest.approx(-0.20626, abs=1e-4)
    assert expert_actions(track)[0, 1] == pytest.approx(-0.20626, abs=1e-4)
    # 1 m outside (right of) the arc, at (0, -1): dy = 2.57878, chord = 8.20428,
    # kappa = 2 sin(atan2(2.57878, 7.78837)) / 8.20428 = 0.076625 -> steer -0.31321: harder left, back in.
    assert recovery_steer(track, [0], [[-1.0, 0.0]])[0] == pytest.approx(-0.31321, abs=1e-4)
    # 1 m inside (left), at (0, 1): dy = 0.57878, kappa = 0.018978 -> steer -0.07876: less left, back out.
    assert recovery_steer(track, [0], [[1.0, 0.0]])[0] == pytest.approx(-0.07876, abs=1e-4)


def test_standing_samples_keep_steer_zero():
    track = straight_track(speed_mps=0.0)
    assert recovery_steer(track, [0], [[1.0, 10.0]])[0] == 0.0


def test_perturbed_pose_moves_left_of_the_heading_and_turns_ccw():
    x, y, h = perturbed_pose(np.array([10.0]), np.array([5.0]), np.array([math.pi / 2]), np.array([[1.0, 30.0]]))
    # Heading north: left is west.
    assert (x[0], y[0], h[0]) == pytest.approx((9.0, 5.0, math.pi / 2 + math.radians(30)))


def test_camera_pose_is_the_vehicles_pose_perturbed():
    frame = make_frame(ids=["a", "b"], x_m=[0.0, 10.0], y_m=[0.0, 0.0], heading_rad=[0.0, 0.0])
    x, y, heading = camera_pose(frame, "b", -0.5, -5.0)
    # Heading east: 0.5 m to the right is y = -0.5; turned 5 degrees clockwise.
    assert (x, y) == (10.0, -0.5) and heading == pytest.approx(math.radians(-5.0))
    assert camera_pose(frame, "a", 0.0, 0.0) == (0.0, 0.0, 0.0)
    assert frame.y_m[1] == 0.0  # the frame is untouched


def test_camera_pose_keeps_the_heading_within_pi():
    frame = make_frame(ids=["a"], x_m=[0.0], y_m=[0.0], heading_rad=[math.pi - 0.01])
    assert camera_pose(frame, "a", 0.0, 10.0)[2] == pytest.approx(math.pi - 0.01 + math.radians(10) - 2 * math.pi)


def test_draw_perturbations_picks_the_share_of_eligible_samples_within_bounds():
    eligible = np.array([True] * 80 + [False] * 20)
    draws = draw_perturbations(eligible, 0.25, 1.0, 15.0, np.random.default_rng(3))
    perturbed = np.any(draws != 0, axis=1)
    assert perturbed.sum() == 20 and not perturbed[80:].any()
    assert np.abs(draws[:, 0]).max() <= 1.0 and np.abs(draws[:, 1]).max() <= 15.0
    assert np.array_equal(draws, draw_perturbations(eligible, 0.25, 1.0, 15.0, np.random.default_rng(3)))
    assert not draw_perturbations(eligible, 0.0, 1.0, 15.0, np.random.default_rng(3)).any()


def test_recovery_settings_are_checked():
    assert DatasetConfig().recovery_share == 0.25
    with pytest.raises(CrchflError, match="dataset.recovery_share"):
        from_mapping(DatasetConfig, {"recovery_share": 1.5})
    with pytest.raises(CrchflError, match="dataset.recovery_lateral_m"):
        from_mapping(DatasetConfig, {"recovery_lateral_m": -1.0})
    with pytest.raises(CrchflError, match="dataset.recovery_yaw_deg"):
        from_mapping(DatasetConfig, {"recovery_yaw_deg": 90.0})
    assert ExpertConfig().max_steer_angle_deg == 40.0 and ExpertConfig().wheelbase_m == WHEELBASE_M
