"""Vehicle motion for the closed loop: a kinematic bicycle model that inverts the expert's
label mappings (expert.py), so an action means in the loop what it meant in the data set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crchfl_sumo.data.expert import ExpertConfig, resistance_mps2, wheel_angle_from_steer

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
    return float(wheel_angle_from_steer(steer, config))


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


