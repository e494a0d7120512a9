"""Closed-loop driving: a policy (a trained model, or a script) drives an ego vehicle in SUMO.

Every step the ego's four cameras are rendered from the current Frame, the
policy predicts (throttle, steer, brake), and the ego moves by a kinematic
bicycle model that inverts the expert's label mappings (expert.py), so that an
action means in the loop what it meant in the data set:

    delta   = -steer * max_steer_angle            wheel angle, CCW + (positive steer = RIGHT)
    kappa   = tan(delta) / wheelbase              path curvature of the footprint centre
    a       = throttle * max_accel - brake * max_decel - resistance(v)
    v'      = max(0, v + a dt);  the centre moves (v + v') / 2 * dt along the arc of curvature kappa

The expert labelled the footprint centre's track with delta = atan(wheelbase *
kappa), so the loop moves the centre on arcs of curvature tan(delta) /
wheelbase: a steer label replayed gives back the curvature it was made from.
In SUMO the ego is placed with moveToXY at its progress on the route, on the
lane the route plans there (its front bumper on that lane's centre line): SUMO
never maps it onto another lane or edge. Its exact pose stays the loop's: the
cameras, the metrics and the collision check (the footprints overlap) use it.
The ego's speed is set, so the other vehicles follow, stop behind and yield to
it as to any other vehicle.

Metrics are measured against the planned route's lane centre line (the lanes
of the route's edges joined by the junctions' internal lanes), read from the
network with sumolib. docs/drive.md defines each of them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_DRIVE_S, check_range
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.driving.dynamics import VehicleState, acceleration_from_pedals, bicycle_step
from crchfl_sumo.driving.policies import Observation, Policy, leader_gap_m
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.sumo.route import (
    RED_LETTERS,
    Crossing,
    RouteGeometry,
    next_crossing,
    on_road,
    point_at,
    project_points,
    read_net,
    road_area,
    signal_letter,
)
from crchfl_sumo.sumo.scenario import Scenario
from crchfl_sumo.sumo.simulation import Simulation

log = logging.getLogger(__name__)

DEFAULT_TYPE = "DEFAULT_VEHTYPE"  # SUMO's built-in type, for scenarios without an 'ego' type
# SUMO options of a drive: collisions are reported and nothing is removed (the run
# measures them), any physical overlap counts, and a standing ego is never teleported.
DRIVE_SUMO_OPTIONS = (
    "--collision.action=warn",
    "--collision.check-junctions=true",
    "--collision.mingap-factor=0",
    "--time-to-teleport=-1",
)
# Traffic around the ego (surroundings): the radius of the vehicles whose speed the ego's is compared
# with (CARLA's Background Activity keeps its traffic about this close), and how far ahead a leader counts.
TRAFFIC_RADIUS_M = 50.0
LEADER_RANGE_M = 50.0
STUCK_PROGRESS_M = 1.0  # progress that counts as moving on (creeping adds up to it)
_SEARCH_BACK_M = 10.0  # the ego's progress is searched this far behind ...
_SEARCH_AHEAD_M = 25.0  # ... and this far ahead of the last step's (routes may cross themselves)

Action = tuple[float, float, float]  # (throttle, steer, brake), labels.py conventions


def red_light_violations(
    crossings: Sequence[Crossing], front_before_m: float, front_after_m: float, tls_states: Mapping[str, str]
) -> list[Crossing]:
    """Crossings whose stop line the front bumper passed in this step while the link showed red."""
    return [
        c
        for c in crossings
        if front_before_m < c.s_start_m <= front_after_m and signal_letter(c, tls_states) in RED_LETTERS
    ]


def lane_departed(offset_m, lane_width_m, vehicle_width_m: float) -> np.ndarray:
    """True where a wheel is over the lane's edge: |offset| > lane_width / 2 - vehicle_width / 2."""
    return np.abs(np.asarray(offset_m)) > np.asarray(lane_width_m) / 2.0 - vehicle_width_m / 2.0


def count_onsets(mask) -> int:
    """Number of runs of True (events that last several steps count once)."""
    mask = np.asarray(mask, dtype=bool)
    return int(np.count_nonzero(mask[1:] & ~mask[:-1]) + (1 if len(mask) and mask[0] else 0))


def footprints_overlap(
    x_m: float, y_m: float, heading_rad: float, length_m: float, width_m: float,
    others_x_m, others_y_m, others_heading_rad, others_length_m, others_width_m,
) -> np.ndarray:
    """Which other footprints (rectangles around their centres) overlap the given one, per other vehicle.

    Separating axis test: two rectangles are apart exactly when, along one of
    their four side directions, the gap between their centres exceeds the sum
    of their half extents. SUMO checks collisions along lanes only, so this
    also catches an ego that hits a vehicle while it is off its lane.
    """
    ox, oy = np.asarray(others_x_m, np.float64), np.asarray(others_y_m, np.float64)
    oh = np.asarray(others_heading_rad, np.float64)
    half_l, half_w = np.asarray(others_length_m, np.float64) / 2.0, np.asarray(others_width_m, np.float64) / 2.0
    dx, dy = ox - x_m, oy - y_m
    apart = np.zeros(len(ox), dtype=bool)
    for axis in (np.full_like(oh, heading_rad), np.full_like(oh, heading_rad + math.pi / 2.0), oh, oh + math.pi / 2.0):
        gap = np.abs(dx * np.cos(axis) + dy * np.sin(axis))
        ego_reach = length_m / 2.0 * np.abs(np.cos(axis - heading_rad)) + width_m / 2.0 * np.abs(np.sin(axis - heading_rad))
        other_reach = half_l * np.abs(np.cos(axis - oh)) + half_w * np.abs(np.sin(axis - oh))
        apart |= gap > ego_reach + other_reach
    return ~apart


# --- the loop ------------------------------------------------------------------------------------


# The ranges of DriveConfig's settings, each with its reason. Its times are at most MAX_DRIVE_S, the hour a drive
# lasts at most (`drive --warmup-s` and `--max-s` take the same); stuck_s may be inf: a drive never ends stuck.
MAX_FINISH_BEFORE_END_M = 100.0  # farther than a town block (about 100 m) from its end, a route is not reached
MAX_LOST_OFFSET_M = 100.0  # a town block off its route's centre line, the ego is on another street
MAX_OFF_ROAD_MARGIN_M = 10.0  # three lane widths (3.2 m each) beyond a lane's edge is off any road


@dataclass(frozen=True)
class DriveConfig:
    """Settings of a closed-loop drive (each with a range, checked in __post_init__: the bounds above).

    ego_id               id of the driven vehicle in SUMO
    type_id              its SUMO vehicle type (SUMO's default type if the scenario lacks it)
    warmup_s             traffic runs this long before the ego is added, so that it meets moving traffic
    insert_timeout_s     how long SUMO may wait for room to insert the ego at the route's start
    finish_before_end_m  the route counts as completed when the ego's centre is this close to its end
    lost_offset_m        the drive ends when the ego is farther than this from the route's centre line
    off_road_margin_m    the centre may be this far off a lane's edge before it counts as off the road
    stuck_s              the drive ends when the ego has not gained STUCK_PROGRESS_M of progress for this
                         long (the Leaderboard's "agent blocked"; inf: never)
    """

    ego_id: str = "ego"
    type_id: str = "ego"
    warmup_s: float = 20.0
    insert_timeout_s: float = 60.0
    finish_before_end_m: float = 5.0
    lost_offset_m: float = 10.0
    off_road_margin_m: float = 0.0
    stuck_s: float = math.inf

    def __post_init__(self) -> None:
        check_range(self.warmup_s, "drive.warmup_s", 0, MAX_DRIVE_S, "simulated seconds")
        check_range(self.insert_timeout_s, "drive.insert_timeout_s", 0, MAX_DRIVE_S, "simulated seconds", lo_open=True)
        check_range(self.finish_before_end_m, "drive.finish_before_end_m", 0, MAX_FINISH_BEFORE_END_M, "metres")
        check_range(self.lost_offset_m, "drive.lost_offset_m", 0, MAX_LOST_OFFSET_M, "metres", lo_open=True)
        check_range(self.off_road_margin_m, "drive.off_road_margin_m", 0, MAX_OFF_ROAD_MARGIN_M, "metres")
        check_range(self.stuck_s, "drive.stuck_s", 0, MAX_DRIVE_S, "simulated seconds (or inf: never)",
                    lo_open=True, inf_ok=True)
        if not self.ego_id:
            raise CrchflError("drive.ego_id must not be empty")


@dataclass(frozen=True)
class DriveLog:
    """One row per step of the drive, the ego's state when the policy acted (arrays [T]).

    The last row is the state the drive ended in; its action is nan.
    signal_* describe the next stop line on the route ('' / inf / -1 if none);
    red_light marks the step whose move crossed a stop line on red.
    """

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    throttle: np.ndarray
    steer: np.ndarray
    brake: np.ndarray
    progress_m: np.ndarray
    offset_m: np.ndarray
    lane_width_m: np.ndarray
    on_road: np.ndarray
    colliding: np.ndarray
    red_light: np.ndarray
    signal_letter: np.ndarray
    signal_dist_m: np.ndarray
    crossing_ahead: np.ndarray
    traffic_speed_mps: np.ndarray  # mean speed of the other vehicles within TRAFFIC_RADIUS_M (NaN: none)
    leader_gap_m: np.ndarray  # bumper gap to the vehicle ahead in the ego's lane within LEADER_RANGE_M (inf: none)

    def __len__(self) -> int:
        return len(self.t_s)

    def columns(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class DriveResult:
    """A finished drive: its log, metrics and the frames the policy saw (ego pose as driven)."""

    log: DriveLog
    metrics: dict[str, Any]
    frames: list[Frame]
    route: RouteGeometry
    ego_id: str
    vehicle_length_m: float
    vehicle_width_m: float


def with_ego_pose(frame: Frame, row: int, state: VehicleState) -> Frame:
    """The frame with the ego's row set to the bicycle model's state (what the cameras must show)."""
    columns = {}
    values = {"x_m": state.x_m, "y_m": state.y_m, "heading_rad": state.heading_rad, "speed_mps": state.speed_mps}
    for name, value in values.items():
        column = getattr(frame, name).copy()
        column[row] = value
        columns[name] = column
    return dataclasses.replace(frame, **columns)


def drive(
    scenario: Scenario,
    route: RouteGeometry,
    policy: Policy,
    seed: int = 0,
    max_s: float = 120.0,
    config: DriveConfig = DriveConfig(),
    renderer=None,
    expert: ExpertConfig = ExpertConfig(),
    keep_frames: bool = True,
    sumo_log: Path | None = None,
    sumo_options: tuple[str, ...] = (),
) -> DriveResult:
    """Drive ``route`` in ``scenario`` with ``policy`` for at most ``max_s`` simulated seconds.

    ``renderer`` (raster.Renderer of the scenario's world) renders the ego's
    cameras for the policy every step; a policy without images passes None.
    ``sumo_log``: SUMO's warnings go to this file instead of the console (sumo_warnings counts them).
    ``sumo_options``: more of SUMO's options (its own output files, sumo.outputs).
    """
    if not max_s > 0:
        raise CrchflError(f"--max-s must be > 0, got {max_s}")
    ego = config.ego_id
    dt = scenario.step_length_s
    area = road_area(read_net(Path(scenario.net_path)))
    rows: list[dict[str, Any]] = []
    frames: list[Frame] = []
    quiet = warnings_to(sumo_log)
    options = (*DRIVE_SUMO_OPTIONS, *quiet, *sumo_options)
    with Simulation(scenario, seed=seed, extra_options=options, watch=[ego]) as sim:
        for _ in range(int(round(config.warmup_s / dt))):
            sim.step()
        type_id = config.type_id if config.type_id in sim.vehicle_type_ids() else DEFAULT_TYPE
        sim.add_external_vehicle(ego, route.edges, type_id)
        for _ in range(max(1, int(round(config.insert_timeout_s / dt)))):
            frame = sim.step()
            if ego in frame.ids:
                break
        else:
            raise CrchflError(
                f"SUMO found no room to insert the ego at the start of edge '{route.edges[0]}' within "
                f"{config.insert_timeout_s} s; start the route on another edge or change drive.warmup_s"
            )
        row = frame.index_of(ego)
        length, width = float(frame.length_m[row]), float(frame.width_m[row])
        max_accel, max_decel = float(frame.max_accel_mps2[row]), float(frame.max_decel_mps2[row])
        state = VehicleState(float(frame.x_m[row]), float(frame.y_m[row]), float(frame.heading_rad[row]), 0.0)
        first_stop = route.crossings[0].s_start_m if route.crossings else route.length_m
        s, offset, lane_width = (
            float(v[0]) for v in project_points(route, state.x_m, state.y_m, -math.inf, first_stop)
        )
        start_s, goal_s = s, route.length_m - config.finish_before_end_m
        t_start = frame.t_s
        colliding, red, removed = False, False, False
        moved_s, moved_t = s, t_start  # the last time the ego gained STUCK_PROGRESS_M
        while True:
            row = frame.index_of(ego)
            frame = with_ego_pose(frame, row, state)
            index = next_crossing(route.crossings, s + length / 2.0)
            letter = signal_letter(route.crossings[index], frame.tls_states) if index >= 0 else ""
            record = {
                "t_s": frame.t_s - t_start, "x_m": state.x_m, "y_m": state.y_m, "heading_rad": state.heading_rad,
                "speed_mps": state.speed_mps, "progress_m": s, "offset_m": offset, "lane_width_m": lane_width,
                "on_road": on_road(area, state.x_m, state.y_m, config.off_road_margin_m),
                "colliding": colliding, "red_light": red, "signal_letter": letter,
                "signal_dist_m": route.crossings[index].s_start_m - (s + length / 2.0) if index >= 0 else math.inf,
                "crossing_ahead": index,
                **surroundings(frame, row, route, s, length),
            }
            if removed:
                end = "removed by SUMO"
            elif s >= goal_s:
                end = "completed"
            elif abs(offset) > config.lost_offset_m:
                end = "left the route"
            elif frame.t_s - moved_t >= config.stuck_s - 1e-9:
                end = "stuck"
            elif frame.t_s - t_start >= max_s - 1e-9:
                end = "time limit"
            else:
                end = None
            if keep_frames:
                frames.append(frame)
            if end is not None:
                rows.append(record | {"throttle": math.nan, "steer": math.nan, "brake": math.nan})
                break
            images = renderer.render(frame, [ego])[0] if renderer is not None else None
            throttle, steer, brake = policy(Observation(frame, ego, row, s, images, offset, lane_width, dt))
            rows.append(record | {"throttle": throttle, "steer": steer, "brake": brake})
            accel = acceleration_from_pedals(throttle, brake, state.speed_mps, max_accel, max_decel, expert)
            new_state = bicycle_step(state, accel, steer, dt, expert)
            new_s, offset, lane_width = (
                float(v[0])
                for v in project_points(route, new_state.x_m, new_state.y_m, s - _SEARCH_BACK_M, s + _SEARCH_AHEAD_M)
            )
            # SUMO holds the ego on the lane its route plans, at the ego's progress: never on another lane or
            # edge (its own pose, which the cameras and metrics use, stays the loop's)
            front_s = new_s + length / 2.0
            x_front, y_front, heading = point_at(route, front_s)
            sim.place_vehicle(ego, x_front, y_front, heading, new_state.speed_mps, lane_id=route.lane_at(front_s))
            seen = frame
            frame = sim.step()
            removed = ego not in frame.ids
            if removed:  # SUMO let it arrive or teleported it: end with the last picture of it
                log.warning("SUMO removed the ego '%s' at t=%.2f s; the drive ends there", ego, frame.t_s)
                frame = dataclasses.replace(seen, t_s=frame.t_s, tls_states=frame.tls_states)
            colliding = ego in sim.colliding_vehicles() or _touches_another(frame, ego, new_state, length, width)
            red = bool(red_light_violations(route.crossings, s + length / 2.0, new_s + length / 2.0, seen.tls_states))
            state, s = new_state, new_s
            if s >= moved_s + STUCK_PROGRESS_M:
                moved_s, moved_t = s, frame.t_s
    drive_log = _log_from_rows(rows)
    metrics = drive_metrics(drive_log, start_s, goal_s, width, dt, end)
    log.info(
        "drive from %s ended (%s) after %.1f s: completion %.2f",
        route.edges[0], end, drive_log.t_s[-1], metrics["completion"],
    )
    return DriveResult(drive_log, metrics, frames, route, ego, length, width)


def warnings_to(sumo_log: Path | None) -> tuple[str, ...]:
    """SUMO options that send its warnings to ``sumo_log`` instead of the console (its folder made);
    none for None."""
    if sumo_log is None:
        return ()
    Path(sumo_log).parent.mkdir(parents=True, exist_ok=True)
    return (f"--error-log={sumo_log}", "--no-warnings=true")


def sumo_warnings(path: Path) -> int:
    """Warnings SUMO wrote (drive's ``sumo_log``) to the file ``path``, or to the *.log files of the folder
    ``path``; 0 where there is none."""
    path = Path(path)
    files = [path] if path.is_file() else sorted(path.glob("*.log")) if path.is_dir() else []
    return sum(line.startswith("Warning:") for file in files
               for line in file.read_text(encoding="utf-8", errors="replace").splitlines())


def surroundings(frame: Frame, row: int, route: RouteGeometry, s_m: float, length_m: float) -> dict[str, float]:
    """The traffic around the ego at one step: the mean speed of the other vehicles within
    TRAFFIC_RADIUS_M (the Leaderboard's minimum-speed test and Bench2Drive's efficiency compare the
    ego's speed with it) and the bumper gap to the nearest vehicle ahead in the ego's lane on its
    route within LEADER_RANGE_M (in the lane as the reference driver counts it)."""
    others = np.flatnonzero(np.arange(len(frame)) != row)
    distance = np.hypot(frame.x_m[others] - frame.x_m[row], frame.y_m[others] - frame.y_m[row])
    near = others[distance < TRAFFIC_RADIUS_M]
    traffic = float(np.mean(frame.speed_mps[near])) if len(near) else math.nan
    return {"traffic_speed_mps": traffic,
            "leader_gap_m": leader_gap_m(frame, near, route, s_m, length_m / 2.0, LEADER_RANGE_M)}


def _touches_another(frame: Frame, ego: str, state: VehicleState, length_m: float, width_m: float) -> bool:
    """Does the ego's footprint at ``state`` overlap another vehicle's in ``frame``?"""
    others = frame.ids != ego
    if not others.any():
        return False
    return bool(
        footprints_overlap(
            state.x_m, state.y_m, state.heading_rad, length_m, width_m,
            frame.x_m[others], frame.y_m[others], frame.heading_rad[others],
            frame.length_m[others], frame.width_m[others],
        ).any()
    )


def _log_from_rows(rows: list[dict[str, Any]]) -> DriveLog:
    kinds = {"on_road": bool, "colliding": bool, "red_light": bool, "signal_letter": str, "crossing_ahead": np.int64}
    return DriveLog(
        **{
            f.name: np.array([r[f.name] for r in rows], dtype=kinds.get(f.name, np.float64))
            for f in dataclasses.fields(DriveLog)
        }
    )


def drive_metrics(
    drive_log: DriveLog, start_s_m: float, goal_s_m: float, vehicle_width_m: float, step_s: float, end_reason: str
) -> dict[str, Any]:
    """The per-route metrics of a drive (docs/drive.md defines each)."""
    departed = lane_departed(drive_log.offset_m, drive_log.lane_width_m, vehicle_width_m)
    off_road = ~drive_log.on_road
    span = max(goal_s_m - start_s_m, 1e-9)
    best = float(np.max(drive_log.progress_m)) if len(drive_log) else start_s_m
    path_m = float(np.sum(np.hypot(np.diff(drive_log.x_m), np.diff(drive_log.y_m))))
    duration_s = float(drive_log.t_s[-1]) if len(drive_log) else 0.0
    return {
        "end_reason": end_reason,
        "completion": float(np.clip((best - start_s_m) / span, 0.0, 1.0)),
        "duration_s": duration_s,
        "distance_m": path_m,
        "mean_speed_mps": path_m / duration_s if duration_s > 0 else 0.0,
        "collisions": count_onsets(drive_log.colliding),
        "lane_departures": count_onsets(departed),
        "lane_departure_s": float(np.count_nonzero(departed[:-1]) * step_s),
        "max_abs_offset_m": float(np.max(np.abs(drive_log.offset_m))) if len(drive_log) else 0.0,
        "off_road_events": count_onsets(off_road),
        "off_road_s": float(np.count_nonzero(off_road[:-1]) * step_s),
        "red_light_violations": int(np.count_nonzero(drive_log.red_light)),
    }
