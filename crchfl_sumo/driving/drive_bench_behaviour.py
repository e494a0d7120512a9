"""How an episode was driven beyond success: the metrics of CARLA Leaderboard 2.0 and Bench2Drive.

Pure functions of a drive's log (drive.DriveLog) and route. Sources (read from the code, pinned):
carla-simulator/leaderboard@leaderboard-2.0 leaderboard/utils/statistics_manager.py and
scenario_runner's atomic_criteria.py (MinimumSpeedRouteTest, ActorBlockedTest); Bench2Drive
tools/efficiency_smoothness_benchmark.py and tools/ability_benchmark.py; nuPlan's comfort bounds
(nuplan-devkit, simulation_metric/low_level/*.yaml). docs/drive.md gives each definition.

- Speed against the traffic (``traffic_speed_ratios``): the route is cut into checkpoints of equal
  length; at each one reached, p = 100 x the ego's mean speed / the traffic's mean speed over the
  steps since the last one (the traffic: other vehicles within drive.TRAFFIC_RADIUS_M). The
  Leaderboard's minimum-speed penalty uses 4 checkpoints and costs 1 - 0.3 (1 - p / 100) for each
  p < 100; Bench2Drive's efficiency is the mean p over 20 checkpoints, not clipped.
- Smoothness (``smoothness``): the share of 2 s windows in which every comfort signal keeps
  within nuPlan's bounds. The signals are Savitzky-Golay derivatives (window 7, as Bench2Drive) of
  the ego's speed and heading, with the log's own time step, in SI units (Bench2Drive's code
  checks the yaw rate where it names the yaw acceleration and takes CARLA's degrees for radians:
  not copied).
- Abilities (``abilities``): per junction approached, whether the ego turned through it, stopped
  at its red, went at its green, yielded on its minor green; per planned lane change, whether it
  ended up on the lane planned; per episode, whether it followed a leader without a collision. Bench2Drive groups its routes by scenario type; the towns' routes
  have no scenarios, so the abilities are read off the drive itself.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from scipy.signal import savgol_filter

from crchfl_sumo.sumo.route import RED_LETTERS, Crossing, LaneChange

# Leaderboard 2.0: MinimumSpeedRouteTest(checkpoints=4) and PENALTY_PERC_DICT[MIN_SPEED] = [0.7, 'decreases'];
# Bench2Drive: checkpoints=20 for its efficiency.
MIN_SPEED_CHECKPOINTS = 4
MIN_SPEED_FLOOR = 0.7
EFFICIENCY_CHECKPOINTS = 20
# The Leaderboard records a last checkpoint at the end when the ego passed this share of the route.
LAST_CHECKPOINT_SHARE = 0.95

# nuPlan's comfort bounds (ego_is_comfortable; Bench2Drive's smoothness uses the same), all strict.
COMFORT_BOUNDS = {
    "lon_accel_mps2": (-4.05, 2.40),
    "lat_accel_mps2": (-4.89, 4.89),
    "yaw_rate_radps": (-0.95, 0.95),
    "yaw_accel_radps2": (-1.93, 1.93),
    "lon_jerk_mps3": (-4.13, 4.13),
    "jerk_mps3": (-8.37, 8.37),
}
SAVGOL_WINDOW = 7  # samples (Bench2Drive's)
COMFORT_WINDOW_S = 2.0  # Bench2Drive's 20 samples at the 0.1 s its code assumes

# Abilities: a junction counts as approached once the front bumper is this close to its stop line.
APPROACH_M = 30.0
STAND_MPS = 0.5  # slower than this is standing
GREEN_HESITATION_S = 2.0  # standing this long at a green with the road ahead free fails "go at green"
FREE_ROAD_M = 15.0  # a leader farther than this leaves the road free
FOLLOW_GAP_M = 20.0  # a leader this close ...
FOLLOW_MIN_S = 5.0  # ... for this long makes an episode a "follow a leader" attempt
SETTLE_M = 5.0  # a lane change is judged this far past the end of its planned move
ABILITIES = ("turn_at_junction", "stop_at_red", "go_at_green", "yield_on_minor_green", "follow_a_leader",
             "change_lane")


# Traffic that stands (a queue at a light, vehicles waiting to be inserted) gives no speed to compare with:
# a ratio to 0.01 m/s would be 100,000 % (measured: 667,554 % for a reference driver beside a queue).
MIN_TRAFFIC_SPEED_MPS = 0.5


def traffic_speed_ratios(log, start_m: float, goal_m: float, checkpoints: int) -> list[float]:
    """p in % at each checkpoint the ego reached (with traffic around it in that stretch that moves, at
    MIN_TRAFFIC_SPEED_MPS or more on average)."""
    span = max(goal_m - start_m, 1e-9)
    stretch = np.clip(np.floor((np.asarray(log.progress_m) - start_m) / span * checkpoints), 0, checkpoints - 1)
    best = float(np.max(log.progress_m)) - start_m if len(log.progress_m) else 0.0
    reached = min(checkpoints, int(best / span * checkpoints + 1e-9))
    if best / span >= LAST_CHECKPOINT_SHARE:
        reached = checkpoints
    ratios = []
    for k in range(reached):
        rows = stretch == k
        traffic = np.asarray(log.traffic_speed_mps)[rows]
        traffic = traffic[np.isfinite(traffic)]
        if len(traffic) and traffic.mean() >= MIN_TRAFFIC_SPEED_MPS:
            ratios.append(100.0 * float(np.mean(np.asarray(log.speed_mps)[rows])) / float(traffic.mean()))
    return ratios


def min_speed_penalty(ratios: Sequence[float]) -> float:
    """The Leaderboard 2.0 factor: prod over checkpoints with p < 100 of 1 - (1 - 0.7)(1 - p / 100)."""
    return float(math.prod(1.0 - (1.0 - MIN_SPEED_FLOOR) * (1.0 - p / 100.0) for p in ratios if p < 100.0))


def comfort_signals(speed_mps, heading_rad, step_s: float) -> dict[str, np.ndarray]:
    """The six comfort signals per step (COMFORT_BOUNDS' keys); empty arrays for fewer than SAVGOL_WINDOW steps."""
    v = np.asarray(speed_mps, dtype=np.float64)
    if len(v) < SAVGOL_WINDOW:
        return {key: np.zeros(0) for key in COMFORT_BOUNDS}
    yaw = np.unwrap(np.asarray(heading_rad, dtype=np.float64))

    def derivative(x, order=1, poly=2):
        return savgol_filter(x, SAVGOL_WINDOW, max(poly, order), deriv=order, delta=step_s)

    lon = derivative(v)
    yaw_rate = derivative(yaw)
    lat = savgol_filter(v, SAVGOL_WINDOW, 2) * yaw_rate
    return {
        "lon_accel_mps2": lon,
        "lat_accel_mps2": lat,
        "yaw_rate_radps": yaw_rate,
        "yaw_accel_radps2": derivative(yaw, order=2, poly=3),
        "lon_jerk_mps3": derivative(lon),
        "jerk_mps3": derivative(np.hypot(lon, lat)),
    }


def smoothness(speed_mps, heading_rad, step_s: float) -> float | None:
    """Share of the drive's full COMFORT_WINDOW_S windows within every comfort bound (None: no full window)."""
    signals = comfort_signals(speed_mps, heading_rad, step_s)
    per_window = max(1, int(round(COMFORT_WINDOW_S / step_s)))
    windows = len(signals["lon_accel_mps2"]) // per_window
    if windows == 0:
        return None
    inside = np.ones(windows * per_window, dtype=bool)
    for key, (lo, hi) in COMFORT_BOUNDS.items():
        x = signals[key][: windows * per_window]
        inside &= (x > lo) & (x < hi)
    return float(inside.reshape(windows, per_window).all(axis=1).mean())


def _longest_run_s(mask: np.ndarray, step_s: float) -> float:
    longest = current = 0
    for m in mask:
        current = current + 1 if m else 0
        longest = max(longest, current)
    return longest * step_s


def abilities(
    log, crossings: Sequence[Crossing], step_s: float, lane_changes: Sequence[LaneChange] = ()
) -> dict[str, list[int]]:
    """Per ability, [attempts, successes] in one drive.

    A junction is approached when the front bumper comes within APPROACH_M of its stop line. Then:
    - turn_at_junction (a left or right link): success when the ego left the junction on its route
      (its progress passed the junction's end) without a collision from the approach on;
    - stop_at_red (its signal showed red during the approach): no red light run there;
    - go_at_green (a major green, 'G', with the road ahead free during the approach): never standing
      GREEN_HESITATION_S or longer while it showed green and the road ahead was free;
    - yield_on_minor_green (a minor green, 'g', during the approach): no collision from the approach
      until the ego left the junction (or the drive ended);
    per planned lane change whose move the ego's centre reached, change_lane: success when, SETTLE_M past
    the move's end, the ego is within half a lane width of the route's centre line (on the lane planned),
    with no collision from the move's start until then;
    and per drive, follow_a_leader (a leader within FOLLOW_GAP_M for FOLLOW_MIN_S in all): no collision.
    """
    tally = {name: [0, 0] for name in ABILITIES}
    ahead = np.asarray(log.crossing_ahead)
    dist = np.asarray(log.signal_dist_m, dtype=np.float64)
    letters = np.asarray(log.signal_letter)
    progress = np.asarray(log.progress_m, dtype=np.float64)
    colliding = np.asarray(log.colliding, dtype=bool)
    red = np.asarray(log.red_light, dtype=bool)
    speed = np.asarray(log.speed_mps, dtype=np.float64)
    gap = np.asarray(log.leader_gap_m, dtype=np.float64)
    # the step a red light was run at crossing c: the row before red_light (the move crossed its line)
    ran_red_at = {int(ahead[i - 1]) for i in np.flatnonzero(red) if i > 0}
    for c, crossing in enumerate(crossings):
        approach = (ahead == c) & (dist <= APPROACH_M)
        if not approach.any():
            continue
        first = int(np.flatnonzero(approach)[0])
        left = np.flatnonzero(progress[first:] > crossing.s_end_m)
        until = first + int(left[0]) if len(left) else len(progress)
        clean = not colliding[first : until + 1].any()
        seen = set(letters[approach])

        def count(name: str, success: bool) -> None:
            tally[name][0] += 1
            tally[name][1] += int(success)

        if crossing.direction in ("l", "L", "r", "R"):
            count("turn_at_junction", bool(len(left)) and clean)
        if seen & set(RED_LETTERS):
            count("stop_at_red", c not in ran_red_at)
        green_free = approach & (letters == "G") & (gap > FREE_ROAD_M)
        if green_free.any():
            count("go_at_green", _longest_run_s(green_free & (speed < STAND_MPS), step_s) < GREEN_HESITATION_S)
        if "g" in seen:
            count("yield_on_minor_green", clean)
    for change in lane_changes:
        reached = np.flatnonzero(progress >= change.s_start_m)
        if not len(reached):
            continue
        settled = np.flatnonzero(progress >= change.s_end_m + SETTLE_M)
        tally["change_lane"][0] += 1
        if len(settled):
            at = int(settled[0])
            on_lane = abs(float(log.offset_m[at])) <= float(log.lane_width_m[at]) / 2.0
            tally["change_lane"][1] += int(on_lane and not colliding[reached[0] : at + 1].any())
    if float(np.count_nonzero(gap <= FOLLOW_GAP_M)) * step_s >= FOLLOW_MIN_S:
        tally["follow_a_leader"] = [1, int(not colliding.any())]
    return tally


def behaviour(
    log, crossings: Sequence[Crossing], start_m: float, goal_m: float, step_s: float,
    lane_changes: Sequence[LaneChange] = (),
) -> dict[str, Any]:
    """One episode's Leaderboard 2.0 and Bench2Drive figures (JSON-ready)."""
    efficiency = traffic_speed_ratios(log, start_m, goal_m, EFFICIENCY_CHECKPOINTS)
    return {
        "min_speed_penalty": min_speed_penalty(traffic_speed_ratios(log, start_m, goal_m, MIN_SPEED_CHECKPOINTS)),
        "efficiency": float(np.mean(efficiency)) if efficiency else None,
        "smoothness": smoothness(log.speed_mps, log.heading_rad, step_s),
        "abilities": abilities(log, crossings, step_s, lane_changes),
    }
