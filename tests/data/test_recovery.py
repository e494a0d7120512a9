import math

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.settings import DatasetConfig
from crchfl_sumo.data.expert import ExpertConfig, Track, expert_actions
from crchfl_sumo.data.recovery import (
    QUEUE_CLOSE_M,
    QUEUE_GAP_MIN_M,
    RED_BACK_MAX_M,
    RED_BACK_MIN_M,
    camera_pose,
    draw_perturbations,
    draw_queue_shifts,
    draw_red_line_shifts,
    gap_ahead,
    perturbed_pose,
    recovery_steer,
)
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
    steer = recovery_steer(straight_track(), [0], [[1.0, 0.0, 0.0]])
    assert steer[0] == pytest.approx(0.31439, abs=1e-4)
    assert recovery_steer(straight_track(), [0], [[-1.0, 0.0, 0.0]])[0] == pytest.approx(-0.31439, abs=1e-4)
    # Unperturbed: the expert's own label (0 on a straight road).
    assert recovery_steer(straight_track(), [0], [[0.0, 0.0, 0.0]])[0] == pytest.approx(0.0, abs=1e-12)


def test_straight_road_yawed_left_steers_right():
    # On the track, turned 10 deg left: alpha = -10 deg, chord = 5 m,
    # kappa = 2 sin(-10 deg) / 5 = -0.069459, steer = atan(2.9 * 0.069459) / 40 deg = +0.28472.
    steer = recovery_steer(straight_track(), [0], [[0.0, 10.0, 0.0]])
    assert steer[0] == pytest.approx(0.28472, abs=1e-4)


def test_curve_offsets_steer_back_onto_the_arc():
    # A left-hand circle of radius 20 m around (0, 20), driven from (0, 0) heading east at 10 m/s:
    # look-ahead 8 m, target at 8/20 = 0.4 rad along the arc: (20 sin 0.4, 20 - 20 cos 0.4) = (7.78837, 1.57878).
    radius = 20.0
    phi = np.arange(0.0, 2.0, 0.1 / radius)
    track = track_along(radius * np.sin(phi), radius - radius * np.cos(phi), phi, 10.0)
    # On the arc: kappa = 1/R = 0.05, steer = -atan(2.9 * 0.05) / 40 deg = -0.20626 (left).
    assert recovery_steer(track, [0], [[0.0, 0.0, 0.0]])[0] == pytest.approx(-0.20626, abs=1e-4)
    assert expert_actions(track)[0, 1] == pytest.approx(-0.20626, abs=1e-4)
    # 1 m outside (right of) the arc, at (0, -1): dy = 2.57878, chord = 8.20428,
    # kappa = 2 sin(atan2(2.57878, 7.78837)) / 8.20428 = 0.076625 -> steer -0.31321: harder left, back in.
    assert recovery_steer(track, [0], [[-1.0, 0.0, 0.0]])[0] == pytest.approx(-0.31321, abs=1e-4)
    # 1 m inside (left), at (0, 1): dy = 0.57878, kappa = 0.018978 -> steer -0.07876: less left, back out.
    assert recovery_steer(track, [0], [[1.0, 0.0, 0.0]])[0] == pytest.approx(-0.07876, abs=1e-4)


def test_standing_samples_keep_steer_zero():
    track = straight_track(speed_mps=0.0)
    assert recovery_steer(track, [0], [[1.0, 10.0, 0.0]])[0] == 0.0


def test_perturbed_pose_moves_left_of_the_heading_and_turns_ccw():
    x, y, h = perturbed_pose(np.array([10.0]), np.array([5.0]), np.array([math.pi / 2]), np.array([[1.0, 30.0, 0.0]]))
    # Heading north: left is west.
    assert (x[0], y[0], h[0]) == pytest.approx((9.0, 5.0, math.pi / 2 + math.radians(30)))
    # Forward is along the heading before the turn: 2 m north, then 1 m west.
    x, y, h = perturbed_pose(np.array([10.0]), np.array([5.0]), np.array([math.pi / 2]), np.array([[1.0, 30.0, 2.0]]))
    assert (x[0], y[0], h[0]) == pytest.approx((9.0, 7.0, math.pi / 2 + math.radians(30)))


def test_camera_pose_is_the_vehicles_pose_perturbed():
    frame = make_frame(ids=["a", "b"], x_m=[0.0, 10.0], y_m=[0.0, 0.0], heading_rad=[0.0, 0.0])
    x, y, heading = camera_pose(frame, "b", -0.5, -5.0, 0.0)
    # Heading east: 0.5 m to the right is y = -0.5; turned 5 degrees clockwise.
    assert (x, y) == (10.0, -0.5) and heading == pytest.approx(math.radians(-5.0))
    assert camera_pose(frame, "a", 0.0, 0.0, 0.0) == (0.0, 0.0, 0.0)
    # 1.5 m forward (east) as well: x = 11.5.
    assert camera_pose(frame, "b", -0.5, 0.0, 1.5) == (11.5, -0.5, 0.0)
    assert frame.y_m[1] == 0.0  # the frame is untouched


def test_camera_pose_keeps_the_heading_within_pi():
    frame = make_frame(ids=["a"], x_m=[0.0], y_m=[0.0], heading_rad=[math.pi - 0.01])
    assert camera_pose(frame, "a", 0.0, 10.0, 0.0)[2] == pytest.approx(math.pi - 0.01 + math.radians(10) - 2 * math.pi)


def test_draw_perturbations_picks_the_share_of_eligible_samples_within_bounds():
    eligible = np.array([True] * 80 + [False] * 20)
    draws = draw_perturbations(eligible, 0.25, 1.0, 15.0, np.random.default_rng(3))
    perturbed = np.any(draws != 0, axis=1)
    assert draws.shape == (100, 3) and not draws[:, 2].any()  # forward shifts are queue samples' alone
    assert perturbed.sum() == 20 and not perturbed[80:].any()
    assert np.abs(draws[:, 0]).max() <= 1.0 and np.abs(draws[:, 1]).max() <= 15.0
    assert np.array_equal(draws, draw_perturbations(eligible, 0.25, 1.0, 15.0, np.random.default_rng(3)))
    assert not draw_perturbations(eligible, 0.0, 1.0, 15.0, np.random.default_rng(3)).any()


def test_recovery_settings_are_checked():
    assert DatasetConfig().recovery_share == 0.25
    with pytest.raises(CrchflError, match="dataset.recovery_share"):
        from_mapping(DatasetConfig, {"recovery_share": 1.5})
    with pytest.raises(CrchflError, match="dataset.recovery_red_share"):
        from_mapping(DatasetConfig, {"recovery_red_share": -0.1})
    with pytest.raises(CrchflError, match="dataset.recovery_lateral_m"):
        from_mapping(DatasetConfig, {"recovery_lateral_m": -1.0})
    with pytest.raises(CrchflError, match="dataset.recovery_yaw_deg"):
        from_mapping(DatasetConfig, {"recovery_yaw_deg": 90.0})
    assert ExpertConfig().max_steer_angle_deg == 40.0 and ExpertConfig().wheelbase_m == WHEELBASE_M


def queue_frame(leader_x_m, leader_speed_mps=0.0, leader_y_m=0.0, leader_heading_rad=0.0):
    """The ego at the origin heading east (length 4.5 m); one other vehicle (length 5 m)."""
    return make_frame(
        ids=["ego", "lead"], x_m=[0.0, leader_x_m], y_m=[0.0, leader_y_m], heading_rad=[0.0, leader_heading_rad],
        speed_mps=[0.0, leader_speed_mps], length_m=[4.5, 5.0],
    )


def test_gap_ahead_is_bumper_to_bumper_to_a_standing_leader_in_the_lane():
    # Centres 7.25 m apart, half lengths 2.25 + 2.5: a 2.5 m gap (SUMO's standstill minGap).
    assert gap_ahead(queue_frame(7.25), "ego", 0.1) == pytest.approx(2.5)
    assert gap_ahead(queue_frame(7.25, leader_y_m=1.4), "ego", 0.1) == pytest.approx(2.5)  # still in the lane
    for frame in (
        queue_frame(7.25, leader_speed_mps=3.0),  # moving: no queue
        queue_frame(-7.25),  # behind
        queue_frame(7.25, leader_y_m=3.5),  # the next lane
        queue_frame(7.25, leader_heading_rad=math.pi),  # oncoming
        make_frame(ids=["ego"], x_m=[0.0], y_m=[0.0], heading_rad=[0.0]),  # alone
    ):
        assert gap_ahead(frame, "ego", 0.1) == math.inf


def test_gap_ahead_takes_the_nearest_vehicle_ahead():
    # A moving car 2 m ahead hides the standing one behind it: no standing leader.
    frame = make_frame(ids=["ego", "near", "far"], x_m=[0.0, 6.75, 20.0], y_m=[0.0] * 3, heading_rad=[0.0] * 3,
                       speed_mps=[0.0, 2.0, 0.0], length_m=[4.5, 4.5, 4.5])
    assert gap_ahead(frame, "ego", 0.1) == math.inf


def test_queue_shifts_move_eligible_standing_samples_closer_than_sumo_stands():
    standing = np.array([True] * 6 + [False] * 2)
    gap = np.array([2.5, 2.5, 4.0, 1.5, 9.0, np.inf, 2.5, 2.5])
    shifts = draw_queue_shifts(standing, gap, 1.0, np.random.default_rng(0))
    # Eligible: standing with a gap in (2, 5] m (rows 0 to 2); the rest never move.
    assert np.all(shifts[:3] > 0) and not shifts[3:].any()
    left = gap[:3] - shifts[:3]  # the gap the shifted sample stands at
    assert np.all((left >= QUEUE_GAP_MIN_M) & (left <= QUEUE_CLOSE_M))
    assert np.array_equal(shifts, draw_queue_shifts(standing, gap, 1.0, np.random.default_rng(0)))
    assert np.count_nonzero(draw_queue_shifts(standing, gap, 1 / 3, np.random.default_rng(0))) == 1
    # Share 0 draws nothing: the generator is left as it was.
    rng = np.random.default_rng(5)
    assert not draw_queue_shifts(standing, gap, 0.0, rng).any()
    assert rng.uniform() == np.random.default_rng(5).uniform()


def test_red_line_shifts_move_eligible_standing_samples_back_from_their_red_line():
    standing = np.array([True, True, True, True, False, True])
    red_line_m = np.array([1.0, 2.9, 3.5, np.inf, 1.0, 1.0])
    queue = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.2])  # the last one is a queue sample already
    shifts = draw_red_line_shifts(standing, red_line_m, queue, 1.0, np.random.default_rng(0))
    # Eligible: standing, within 3 m of a red line, not queue-shifted (rows 0 and 1); they move 1 to 6 m back.
    assert np.all((shifts[:2] <= -RED_BACK_MIN_M) & (shifts[:2] >= -RED_BACK_MAX_M))
    assert shifts[2:].tolist() == [0.0, 0.0, 0.0, 1.2]
    assert np.array_equal(shifts, draw_red_line_shifts(standing, red_line_m, queue, 1.0, np.random.default_rng(0)))
    assert np.count_nonzero(draw_red_line_shifts(standing, red_line_m, queue, 0.5, np.random.default_rng(0)) < 0) == 1
    # Share 0, or no red line known, draws nothing: the generator is left as it was.
    for share, lines in ((0.0, red_line_m), (1.0, None)):
        rng = np.random.default_rng(5)
        assert draw_red_line_shifts(standing, lines, queue, share, rng).tolist() == queue.tolist()
        assert rng.uniform() == np.random.default_rng(5).uniform()
