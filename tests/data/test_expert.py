import dataclasses
import math

import numpy as np
import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import (
    ExpertConfig,
    Track,
    expert_actions,
    expert_from_labels,
    expert_labels,
    pedals,
    pedals_towards,
    pursuit_curvature,
    resistance_mps2,
    steer_from_curvature,
    target_speed_from_accel,
    target_speeds,
    tracks_from_frames,
    wheel_angle_from_steer,
)
from crchfl_sumo.data.labels import STEER_CLASS_VALUES
from crchfl_sumo.sumo.frame import make_frame

CFG = ExpertConfig()
DT_S = 0.25


def make_track(x, y, heading, speed, accel=None, vehicle="v"):
    n = len(x)
    return Track(
        vehicle=vehicle,
        t_s=np.arange(n) * DT_S,
        x_m=np.asarray(x, float),
        y_m=np.asarray(y, float),
        heading_rad=np.asarray(heading, float),
        speed_mps=np.asarray(speed, float),
        accel_mps2=np.zeros(n) if accel is None else np.asarray(accel, float),
        max_accel_mps2=np.full(n, 2.6),
        max_decel_mps2=np.full(n, 4.5),
    )


def turn_track(radius_m, left, speed_mps=6.0, straight_m=30.0, exit_m=30.0):
    """Drive east along a straight, then a 90-degree arc (left or right), then straight on."""
    arc_m = radius_m * math.pi / 2
    s = np.arange(0.0, straight_m + arc_m + exit_m, speed_mps * DT_S)
    sign = 1.0 if left else -1.0
    x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
    for i, si in enumerate(s):
        if si <= straight_m:
            x[i], y[i], h[i] = si, 0.0, 0.0
        elif si <= straight_m + arc_m:
            phi = (si - straight_m) / radius_m
            x[i] = straight_m + radius_m * math.sin(phi)
            y[i] = sign * radius_m * (1 - math.cos(phi))
            h[i] = sign * phi
        else:
            rest = si - straight_m - arc_m
            x[i], y[i], h[i] = straight_m + radius_m, sign * (radius_m + rest), sign * math.pi / 2
    return make_track(x, y, h, np.full(len(s), speed_mps)), s


def on_arc(track):
    """Indices of the samples inside the 90-degree arc (heading strictly changing)."""
    turned = np.abs(track.heading_rad)
    return np.flatnonzero((turned > 1e-9) & (turned < math.pi / 2 - 1e-9))


def test_straight_cruise_small_throttle_no_steer_no_brake():
    n = 40
    x = np.arange(n) * 2.0
    actions = expert_actions(make_track(x, np.zeros(n), np.zeros(n), np.full(n, 8.0)))
    assert np.all(actions[:, 1] == 0.0)
    assert np.all(actions[:, 2] == 0.0)
    expected = (0.015 * 9.81 + 2.64e-4 * 64) / 2.6  # resistance at 8 m/s over max accel
    assert actions[:, 0] == pytest.approx(np.full(n, expected), rel=1e-5)
    assert 0 < expected < 0.1


def test_pure_pursuit_curvature_is_exact_on_a_circle():
    radius_m = 15.0
    phi = np.linspace(0, 3 * math.pi / 2, 200)
    x, y = radius_m * np.sin(phi), radius_m * (1 - np.cos(phi))  # CCW circle, heading = phi
    kappa = pursuit_curvature(x, y, phi, np.full(200, 5.0))
    # Well inside the arc (target still on it) the chord formula gives 1/R.
    assert kappa[:100] == pytest.approx(np.full(100, 1 / radius_m), rel=1e-3)


def test_left_turn_steers_negative_and_leads_the_heading():
    track, s = turn_track(radius_m=15.0, left=True)
    actions, classes = expert_labels(track)
    steer = actions[:, 1]
    turning = on_arc(track)
    first_turning = turning[0]
    # Look-ahead 5 m at 6 m/s: the label turns ~0.8 s (3 samples) before the heading does.
    assert np.all(steer[first_turning - 3 : first_turning] < 0)
    assert np.all(steer[: first_turning - 4] == 0)
    # Mid-arc: the bicycle model's steady value, -atan(2.9/15)/40deg, class -0.275.
    mid = turning[len(turning) // 2]
    # (2% slack: the track is a polyline of 1.5 m chords, not the true arc.)
    assert steer[mid] == pytest.approx(-math.atan(2.9 / 15.0) / math.radians(40.0), rel=2e-2)
    assert STEER_CLASS_VALUES[classes[mid]] == pytest.approx(-0.275)
    assert set(classes[turning[2:-2]]) <= {4, 5, 6}  # negative-side classes only
    # The label also straightens out before the heading stops changing.
    done = np.flatnonzero(track.heading_rad >= math.pi / 2 - 1e-9)[0]
    assert abs(steer[done - 1]) < abs(steer[mid])


def test_right_turn_steers_positive():
    track, _ = turn_track(radius_m=10.0, left=False)
    actions, classes = expert_labels(track)
    turning = on_arc(track)
    mid = turning[len(turning) // 2]
    assert actions[mid, 1] == pytest.approx(math.atan(0.29) / math.radians(40.0), rel=2e-2)
    assert STEER_CLASS_VALUES[classes[mid]] == pytest.approx(0.425)
    assert np.all(actions[turning[2:-2], 1] > 0)


def test_end_of_track_extrapolates_straight_on():
    # Track ends in the middle of a left arc: the last sample looks along its heading, steer 0.
    track, _ = turn_track(radius_m=15.0, left=True, exit_m=0.0)
    cut = np.flatnonzero(track.heading_rad > 0.5)[0]
    short = make_track(track.x_m[:cut], track.y_m[:cut], track.heading_rad[:cut], track.speed_mps[:cut])
    steer = expert_actions(short)[:, 1]
    assert steer[-1] == pytest.approx(0.0, abs=1e-9)
    assert steer[-6] < -0.1


def test_stop_at_red_brakes_and_holds_then_pulls_away():
    # 8 m/s, brake at -3 m/s^2 to a stop, stand 10 s at the red, pull away at 2 m/s^2.
    speed, accel = [8.0], [0.0]
    while speed[-1] > 0:
        speed.append(max(speed[-1] - 3.0 * DT_S, 0.0))
        accel.append(-3.0)
    speed += [0.0] * 40
    accel += [0.0] * 40
    for _ in range(10):
        speed.append(speed[-1] + 2.0 * DT_S)
        accel.append(2.0)
    speed, accel = np.array(speed), np.array(accel)
    x = np.concatenate([[0.0], np.cumsum(speed[1:] * DT_S)])
    n = len(speed)
    actions = expert_actions(make_track(x, np.zeros(n), np.zeros(n), speed, accel))
    throttle, brake = actions[:, 0], actions[:, 2]
    standing = (speed == 0) & (accel <= 0)
    assert standing.sum() >= 40
    assert np.all(brake[standing] >= 0.8) and np.all(throttle[standing] == 0)
    braking = (accel < 0) & (speed > 0.1)
    assert np.all(brake[braking] > 0.6) and np.all(throttle[braking] == 0)
    assert np.all(throttle[accel > 0] > 0.7) and np.all(brake[accel > 0] == 0)


def test_pedals_hand_computed_and_never_both():
    speed = np.array([10.0, 10.0, 10.0, 0.0, 0.05])
    accel = np.array([1.0, -0.1, -9.0, 0.0, 1.5])
    throttle, brake = pedals(speed, accel, np.full(5, 2.6), np.full(5, 4.5), CFG)
    res10 = 0.015 * 9.81 + 2.64e-4 * 100
    assert throttle[0] == pytest.approx((1.0 + res10) / 2.6)
    assert throttle[1] == pytest.approx((res10 - 0.1) / 2.6) and brake[1] == 0  # coasting: no brake
    assert brake[2] == 1.0 and throttle[2] == 0  # emergency braking beyond the limit clips
    assert brake[3] == CFG.hold_brake and throttle[3] == 0
    assert throttle[4] > 0 and brake[4] == 0  # pulling away from rest
    assert np.all(throttle * brake == 0)
    assert resistance_mps2(np.array([0.0]), CFG)[0] == 0.0


def test_steer_sign_and_saturation():
    steer = steer_from_curvature(np.array([0.0, 0.05, -0.05, 10.0, -10.0]), CFG)
    assert steer[0] == 0 and steer[1] < 0 < steer[2]
    assert steer[3] == -1.0 and steer[4] == 1.0


def test_progressive_rack_keeps_the_small_classes_and_sharpens_the_largest():
    rack = ExpertConfig(steer_knee=0.275, sharp_steer_gain=2.0)
    # below the knee 40 deg per unit: 0.125 -> 5 deg, 0.275 -> 11 deg; above it 80 deg per unit:
    # 0.425 -> 11 + 0.15 * 80 = 23 deg, and the lock 11 + 0.725 * 80 = 69 deg
    degrees = np.degrees(wheel_angle_from_steer(np.array([0.125, 0.275, 0.425, 1.0, 2.0, -0.425]), rack))
    assert np.allclose(degrees, [-5.0, -11.0, -23.0, -69.0, -69.0, 23.0])  # positive steer = right = clockwise
    assert rack.lock_angle_deg == pytest.approx(69.0)
    # a 6.83 m right turn (tan 23 deg = 2.9 / 6.83) labels 0.425, where the linear rack saturates its class
    kappa = -math.tan(math.radians(23.0)) / CFG.wheelbase_m
    assert steer_from_curvature(np.array([kappa]), rack)[0] == pytest.approx(0.425)
    assert steer_from_curvature(np.array([kappa]), CFG)[0] == pytest.approx(23.0 / 40.0)
    # the two mappings invert each other on both sides of the knee
    steer = np.linspace(-1.0, 1.0, 41)
    kappas = np.tan(wheel_angle_from_steer(steer, rack)) / rack.wheelbase_m
    assert np.allclose(steer_from_curvature(kappas, rack), steer)
    # the default rack is linear: 40 deg at full steer, as before the knee existed
    assert np.degrees(wheel_angle_from_steer(np.array([0.425, 1.0]), CFG)) == pytest.approx([-17.0, -40.0])


def test_a_stored_expert_block_without_the_rack_reads_linear():
    # blocks written before the rack had keys steered linearly, whatever today's default
    assert (expert_from_labels({"max_steer_angle_deg": 40.0}, "m").steer_knee,
            expert_from_labels({}, "m").sharp_steer_gain) == (1.0, 1.0)
    stored = expert_from_labels({"steer_knee": 0.3, "sharp_steer_gain": 2.5}, "m")
    assert (stored.steer_knee, stored.sharp_steer_gain) == (0.3, 2.5)
    with pytest.raises(CrchflError, match=r"data/manifest.json: labels.expert.steer_knee: 1.5 is out of range"):
        expert_from_labels({"steer_knee": 1.5}, "data/manifest.json: labels.expert")
    with pytest.raises(CrchflError, match="model.pt: extra.expert: expected a table"):
        expert_from_labels([1], "model.pt: extra.expert")


def test_standing_vehicle_holds_wheels_straight_then_steers_into_the_turn():
    # Waiting 5 s at the stop line of a left turn, then driving it.
    track, _ = turn_track(radius_m=15.0, left=True)
    wait = on_arc(track)[0] - 2
    rows = np.concatenate([np.full(20, wait), np.arange(wait, len(track))])
    speed = np.where(np.arange(len(rows)) < 20, 0.0, 6.0)
    accel = np.where(np.arange(len(rows)) == 20, 2.0, 0.0)
    stopped = make_track(track.x_m[rows], track.y_m[rows], track.heading_rad[rows], speed, accel)
    actions = expert_actions(stopped)
    assert np.all(actions[:20, 1] == 0) and np.all(actions[:20, 2] == CFG.hold_brake)
    assert actions[20, 1] < -0.1 and actions[20, 0] > 0  # moving off: steer at the bend ahead


def test_tracks_from_frames_groups_by_vehicle_in_time_order():
    frames = [
        make_frame(t_s=0.0, ids=["a"], x_m=[0.0], speed_mps=[1.0]),
        make_frame(t_s=0.25, ids=["a", "b"], x_m=[1.0, 10.0], speed_mps=[2.0, 5.0]),
        make_frame(t_s=0.5, ids=["b"], x_m=[11.0], speed_mps=[6.0], max_decel_mps2=[7.5]),
    ]
    tracks = tracks_from_frames(frames)
    assert sorted(tracks) == ["a", "b"]
    assert tracks["a"].t_s.tolist() == [0.0, 0.25] and tracks["a"].x_m.tolist() == [0.0, 1.0]
    assert tracks["b"].t_s.tolist() == [0.25, 0.5] and tracks["b"].speed_mps.tolist() == [5.0, 6.0]
    assert tracks["b"].max_decel_mps2.tolist() == [4.5, 7.5]
    assert tracks_from_frames([]) == {}


def test_target_speed_is_the_speed_two_seconds_later_on_the_track():
    # 0.25 s samples: standing 1 s, then +1 m/s per sample (4 m/s^2) up to 6 m/s, then cruising.
    speed = np.array([0.0] * 4 + [1.0, 2.0, 3.0, 4.0, 5.0, 6.0] + [6.0] * 6)
    track = make_track(np.zeros(len(speed)), np.zeros(len(speed)), np.zeros(len(speed)), speed)
    target = target_speeds(track, ExpertConfig(speed_horizon_s=2.0))
    assert target.dtype == np.float32 and len(target) == len(speed)
    assert target[0] == speed[8] == 5.0  # 2 s = 8 samples ahead
    assert target[3] == 6.0 and target[-1] == 6.0  # past the end: the last speed
    assert target_speeds(track, ExpertConfig(speed_horizon_s=0.375))[4] == pytest.approx(2.5)  # between samples
    assert len(target_speeds(make_track([], [], [], []), CFG)) == 0


def test_pedals_towards_inverts_the_target_speed_of_a_constant_acceleration():
    speed, accel = np.array([0.0, 4.0, 10.0, 10.0]), np.array([2.0, 1.0, 0.0, -3.0])
    target = speed + CFG.speed_horizon_s * accel  # what a track holding these accelerations has at the horizon
    limits = np.full(4, 2.6), np.full(4, 4.5)
    assert [target_speed_from_accel(v, a) for v, a in zip(speed, accel)] == pytest.approx(target)
    towards = pedals_towards(speed, target, *limits, CFG)
    direct = pedals(speed, accel, *limits, CFG)
    assert towards[0] == pytest.approx(direct[0]) and towards[1] == pytest.approx(direct[1])
    # below STAND_TARGET_MPS a target is a stop: standing, the brake is held; moving, it brakes
    throttle, brake = pedals_towards(np.array([0.0, 3.0]), np.array([0.8, 0.8]), *(a[:2] for a in limits), CFG)
    assert throttle.tolist() == [0.0, 0.0] and brake[0] == CFG.hold_brake and brake[1] > 0
    assert target_speed_from_accel(1.0, -4.5) == 0.0  # never below standing


def test_brake_gain_reaches_a_lower_target_sooner_and_leaves_a_higher_one_alone():
    speed, accel = np.array([4.0, 10.0, 10.0]), np.array([1.0, -1.0, -2.0])
    target = speed + CFG.speed_horizon_s * accel
    limits = np.full(3, 2.6), np.full(3, 4.5)
    geared = pedals_towards(speed, target, *limits, CFG, brake_gain=2.0)
    # speeding up: as labelled; slowing down: twice the deceleration
    direct = pedals(speed, accel * np.array([1.0, 2.0, 2.0]), *limits, CFG)
    assert geared[0] == pytest.approx(direct[0]) and geared[1] == pytest.approx(direct[1])
    assert geared[1][2] > pedals_towards(speed, target, *limits, CFG)[1][2]
    with pytest.raises(CrchflError, match="brake gain"):
        pedals_towards(speed, target, *limits, CFG, brake_gain=0.0)


# key: (values just outside its range, values at or just inside its ends); hand-written from the reasons in expert.py
EXPERT_RANGES = {
    "lookahead_min_m": ((0, 100.5), (0.01, 100)),
    "lookahead_time_s": ((-0.01, 5.01), (0, 5)),
    "wheelbase_m": ((0, 20.01), (0.5, 20)),
    "max_steer_angle_deg": ((0, 90), (0.5, 89.9)),
    "steer_knee": ((0, 1.01), (0.01, 1)),
    "sharp_steer_gain": ((0, 10.01), (0.01, 10)),  # with the knee at 1 the gain acts on nothing: the lock stays 40
    "rolling_resistance": ((-0.01, 1.01), (0, 1)),
    "drag_per_mass_per_m": ((-1e-6, 0.101), (0, 0.1)),
    "stop_speed_mps": ((0, 2.01), (0.01, 2)),
    "hold_brake": ((-0.01, 1.01), (0, 1)),
    "speed_horizon_s": ((0, 5.01), (0.01, 5)),
}


def test_every_expert_setting_is_listed_with_its_range():
    assert set(EXPERT_RANGES) == {f.name for f in dataclasses.fields(ExpertConfig)}


@pytest.mark.parametrize("key", sorted(EXPERT_RANGES))
def test_every_expert_setting_has_a_finite_range(key):
    refused, accepted = EXPERT_RANGES[key]
    for value in (*refused, 1e308, -1e308, 2**63 - 1, math.nan, math.inf, -math.inf):
        with pytest.raises(CrchflError, match=rf"^expert\.{key}: .+; give .+ in [\[(]"):
            ExpertConfig(**{key: value})
    for value in accepted:
        assert getattr(ExpertConfig(**{key: value}), key) == value


def test_config_rejects_bad_values():
    with pytest.raises(CrchflError, match=r"speed_horizon_s: 8 is out of range; give seconds in \(0, 5\]"):
        ExpertConfig(speed_horizon_s=8)
    with pytest.raises(CrchflError, match=r"max_steer_angle_deg: 90 is out of range; give degrees in \(0, 90\)$"):
        ExpertConfig(max_steer_angle_deg=90)  # a wheel at 90 deg rolls sideways: the bound is open
    with pytest.raises(CrchflError, match="91 deg lock"):  # 40 * (0.5 + 0.5 * 3.55)
        ExpertConfig(steer_knee=0.5, sharp_steer_gain=3.55)
    # a stored block (a manifest's labels.expert) names its file and key, whatever the value
    with pytest.raises(CrchflError, match=r"^data/manifest.json: labels.expert.wheelbase_m: 1e\+308 is out of range"):
        expert_from_labels({"wheelbase_m": 1e308}, "data/manifest.json: labels.expert")
