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

Queue samples are the same idea along the lane. SUMO stops a follower
minGap (2.5 m) behind a standing leader and never closer, so a learner that
creeps forward in a queue soon sees its leader closer than any sample shows,
and there it may drive on into it. A share of the standing samples with a
standing leader at most QUEUE_GAP_MAX_M ahead (``gap_ahead``) is rendered
moved forward along the heading:

    new gap g' ~ U(QUEUE_GAP_MIN_M, QUEUE_CLOSE_M),  forward shift s = gap - g'
    pose' = (p + s * (cos h, sin h), h)

and labelled to stay: the standing sample's pedals (holding the brake) and
a target speed of 0, whatever the queue does next.

Red-line samples are the same idea backwards. SUMO's first car at a red
light stands about a metre before the line and passes the few metres before
it at a walking pace, so the data holds few red-light states 2 to 8 m short of
the line (about 100 in the paper split's training shards against 1,261 standing
within 2 m); a learner that creeps to its red stops there, its stop head reads
the red as farther than it is, and it rolls over the line (docs/measurements.md,
2026-12-06, fifth). A share of the standing samples within RED_LINE_NEAR_M of a
red line is rendered moved back along the heading:

    back shift b ~ U(RED_BACK_MIN_M, RED_BACK_MAX_M),  pose' = (p - b * (cos h, sin h), h)

and labelled to stay, as queue samples are; its stop-line distance grows by b.
The shift is straight back, as the last metres before a stop line are.
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

# The columns of a sample's perturbation [N, 3], as the shard stores it ("perturbation").
LATERAL_M, YAW_DEG, FORWARD_M = range(3)
# positive = the rendered pose is left of / turned left of / ahead of the track
PERTURBATION_NAMES = ("lateral_m", "yaw_deg", "forward_m")

QUEUE_GAP_MAX_M = 5.0  # a standing leader at most this far ahead (bumper to bumper) makes a queue sample
QUEUE_GAP_MIN_M = 0.5  # the closest a shifted sample stands to its leader ...
QUEUE_CLOSE_M = 2.0  # ... and the farthest: closer than SUMO's standstill gap (minGap, 2.5 m by default)
RED_LINE_NEAR_M = 3.0  # a standing sample this close to a red stop line (the first in line) makes a red-line sample
RED_BACK_MIN_M = 1.0  # how far back such a sample is moved: at least ...
RED_BACK_MAX_M = 6.0  # ... and at most (a standing car this far before its line is the gap in the data)
CORRIDOR_HALF_WIDTH_M = 1.5  # a vehicle whose centre is this close to the heading line is in the lane ahead
SAME_DIRECTION_DEG = 30.0  # ... and heads within this of the vehicle's own heading


def gap_ahead(frame: Frame, vehicle: str, stop_speed_mps: float) -> float:
    """Bumper-to-bumper gap [m] from ``vehicle`` to the nearest standing vehicle ahead of it in its lane, or inf.

    Ahead in its lane: centre in front of it, within CORRIDOR_HALF_WIDTH_M of
    its heading line, heading the same way (within SAME_DIRECTION_DEG); a
    straight corridor, as queues stand on the straight approach to a stop line.
    The nearest such vehicle counts only if it stands (slower than ``stop_speed_mps``).
    """
    row = frame.index_of(vehicle)
    heading = frame.heading_rad[row]
    dx, dy = frame.x_m - frame.x_m[row], frame.y_m - frame.y_m[row]
    forward = dx * np.cos(heading) + dy * np.sin(heading)
    lateral = -dx * np.sin(heading) + dy * np.cos(heading)
    aligned = np.cos(frame.heading_rad - heading) >= math.cos(math.radians(SAME_DIRECTION_DEG))
    ahead = (forward > 0) & (np.abs(lateral) <= CORRIDOR_HALF_WIDTH_M) & aligned
    ahead[row] = False
    if not ahead.any():
        return math.inf
    gaps = forward - (frame.length_m + frame.length_m[row]) / 2
    nearest = np.flatnonzero(ahead)[np.argmin(gaps[ahead])]
    return float(gaps[nearest]) if frame.speed_mps[nearest] < stop_speed_mps else math.inf


def draw_queue_shifts(
    standing: np.ndarray, gap_m: np.ndarray | None, share: float, rng: np.random.Generator
) -> np.ndarray:
    """Per sample the forward shift [m], float64 [N]: round(share * eligible) of the eligible samples
    (standing, with a standing leader more than QUEUE_CLOSE_M and at most QUEUE_GAP_MAX_M ahead:
    ``gap_m``, inf for none; None: no sample has one), drawn without replacement, move towards it
    until it stands g' ~ U(QUEUE_GAP_MIN_M, QUEUE_CLOSE_M) behind; the rest 0."""
    out = np.zeros(len(standing))
    if share == 0 or gap_m is None:
        return out  # no draws: the other recovery draws stay as they were without queue samples
    gap_m = np.asarray(gap_m, dtype=np.float64)
    candidates = np.flatnonzero(np.asarray(standing, dtype=bool) & (gap_m > QUEUE_CLOSE_M) & (gap_m <= QUEUE_GAP_MAX_M))
    chosen = np.sort(rng.choice(candidates, size=int(round(share * len(candidates))), replace=False))
    out[chosen] = gap_m[chosen] - rng.uniform(QUEUE_GAP_MIN_M, QUEUE_CLOSE_M, size=len(chosen))
    return out


def draw_red_line_shifts(
    standing: np.ndarray, red_line_m: np.ndarray | None, forward_m: np.ndarray, share: float, rng: np.random.Generator
) -> np.ndarray:
    """Per sample the forward shift [m], float64 [N]: ``forward_m`` (the queue shifts), except that round(share *
    eligible) of the eligible samples (standing, not queue-shifted, with a red stop line at most RED_LINE_NEAR_M
    ahead: ``red_line_m``, inf for none; None: no sample has one), drawn without replacement, move back by
    U(RED_BACK_MIN_M, RED_BACK_MAX_M) (a negative shift)."""
    out = np.array(forward_m, dtype=np.float64)
    if share == 0 or red_line_m is None:
        return out  # no draws: every other draw stays as it was without red-line samples
    eligible = np.asarray(standing, dtype=bool) & (out == 0) & (np.asarray(red_line_m) <= RED_LINE_NEAR_M)
    candidates = np.flatnonzero(eligible)
    chosen = np.sort(rng.choice(candidates, size=int(round(share * len(candidates))), replace=False))
    out[chosen] = -rng.uniform(RED_BACK_MIN_M, RED_BACK_MAX_M, size=len(chosen))
    return out


def draw_perturbations(
    eligible: np.ndarray, share: float, lateral_m: float, yaw_deg: float, rng: np.random.Generator
) -> np.ndarray:
    """Per sample (lateral_m, yaw_deg, forward_m), float64 [N, 3]: round(share * eligible) eligible samples
    drawn without replacement get uniform lateral and yaw offsets, the rest 0 (forward_m is always 0
    here: draw_queue_shifts fills it)."""
    eligible = np.asarray(eligible, dtype=bool)
    out = np.zeros((len(eligible), 3))
    candidates = np.flatnonzero(eligible)
    chosen = np.sort(rng.choice(candidates, size=int(round(share * len(candidates))), replace=False))
    out[chosen, LATERAL_M] = rng.uniform(-lateral_m, lateral_m, size=len(chosen))
    out[chosen, YAW_DEG] = rng.uniform(-yaw_deg, yaw_deg, size=len(chosen))
    return out


def recovery_steer(
    track: Track, rows: np.ndarray, perturbation: np.ndarray, config: ExpertConfig = ExpertConfig()
) -> np.ndarray:
    """Expert steer at track rows ``rows`` rendered from the perturbed poses ``perturbation`` [R, 3]
    (lateral_m, yaw_deg, forward_m): pure pursuit from the perturbed pose to the unperturbed sample's target."""
    rows = np.asarray(rows, dtype=np.int64)
    perturbation = np.asarray(perturbation, dtype=np.float64).reshape(-1, 3)
    target_x, target_y = pursuit_targets(track.x_m, track.y_m, track.heading_rad, lookahead_m(track.speed_mps, config))
    x, y, heading = perturbed_pose(track.x_m[rows], track.y_m[rows], track.heading_rad[rows], perturbation)
    curvature = curvature_towards(x, y, heading, target_x[rows], target_y[rows])
    standing = is_standing(track.speed_mps[rows], track.accel_mps2[rows], config)
    return np.where(standing, 0.0, steer_from_curvature(curvature, config))


def perturbed_pose(
    x_m: np.ndarray, y_m: np.ndarray, heading_rad: np.ndarray, perturbation: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, heading) moved ``forward_m`` along the heading and ``lateral_m`` to its left, and turned
    ``yaw_deg`` CCW (``perturbation`` [N, 3]: lateral_m, yaw_deg, forward_m)."""
    lateral, forward = perturbation[:, LATERAL_M], perturbation[:, FORWARD_M]
    yaw_rad = np.radians(perturbation[:, YAW_DEG])
    cos, sin = np.cos(heading_rad), np.sin(heading_rad)
    return x_m + forward * cos - lateral * sin, y_m + forward * sin + lateral * cos, heading_rad + yaw_rad


def camera_pose(
    frame: Frame, vehicle: str, lateral_m: float, yaw_deg: float, forward_m: float
) -> tuple[float, float, float]:
    """(x_m, y_m, heading_rad) of ``vehicle`` in ``frame``, perturbed: where a sample's cameras stand."""
    row = frame.index_of(vehicle)
    x, y, heading = (getattr(frame, c)[row : row + 1] for c in ("x_m", "y_m", "heading_rad"))
    if lateral_m == 0 and yaw_deg == 0 and forward_m == 0:
        return float(x[0]), float(y[0]), float(heading[0])
    px, py, ph = perturbed_pose(x, y, heading, np.array([[lateral_m, yaw_deg, forward_m]]))
    return float(px[0]), float(py[0]), math.remainder(float(ph[0]), 2 * math.pi)

