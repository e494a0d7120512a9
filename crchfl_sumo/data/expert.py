"""SUMO's own driving -> expert actions (throttle, steer, brake) per sample.

SUMO moves vehicles along lanes; it has no pedals and no steering wheel. The
expert turns a vehicle's recorded track into the actions a driver would have
used to drive it:

steer (pure pursuit over the FUTURE track, so the label leads the motion)
    L      = max(lookahead_min_m, lookahead_time_s * speed)   look-ahead distance
    P      = the point L metres further along the vehicle's own future track
             (beyond the track's end: extrapolated along the last heading)
    alpha  = bearing of P seen from the vehicle, minus its heading (CCW +)
    kappa  = 2 sin(alpha) / |P - position|    curvature of the arc through P
    delta  = atan(wheelbase_m * kappa)        bicycle-model wheel angle
    steer  = clip(-delta / max_steer_angle, -1, 1)     below steer_knee; above it a progressive
             rack turns sharp_steer_gain times faster (steer_from_wheel_angle)
    Headings are CCW (frame.py), so a left turn has kappa > 0 and steer < 0:
    the paper's convention, positive = right.
    A standing vehicle (below) holds its wheels straight, steer 0: waiting at
    a light, its images do not show which way its route turns, so a label
    from the path ahead would be noise there (and the paper's red-light
    example carries steer 0.000).

throttle / brake (from the acceleration SUMO applied, plus what holding speed costs)
    a_cmd    = accel + resistance(speed)
    resistance(v) = rolling_resistance * g + drag_per_mass_per_m * v^2   [m/s^2]
    throttle = clip(a_cmd / max_accel, 0, 1)
    brake    = clip(-a_cmd / max_decel, 0, 1)
    Cruising at constant speed gives a small positive throttle, coasting
    down gently gives neither pedal, and the two are never pressed together.
    At a standstill (speed < stop_speed_mps and not accelerating away) the
    driver holds the brake: brake = max(brake, hold_brake), throttle 0.

target speed (what a model of ``longitudinal = "target_speed"`` learns instead of the pedals)
    target = the speed the vehicle has speed_horizon_s later on its own track
             (linear in time between samples; past the track's end, its last speed)
    A controller turns a target back into pedals (pedals_towards): the
    acceleration (target - speed) / speed_horizon_s through the pedal mapping
    above. The label says "go" or "stop" whatever the current speed, where the
    throttle label of a car cruising (~0.08) and of one standing at a red
    light (0) are almost the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.data.labels import digitize_steer
from crchfl_sumo.sumo.frame import Frame

GRAVITY_MPS2 = 9.81
# SUMO's passenger-car limits (every vehicle type of the built-in towns): the pedal scale where
# a sample does not carry its vehicle's own (evaluation of a target-speed model).
PASSENGER_MAX_ACCEL_MPS2 = 2.6
PASSENGER_MAX_DECEL_MPS2 = 4.5
# A target speed below this means "stand": the labels put a standing queue at 0 and a start from
# standing at 2.6 m/s or more, so a model's small positive guess at a red light does not creep forward.
STAND_TARGET_MPS = 1.0
DEFAULT_SPEED_HORIZON_S = 1.0  # the target speed's horizon (ExpertConfig and ModelConfig)

# The ranges of ExpertConfig's settings, each with its reason.
# Pure pursuit looks a few to tens of metres ahead; a point 100 m ahead lies past the next junction
# of any town block, so its bearing no longer says how to follow the lane.
MAX_PURSUIT_LOOKAHEAD_M = 100.0
# Trackers look 0.5 to 2 s ahead; 5 s is 70 m at the towns' 50 km/h, past the next junction as above.
MAX_PURSUIT_LOOKAHEAD_S = 5.0
# Longer than the whole of any road vehicle but a road train (the EU allows 18.75 m), so more than any wheelbase.
MAX_WHEELBASE_M = 20.0
# At 90 deg a wheel rolls sideways: the bicycle model's tan(delta) has no finite value (open bound).
MAX_STEER_LOCK_DEG = 90.0
# Variable-ratio racks change their ratio by well under 2x; tenfold bounds any tuning of the steer classes.
MAX_SHARP_STEER_GAIN = 10.0
# A coefficient: tyres on asphalt 0.01 to 0.015, on loose sand about 0.3; at 1 rolling alone brakes at 1 g.
MAX_ROLLING_RESISTANCE = 1.0
# A car's is about 2.6e-4 1/m; at 0.1 1/m drag alone brakes at 1 g from 10 m/s (36 km/h).
MAX_DRAG_PER_MASS_PER_M = 0.1
# A vehicle faster than 2 m/s (7 km/h, above walking pace) is rolling, not standing at a light.
MAX_STOP_SPEED_MPS = 2.0
# Further ahead, the target speed no longer says what to do now (ModelConfig.speed_horizon_s takes the same range).
MAX_SPEED_HORIZON_S = 5.0


@dataclass(frozen=True)
class ExpertConfig:
    """Constants of the expert's label mapping (docs/dataset.md explains each choice).

    Each has a range, checked in __post_init__ against the bounds above, their reasons beside them.
    lookahead_min_m, lookahead_time_s: L = max(lookahead_min_m, lookahead_time_s * speed).
    wheelbase_m: bicycle-model wheelbase (a mid-size saloon, 2.9 m).
    max_steer_angle_deg: wheel angle per unit of steer up to steer_knee (with
        the knee at 1, the lock). 40 deg puts Town01's left turns (radius ~15 m)
        on the paper's -0.275 class.
    steer_knee, sharp_steer_gain: above |steer| = steer_knee the wheel turns
        sharp_steer_gain times faster per unit of steer (a progressive rack, as
        variable-ratio steering has), so the paper's sharpest class reaches a
        tighter turn while the classes below keep their angles. Knee 1: linear.
        The lock they give at |steer| = 1 (lock_angle_deg) stays below 90 deg too.
    rolling_resistance: rolling-resistance coefficient (tyres on asphalt).
    drag_per_mass_per_m: 0.5 * rho_air * Cd * A / mass [1/m] (1.2*0.3*2.2/2/1500).
    stop_speed_mps: below this speed a vehicle counts as standing.
    hold_brake: brake a driver holds at a standstill.
    speed_horizon_s: the target speed is the speed this long ahead (and the
        controller reaches a target over this long); 1 s drove better than 2 s
        in traffic (docs/model.md), and a start from standing still reads 2.6
        m/s, above STAND_TARGET_MPS.
    """

    lookahead_min_m: float = 5.0
    lookahead_time_s: float = 0.8
    wheelbase_m: float = 2.9
    max_steer_angle_deg: float = 40.0
    steer_knee: float = 1.0
    sharp_steer_gain: float = 1.0
    rolling_resistance: float = 0.015
    drag_per_mass_per_m: float = 2.64e-4
    stop_speed_mps: float = 0.1
    hold_brake: float = 0.9
    speed_horizon_s: float = DEFAULT_SPEED_HORIZON_S

    def __post_init__(self) -> None:
        check_range(self.lookahead_min_m, "expert.lookahead_min_m", 0, MAX_PURSUIT_LOOKAHEAD_M, "metres", lo_open=True)
        check_range(self.lookahead_time_s, "expert.lookahead_time_s", 0, MAX_PURSUIT_LOOKAHEAD_S, "seconds")
        check_range(self.wheelbase_m, "expert.wheelbase_m", 0, MAX_WHEELBASE_M, "metres", lo_open=True)
        check_range(self.max_steer_angle_deg, "expert.max_steer_angle_deg", 0, MAX_STEER_LOCK_DEG, "degrees",
                    lo_open=True, hi_open=True)
        check_range(self.steer_knee, "expert.steer_knee", 0, 1, "a share of full steer", lo_open=True)
        check_range(self.sharp_steer_gain, "expert.sharp_steer_gain", 0, MAX_SHARP_STEER_GAIN,
                    "a factor (1: a linear rack)", lo_open=True)
        check_range(self.rolling_resistance, "expert.rolling_resistance", 0, MAX_ROLLING_RESISTANCE,
                    "a coefficient (asphalt: 0.015)")
        check_range(self.drag_per_mass_per_m, "expert.drag_per_mass_per_m", 0, MAX_DRAG_PER_MASS_PER_M,
                    "1/m (a car: 2.64e-4)")
        check_range(self.stop_speed_mps, "expert.stop_speed_mps", 0, MAX_STOP_SPEED_MPS, "m/s", lo_open=True)
        check_range(self.hold_brake, "expert.hold_brake", 0, 1, "a brake pedal position")
        check_range(self.speed_horizon_s, "expert.speed_horizon_s", 0, MAX_SPEED_HORIZON_S, "seconds", lo_open=True)
        if self.lock_angle_deg >= MAX_STEER_LOCK_DEG:
            raise CrchflError(
                f"expert.max_steer_angle_deg, steer_knee and sharp_steer_gain give a {self.lock_angle_deg:g} deg "
                f"lock at |steer| = 1; it must be < {MAX_STEER_LOCK_DEG:g} deg"
            )

    @property
    def lock_angle_deg(self) -> float:
        """The wheel angle at |steer| = 1."""
        return self.max_steer_angle_deg * (self.steer_knee + self.sharp_steer_gain * (1.0 - self.steer_knee))


# A stored expert block written before the progressive rack existed steered linearly.
LINEAR_RACK = {"steer_knee": 1.0, "sharp_steer_gain": 1.0}


def expert_from_labels(mapping, where: str) -> ExpertConfig:
    """The ExpertConfig of a stored block (a manifest's labels.expert, a checkpoint's extra.expert), checked;
    keys it lacks take today's defaults, except the rack, which is linear as it was before it had keys."""
    if not isinstance(mapping, dict):
        raise CrchflError(f"{where}: expected a table of expert settings, got {type(mapping).__name__}")
    return from_mapping(ExpertConfig, {**LINEAR_RACK, **mapping}, where)


@dataclass(frozen=True)
class Track:
    """One vehicle's recorded states in time order; every array is [T].

    max_accel_mps2 / max_decel_mps2 are the vehicle type's limits (constant
    along a track, kept per sample for simple vectorised maths). lane_id: the
    SUMO lane of each row ('' where not read; None for a track made by hand).
    """

    vehicle: str
    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    max_accel_mps2: np.ndarray
    max_decel_mps2: np.ndarray
    lane_id: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t_s)


def tracks_from_frames(frames: Sequence[Frame]) -> dict[str, Track]:
    """Per-vehicle tracks from a run's frames (vehicle id -> Track, in time order)."""
    if not frames:
        return {}
    columns = ("x_m", "y_m", "heading_rad", "speed_mps", "accel_mps2", "max_accel_mps2", "max_decel_mps2")
    ids = np.concatenate([f.ids for f in frames])
    t_s = np.concatenate([np.full(len(f), f.t_s, dtype=np.float64) for f in frames])
    stacked = {c: np.concatenate([getattr(f, c) for f in frames]).astype(np.float64) for c in columns}
    lanes = np.concatenate([f.lane_id for f in frames])
    # A stable sort by id keeps each vehicle's rows in frame (time) order.
    order = np.argsort(ids, kind="stable")
    ids, t_s, lanes = ids[order], t_s[order], lanes[order]
    stacked = {c: v[order] for c, v in stacked.items()}
    names, starts = np.unique(ids, return_index=True)
    ends = np.append(starts[1:], len(ids))
    return {
        str(name): Track(str(name), t_s[a:b], **{c: stacked[c][a:b] for c in columns}, lane_id=lanes[a:b])
        for name, a, b in zip(names, starts, ends)
    }


def lookahead_m(speed_mps: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """Look-ahead distance L [m] per sample."""
    return np.maximum(config.lookahead_min_m, config.lookahead_time_s * np.asarray(speed_mps, dtype=np.float64))


def pursuit_curvature(
    x_m: np.ndarray, y_m: np.ndarray, heading_rad: np.ndarray, lookahead: np.ndarray
) -> np.ndarray:
    """Pure-pursuit curvature [1/m] (CCW +) toward the point ``lookahead`` metres ahead on the track.

    The track is the polyline of the given positions; the point is found by
    arc length, so a vehicle that stands still still looks at the road it will
    drive. Past the last position the path is extended along the last heading.
    """
    x_m, y_m = np.asarray(x_m, np.float64), np.asarray(y_m, np.float64)
    heading_rad = np.asarray(heading_rad, np.float64)
    if len(x_m) == 0:
        return np.zeros(0)
    tx, ty = pursuit_targets(x_m, y_m, heading_rad, lookahead)
    return curvature_towards(x_m, y_m, heading_rad, tx, ty)


def pursuit_targets(
    x_m: np.ndarray, y_m: np.ndarray, heading_rad: np.ndarray, lookahead: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the point ``lookahead`` metres further along the track from each of its positions."""
    x_m, y_m = np.asarray(x_m, np.float64), np.asarray(y_m, np.float64)
    heading_rad = np.asarray(heading_rad, np.float64)
    step_m = np.hypot(np.diff(x_m), np.diff(y_m))
    arc_m = np.concatenate([[0.0], np.cumsum(step_m)])
    target_arc_m = arc_m + lookahead
    # j: first vertex with arc >= target; the target lies on segment (j-1, j).
    j = np.searchsorted(arc_m, target_arc_m, side="left")
    inside = j < len(arc_m)
    jj = np.clip(j, 1, len(arc_m) - 1)
    span = np.where(inside, arc_m[jj] - arc_m[jj - 1], 1.0)
    frac = np.where(inside, (target_arc_m - arc_m[jj - 1]) / np.where(span > 0, span, 1.0), 0.0)
    tx = np.where(inside, x_m[jj - 1] + frac * (x_m[jj] - x_m[jj - 1]), 0.0)
    ty = np.where(inside, y_m[jj - 1] + frac * (y_m[jj] - y_m[jj - 1]), 0.0)
    # Beyond the end: straight on along the last recorded heading.
    beyond_m = target_arc_m - arc_m[-1]
    tx = np.where(inside, tx, x_m[-1] + beyond_m * math.cos(heading_rad[-1]))
    ty = np.where(inside, ty, y_m[-1] + beyond_m * math.sin(heading_rad[-1]))
    return tx, ty


def curvature_towards(
    x_m: np.ndarray, y_m: np.ndarray, heading_rad: np.ndarray, target_x_m: np.ndarray, target_y_m: np.ndarray
) -> np.ndarray:
    """Curvature [1/m] (CCW +) of the arc from each pose (position, heading) through its target point."""
    dx, dy = np.asarray(target_x_m) - x_m, np.asarray(target_y_m) - y_m
    chord_m = np.hypot(dx, dy)
    alpha = np.arctan2(dy, dx) - heading_rad
    # 2 sin(alpha) / chord is exact for a circular arc tangent to the heading.
    return np.where(chord_m > 1e-6, 2.0 * np.sin(alpha) / np.maximum(chord_m, 1e-6), 0.0)


def steer_from_curvature(curvature_per_m: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """Bicycle model: curvature (CCW +) -> steer in [-1, 1] (positive = RIGHT)."""
    return steer_from_wheel_angle(np.arctan(config.wheelbase_m * np.asarray(curvature_per_m, dtype=np.float64)), config)


def steer_from_wheel_angle(delta_rad: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """Wheel angle (CCW +) -> steer in [-1, 1] (positive = RIGHT), through the rack's two slopes."""
    units = np.abs(np.asarray(delta_rad, dtype=np.float64)) / math.radians(config.max_steer_angle_deg)
    knee = config.steer_knee
    magnitude = np.where(units <= knee, units, knee + (units - knee) / config.sharp_steer_gain)
    # (+ 0.0 turns the -0.0 of a straight road into 0.0)
    return np.clip(-np.sign(delta_rad) * magnitude, -1.0, 1.0) + 0.0


def wheel_angle_from_steer(steer: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """Steer (clipped to [-1, 1], positive = RIGHT) -> wheel angle [rad], CCW +: steer_from_wheel_angle's inverse."""
    steer = np.clip(np.asarray(steer, dtype=np.float64), -1.0, 1.0)
    magnitude, knee = np.abs(steer), config.steer_knee
    units = np.where(magnitude <= knee, magnitude, knee + (magnitude - knee) * config.sharp_steer_gain)
    return -np.sign(steer) * units * math.radians(config.max_steer_angle_deg)


def resistance_mps2(speed_mps: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """Deceleration [m/s^2] that rolling resistance and drag impose at ``speed_mps`` (0 at rest)."""
    speed = np.abs(np.asarray(speed_mps, dtype=np.float64))
    rolling = np.where(speed > 0, config.rolling_resistance * GRAVITY_MPS2, 0.0)
    return rolling + config.drag_per_mass_per_m * speed**2


def is_standing(speed_mps: np.ndarray, accel_mps2: np.ndarray, config: ExpertConfig) -> np.ndarray:
    """True where a vehicle stands still: slower than stop_speed_mps and not pulling away."""
    return (np.asarray(speed_mps) < config.stop_speed_mps) & (np.asarray(accel_mps2) <= 0)


def pedals(
    speed_mps: np.ndarray,
    accel_mps2: np.ndarray,
    max_accel_mps2: np.ndarray,
    max_decel_mps2: np.ndarray,
    config: ExpertConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(throttle, brake), each in [0, 1], from speed and applied acceleration (module doc)."""
    speed = np.asarray(speed_mps, dtype=np.float64)
    accel = np.asarray(accel_mps2, dtype=np.float64)
    commanded = accel + resistance_mps2(speed, config)
    throttle = np.clip(commanded / np.asarray(max_accel_mps2, dtype=np.float64), 0.0, 1.0)
    brake = np.clip(-commanded / np.asarray(max_decel_mps2, dtype=np.float64), 0.0, 1.0)
    standing = is_standing(speed, accel, config)
    throttle = np.where(standing, 0.0, throttle)
    brake = np.where(standing, np.maximum(brake, config.hold_brake), brake)
    return throttle, brake


def expert_actions(track: Track, config: ExpertConfig = ExpertConfig()) -> np.ndarray:
    """Actions float32 [T, 3] = (throttle, steer, brake) for every sample of ``track``."""
    curvature = pursuit_curvature(track.x_m, track.y_m, track.heading_rad, lookahead_m(track.speed_mps, config))
    steer = np.where(is_standing(track.speed_mps, track.accel_mps2, config), 0.0, steer_from_curvature(curvature, config))
    throttle, brake = pedals(track.speed_mps, track.accel_mps2, track.max_accel_mps2, track.max_decel_mps2, config)
    return np.stack([throttle, steer, brake], axis=1).astype(np.float32)


def expert_labels(track: Track, config: ExpertConfig = ExpertConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(actions float32 [T, 3], steer_class int64 [T]) for ``track``."""
    actions = expert_actions(track, config)
    return actions, digitize_steer(actions[:, 1])


def target_speeds(track: Track, config: ExpertConfig = ExpertConfig()) -> np.ndarray:
    """float32 [T]: the speed ``track`` has ``config.speed_horizon_s`` after each of its samples."""
    if len(track) == 0:
        return np.zeros(0, np.float32)
    # np.interp holds the last value past the end: the last recorded speed.
    return np.interp(track.t_s + config.speed_horizon_s, track.t_s, track.speed_mps).astype(np.float32)


def target_speed_from_accel(speed_mps: float, accel_mps2: float, config: ExpertConfig = ExpertConfig()) -> float:
    """The speed an acceleration held for speed_horizon_s leads to (never below 0).

    For a driver with no recorded future (the route expert labelling a learner's state).
    """
    return max(0.0, float(speed_mps) + config.speed_horizon_s * float(accel_mps2))


def pedals_towards(
    speed_mps: np.ndarray,
    target_mps: np.ndarray,
    max_accel_mps2: np.ndarray,
    max_decel_mps2: np.ndarray,
    config: ExpertConfig = ExpertConfig(),
    brake_gain: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(throttle, brake) that reach ``target_mps`` in speed_horizon_s: the inverse of target_speeds.

    A target below STAND_TARGET_MPS is a stop; a standing vehicle told to stop
    holds the brake (pedals). ``brake_gain`` > 1 reaches a lower target sooner,
    in speed_horizon_s / brake_gain (1: the exact inverse, as the labels were made).
    """
    if not brake_gain > 0:
        raise CrchflError(f"brake gain must be > 0, got {brake_gain}")
    speed = np.asarray(speed_mps, dtype=np.float64)
    target = np.asarray(target_mps, dtype=np.float64)
    target = np.where(target < STAND_TARGET_MPS, 0.0, target)
    gain = np.where(target < speed, brake_gain, 1.0)
    return pedals(speed, gain * (target - speed) / config.speed_horizon_s, max_accel_mps2, max_decel_mps2, config)
