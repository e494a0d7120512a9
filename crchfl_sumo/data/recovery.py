"""Recovery samples: images from a pose off the track, labelled with the steer that brings the vehicle back.

SUMO drives the data vehicles perfectly on the lane centre, so without help
the data holds no state a learner reaches after its first small error
(covariate shift; PilotNet and l5kit perturb the pose for the same reason).
The rasterizer can draw any pose, so a share of the moving samples is
rendered from a perturbed pose instead:

    lateral offset d ~ U(-lateral_m, lateral_m)   (positive = left of the track)
    yaw offset     e ~ U(-yaw_deg, yaw_deg)       (positive = turned left, CCW)
    pose'  = (p + d * (-sin h, cos h),  h + e)

and labelled by the expert's pure pursuit (expert.py) from pose' towards the
same target as the unperturbed sample: the point L ahead on the vehicle's own
future track. Throttle and brake stay the expert's. Standing samples are never
perturbed: a standing car's steer is 0 by the expert's rule, whatever its pose.
"""

from __future__ import annotations

import math

import numpy as np

from crchfl_sumo.data.expert import (
    ExpertConfig,
    Track,
    curvature_towards,
    is_standing,
    lookahead_m,
    pursuit_targets,
    steer_from_curvature,
)
from crchfl_sumo.sumo.frame import Frame


def draw_perturbations(
    eligible: np.ndarray, share: float, lateral_m: float, yaw_deg: float, rng: np.random.Generator
) -> np.ndarray:
    """Per sample (lateral_m, yaw_deg), float64 [N, 2]: round(share * eligible) eligible samples drawn
    without replacement get uniform offsets, the rest (0, 0)."""
    eligible = np.asarray(eligible, dtype=bool)
    out = np.zeros((len(eligible), 2))
    candidates = np.flatnonzero(eligible)
    chosen = np.sort(rng.choice(candidates, size=int(round(share * len(candidates))), replace=False))
    out[chosen, 0] = rng.uniform(-lateral_m, lateral_m, size=len(chosen))
    out[chosen, 1] = rng.uniform(-yaw_deg, yaw_deg, size=len(chosen))
    return out


def recovery_steer(
    track: Track, rows: np.ndarray, perturbation: np.ndarray, config: ExpertConfig = ExpertConfig()
) -> np.ndarray:
    """Expert steer at track rows ``rows`` rendered from the perturbed poses ``perturbation`` [R, 2]
    (lateral_m, yaw_deg): pure pursuit from the perturbed pose to the unperturbed sample's target."""
    rows = np.asarray(rows, dtype=np.int64)
    perturbation = np.asarray(perturbation, dtype=np.float64).reshape(-1, 2)
    target_x, target_y = pursuit_targets(track.x_m, track.y_m, track.heading_rad, lookahead_m(track.speed_mps, config))
    x, y, heading = perturbed_pose(track.x_m[rows], track.y_m[rows], track.heading_rad[rows], perturbation)
    curvature = curvature_towards(x, y, heading, target_x[rows], target_y[rows])
    standing = is_standing(track.speed_mps[rows], track.accel_mps2[rows], config)
    return np.where(standing, 0.0, steer_from_curvature(curvature, config))


def perturbed_pose(
    x_m: np.ndarray, y_m: np.ndarray, heading_rad: np.ndarray, perturbation: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, heading) moved ``lateral_m`` to the left of the heading and turned ``yaw_deg`` CCW."""
    lateral, yaw_rad = perturbation[:, 0], np.radians(perturbation[:, 1])
    return x_m - lateral * np.sin(heading_rad), y_m + lateral * np.cos(heading_rad), heading_rad + yaw_rad


def camera_pose(frame: Frame, vehicle: str, lateral_m: float, yaw_deg: float) -> tuple[float, float, float]:
    """(x_m, y_m, heading_rad) of ``vehicle`` in ``frame``, perturbed: where a sample's cameras stand."""
    row = frame.index_of(vehicle)
    x, y, heading = (getattr(frame, c)[row : row + 1] for c in ("x_m", "y_m", "heading_rad"))
    if lateral_m == 0 and yaw_deg == 0:
        return float(x[0]), float(y[0]), float(heading[0])
    px, py, ph = perturbed_pose(x, y, heading, np.array([[lateral_m, yaw_deg]]))
    return float(px[0]), float(py[0]), math.remainder(float(ph[0]), 2 * math.pi)

