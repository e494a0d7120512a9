"""Pictures of closed-loop drives: trajectories on the map (the paper's Fig. 5), action frames (Fig. 6), video.

    write_drive_outputs(result, scenario, renderer, out_dir, metrics, label)   the `drive` command's files
    compare_runs([dir_a, dir_b, dir_c], ["CRCHFL", "HFL", "SFL"], "fig5.png") one panel per scheme

A run folder holds metrics.json (with the scenario and the route's edges) and
trajectory.csv (the drive log), so runs of several models can be drawn side
by side later from their folders alone.
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import cv2
import numpy as np

from crchfl_sumo.core.atomic import atomic_path
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.figures import pyplot, save_figure
from crchfl_sumo.core.json_files import read_json_object, write_json
from crchfl_sumo.core.result_files import DRIVE_METRICS_FILE
from crchfl_sumo.driving.drive import DriveLog, DriveResult, lane_departed
from crchfl_sumo.sumo.maps import draw_network
from crchfl_sumo.sumo.route import GREEN_LETTERS, RED_LETTERS, RouteGeometry, read_net, route_geometry
from crchfl_sumo.sumo.scenario import Scenario, load_scenario
from crchfl_sumo.vision.mosaic import VideoWriter, mosaic, top_down_view, write_png

log = logging.getLogger(__name__)

MOMENT_RANGE_M = 20.0  # a light counts for the pictures when its stop line is this close
GREEN_RESPONSE_S = 2.0  # after a light turns green, the picture waits this long at most for the throttle
PANEL_HEIGHT_PX = 64
THROTTLE_RGB = (40, 200, 80)
BRAKE_RGB = (230, 50, 50)
STEER_RGB = (60, 160, 255)
TEXT_RGB = (255, 255, 255)
PANEL_RGB = (30, 30, 30)


# --- which steps to show ---------------------------------------------------------------------


def pick_moments(drive_log: DriveLog) -> dict[str, int]:
    """Rows of the log for the Fig. 6 pictures; a moment that never happened is left out.

    red_light        first step with a red light ahead within MOMENT_RANGE_M
    green_light      the light at a stop line where it was red shows green: the first step
                     within GREEN_RESPONSE_S of that with more throttle than brake (else the
                     step it turned green); without a red before, the first green within range
    t_junction_turn  the step nearest the middle of the first left or right turn driven through
    """
    acted = np.isfinite(drive_log.throttle)
    near = acted & (drive_log.signal_dist_m <= MOMENT_RANGE_M)
    red = near & np.isin(drive_log.signal_letter, list(RED_LETTERS))
    green = near & np.isin(drive_log.signal_letter, list(GREEN_LETTERS))
    moments: dict[str, int] = {}
    if red.any():
        moments["red_light"] = int(np.flatnonzero(red)[0])
    after_red = [
        i for i in np.flatnonzero(green)
        if np.any(red[:i] & (drive_log.crossing_ahead[:i] == drive_log.crossing_ahead[i]))
    ]
    if after_red:
        # The driver's answer to the green: the first step of pulling away within GREEN_RESPONSE_S.
        first = int(after_red[0])
        window = (
            green
            & (drive_log.crossing_ahead == drive_log.crossing_ahead[first])
            & (drive_log.t_s >= drive_log.t_s[first])
            & (drive_log.t_s <= drive_log.t_s[first] + GREEN_RESPONSE_S)
            & (drive_log.throttle > drive_log.brake)
        )
        moments["green_light"] = int(np.flatnonzero(window)[0]) if window.any() else first
    elif green.any():
        moments["green_light"] = int(np.flatnonzero(green)[0])
    return moments


def turn_moment(drive_log: DriveLog, route: RouteGeometry) -> int | None:
    """Row nearest the middle of the first left/right turn the ego drove through (None if none).

    Turns at signalised junctions (the towns' T-junctions) come first, then
    those elsewhere (the towns' rounded corners).
    """
    acted = np.isfinite(drive_log.throttle)
    for crossing in sorted(route.crossings, key=lambda c: (not c.tls_id, c.s_start_m)):
        if crossing.direction.lower() not in ("l", "r"):
            continue
        inside = acted & (drive_log.progress_m >= crossing.s_start_m) & (drive_log.progress_m <= crossing.s_end_m)
        if inside.any():
            middle = 0.5 * (crossing.s_start_m + crossing.s_end_m)
            rows = np.flatnonzero(inside)
            return int(rows[np.argmin(np.abs(drive_log.progress_m[rows] - middle))])
    return None


# --- action frames ----------------------------------------------------------------------------


def action_panel(width_px: int, action: Sequence[float], caption: str) -> np.ndarray:
    """RGB strip [PANEL_HEIGHT_PX, width, 3]: throttle and brake bars, a steer gauge, a caption."""
    panel = np.full((PANEL_HEIGHT_PX, width_px, 3), PANEL_RGB, np.uint8)
    throttle, steer, brake = (float(v) for v in action)
    bar_w = max(40, width_px // 5)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for k, (name, value, rgb) in enumerate((("throttle", throttle, THROTTLE_RGB), ("brake", brake, BRAKE_RGB))):
        x0, y0 = 8 + k * (bar_w + 90), 36
        cv2.putText(panel, f"{name} {value:.2f}", (x0, 24), font, 0.5, TEXT_RGB, 1, cv2.LINE_AA)
        cv2.rectangle(panel, (x0, y0), (x0 + bar_w, y0 + 14), TEXT_RGB, 1)
        if math.isfinite(value):
            cv2.rectangle(panel, (x0, y0), (x0 + int(round(np.clip(value, 0, 1) * bar_w)), y0 + 14), rgb, -1)
    x0 = 8 + 2 * (bar_w + 90)
    # Half the smallest steer class: below it the DAC's nearest value is 0 (straight).
    side = "right" if steer > 0.0625 else "left" if steer < -0.0625 else "straight"
    cv2.putText(panel, f"steer {steer:+.3f} ({side})", (x0, 24), font, 0.5, TEXT_RGB, 1, cv2.LINE_AA)
    centre = x0 + bar_w // 2
    cv2.rectangle(panel, (x0, 36), (x0 + bar_w, 50), TEXT_RGB, 1)
    if math.isfinite(steer):
        tip = centre + int(round(np.clip(steer, -1, 1) * bar_w / 2))
        cv2.rectangle(panel, (min(centre, tip), 36), (max(centre, tip), 50), STEER_RGB, -1)
    cv2.line(panel, (centre, 32), (centre, 54), TEXT_RGB, 1)
    cv2.putText(panel, caption, (x0 + bar_w + 16, 46), font, 0.5, TEXT_RGB, 1, cv2.LINE_AA)
    return panel


def drive_picture(renderer, frame, ego_id: str, action: Sequence[float], caption: str) -> np.ndarray:
    """The ego's four cameras and top-down view with the action it took below them."""
    images = renderer.render(frame, [ego_id])[0]
    picture = mosaic(images, top_down_view(renderer, frame, ego_id))
    return np.vstack([picture, action_panel(picture.shape[1], action, caption)])


# --- trajectories -------------------------------------------------------------------------------


def write_trajectory_csv(path: Path, drive_log: DriveLog) -> None:
    """The drive log as CSV, one row per step (atomic)."""
    columns = drive_log.columns()
    with atomic_path(path) as tmp, tmp.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for values in zip(*columns.values()):
            writer.writerow([_cell(v) for v in values])


def _cell(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return "1" if value else "0"
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return str(value)


def read_trajectory_csv(path: Path) -> DriveLog:
    """A drive log written by write_trajectory_csv."""
    path = Path(path)
    if not path.is_file():
        raise CrchflError(f"{path}: no trajectory.csv; point to a folder written by `crchfl-sumo drive`")
    kinds = {"on_road": bool, "colliding": bool, "red_light": bool, "signal_letter": str, "crossing_ahead": np.int64}
    values = {}
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle))
        for name in DriveLog.__dataclass_fields__:
            # columns added later (traffic_speed_mps, leader_gap_m) read as unknown in older folders
            raw = [r.get(name, "nan") for r in rows]
            kind = kinds.get(name, np.float64)
            values[name] = (
                np.array([v == "1" for v in raw], dtype=bool) if kind is bool else np.array(raw, dtype=kind)
            )
    except (OSError, UnicodeDecodeError, csv.Error, ValueError, TypeError) as exc:
        raise CrchflError(f"{path}: damaged ({exc}); drive the route again into this folder") from None
    if not rows:
        raise CrchflError(f"{path}: holds no step; drive the route again into this folder")
    return DriveLog(**values)


def plot_trajectories(
    net_path: Path,
    route: RouteGeometry,
    runs: Mapping[str, tuple[DriveLog, Mapping[str, Any]]],
    path: Path,
    box_every_s: float = 2.0,
) -> None:
    """One panel per run (label -> (log, metrics)), side by side: the map, the planned route, the path driven.

    As in the paper's Fig. 5, boxes (the ego's footprint, every ``box_every_s``)
    trace the trajectory. Marks: start (circle), end (square), lane departures
    (orange), off-road (magenta), collisions (black x), red-light violations
    (red triangle). The ego's size comes from each run's metrics.
    """
    plt = pyplot()
    from matplotlib.collections import PolyCollection

    if not runs:
        raise CrchflError("no runs to draw; give at least one drive folder")
    xy = route.xy_m
    xs = np.concatenate([xy[:, 0]] + [lg.x_m for lg, _ in runs.values()])
    ys = np.concatenate([xy[:, 1]] + [lg.y_m for lg, _ in runs.values()])
    margin_m = 20.0
    fig, axes = plt.subplots(1, len(runs), figsize=(5.0 * len(runs), 5.0), squeeze=False)
    for k, (ax, (label, (drive_log, metrics))) in enumerate(zip(axes[0], runs.items())):
        draw_network(ax, net_path)
        ax.plot(xy[:, 0], xy[:, 1], color="tab:blue", linewidth=6, alpha=0.25, label="planned route", zorder=2)
        ax.plot(drive_log.x_m, drive_log.y_m, color="tab:red", linewidth=1.5, label="driven", zorder=3)
        ax.plot(drive_log.x_m[:1], drive_log.y_m[:1], "o", color="tab:green", zorder=4, label="start")
        ax.plot(drive_log.x_m[-1:], drive_log.y_m[-1:], "s", color="tab:red", zorder=4, label="end")
        length_m = float(metrics.get("vehicle_length_m", 5.0))
        width_m = float(metrics.get("vehicle_width_m", 1.8))
        step_s = float(drive_log.t_s[1] - drive_log.t_s[0]) if len(drive_log) > 1 else 1.0
        every = max(1, int(round(box_every_s / step_s)))
        boxes = [
            footprint(drive_log.x_m[i], drive_log.y_m[i], drive_log.heading_rad[i], length_m, width_m)
            for i in range(0, len(drive_log), every)
        ]
        ax.add_collection(PolyCollection(boxes, facecolors="none", edgecolors="tab:red", linewidths=0.8, zorder=3))
        departed = lane_departed(drive_log.offset_m, drive_log.lane_width_m, width_m)
        for mask, style, colour, name in (
            (departed, ".", "orange", "lane departure"),
            (~drive_log.on_road, ".", "magenta", "off road"),
            (drive_log.colliding, "x", "black", "collision"),
            (drive_log.red_light, "^", "red", "red light run"),
        ):
            if mask.any():
                ax.plot(
                    drive_log.x_m[mask], drive_log.y_m[mask], style, color=colour, markersize=6, zorder=5, label=name
                )
        ax.set_xlim(xs.min() - margin_m, xs.max() + margin_m)
        ax.set_ylim(ys.min() - margin_m, ys.max() + margin_m)
        ax.set_title(
            f"{label}\ncompletion {100 * metrics.get('completion', 0):.0f} %, "
            f"collisions {metrics.get('collisions', 0)}, "
            f"departures {metrics.get('lane_departures', 0)}, red {metrics.get('red_light_violations', 0)}",
            fontsize=9,
        )
        if k == 0 or ax.get_legend_handles_labels()[1] != axes[0][0].get_legend_handles_labels()[1]:
            ax.legend(fontsize=7, loc="best")  # once, unless this panel has other marks
    save_figure(fig, path)


def footprint(x_m: float, y_m: float, heading_rad: float, length_m: float, width_m: float) -> np.ndarray:
    """Corners [4, 2] of a vehicle's rectangle centred at (x, y), facing ``heading_rad``."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length_m / 2.0, width_m / 2.0]
    return local @ np.array([[c, s], [-s, c]]) + [x_m, y_m]


# --- a run's files --------------------------------------------------------------------------------


def write_drive_outputs(
    result: DriveResult,
    scenario: Scenario,
    renderer,
    out_dir: Path,
    metrics: Mapping[str, Any],
    label: str,
    video: bool = True,
) -> dict[str, Path]:
    """metrics.json, trajectory.csv, trajectory.png, frames/*.png and drive.mp4 of one drive."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {"metrics": out_dir / DRIVE_METRICS_FILE, "trajectory_csv": out_dir / "trajectory.csv"}
    write_json(written["metrics"], dict(metrics))
    write_trajectory_csv(written["trajectory_csv"], result.log)
    written["trajectory_png"] = out_dir / "trajectory.png"
    runs = {label: (result.log, metrics)}
    plot_trajectories(Path(scenario.net_path), result.route, runs, written["trajectory_png"])
    if not result.frames:
        return written
    moments = pick_moments(result.log)
    turn = turn_moment(result.log, result.route)
    if turn is not None:
        moments["t_junction_turn"] = turn
    for name, row in moments.items():
        path = out_dir / "frames" / f"{name}.png"
        path.parent.mkdir(exist_ok=True)
        write_png(path, _picture(result, renderer, row, name.replace("_", " ")))
        written[name] = path
    if video:
        dt = result.log.t_s[1] - result.log.t_s[0] if len(result.log) > 1 else 1.0
        written["video"] = out_dir / "drive.mp4"
        with VideoWriter(written["video"], fps=1.0 / dt) as writer:
            for row in range(len(result.log) - 1):
                writer.write(_picture(result, renderer, row, f"t {result.log.t_s[row]:.1f} s"))
    log.info("drive outputs in %s: %s", out_dir, ", ".join(sorted(written)))
    return written


def _picture(result: DriveResult, renderer, row: int, caption: str) -> np.ndarray:
    lg = result.log
    action = (lg.throttle[row], lg.steer[row], lg.brake[row])
    caption = f"{caption}  v {lg.speed_mps[row]:.1f} m/s"
    if lg.signal_letter[row]:
        caption += f"  light '{lg.signal_letter[row]}' {lg.signal_dist_m[row]:.0f} m"
    return drive_picture(renderer, result.frames[row], result.ego_id, action, caption)


def compare_runs(run_dirs: Sequence[str | Path], labels: Sequence[str] | None, out_path: str | Path) -> Path:
    """Fig. 5: the drives of several models (run folders of one route) side by side."""
    run_dirs = [Path(d) for d in run_dirs]
    labels = list(labels) if labels else [d.name for d in run_dirs]
    if len(labels) != len(run_dirs):
        raise CrchflError(f"--labels: {len(labels)} labels for {len(run_dirs)} run folders; give one per folder")
    runs = {}
    first = None
    for label, folder in zip(labels, run_dirs):
        metrics_path = folder / DRIVE_METRICS_FILE
        if not metrics_path.is_file():
            raise CrchflError(f"{folder}: no metrics.json; point to folders written by `crchfl-sumo drive`")
        metrics = read_json_object(metrics_path, ("scenario", "edges"), "drive the route again into this folder")
        if not (isinstance(metrics["scenario"], str) and isinstance(metrics["edges"], list)):
            raise CrchflError(
                f"{metrics_path}: its scenario or edges are damaged; drive the route again into this folder"
            )
        key = (metrics["scenario"], tuple(metrics["edges"]))
        if first is None:
            first = key
        elif key != first:
            raise CrchflError(
                f"{folder}: drove {key[1]} in {key[0]}, unlike {run_dirs[0]}; compare drives of one route"
            )
        runs[label] = (read_trajectory_csv(folder / "trajectory.csv"), metrics)
    scenario = load_scenario(first[0])
    route = route_geometry(read_net(Path(scenario.net_path)), first[1])
    out_path = Path(out_path)
    plot_trajectories(Path(scenario.net_path), route, runs, out_path)
    return out_path
