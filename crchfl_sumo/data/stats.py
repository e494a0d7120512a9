"""What a data set holds: label statistics, a summary figure and an example mosaic.

Statistics read only the small label arrays of each shard; the mosaic reads a
handful of samples (one per steer class where the data set has one).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crchfl_sumo.core.atomic import atomic_write_bytes
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.figures import pyplot, save_figure
from crchfl_sumo.core.json_files import write_json
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.data.labels import (
    COMMAND_NAMES, LEFT, NUM_COMMANDS, NUM_STEER_CLASSES, RIGHT, STEER_CLASS_VALUES, STRAIGHT,
)
from crchfl_sumo.data.manifest import read_manifest
from crchfl_sumo.data.recovery import FORWARD_M, LATERAL_M, YAW_DEG
from crchfl_sumo.data.route_commands import command_from_turn
from crchfl_sumo.data.shards import LABEL_SHAPES, open_shard, read_shard
from crchfl_sumo.vision.camera import CAMERA_NAMES

log = logging.getLogger(__name__)

PEDAL_BINS = np.linspace(0.0, 1.0, 11)  # 10 bins of width 0.1 for throttle and brake
SPEED_BINS = np.arange(0.0, 17.0, 1.0)  # 1 m/s bins up to 16 m/s (the towns' limit is 13.9 m/s)


def dataset_stats(root: str | Path, verify: bool = True) -> dict[str, Any]:
    """Label statistics of the data set in ``root`` (JSON-ready dict).

    Keys: scenario, seed, samples, png_bytes_per_sample, per_vehicle (list of
    vehicle/town/edge/split/samples), and per split ('train', 'test', 'all'):
    steer_class_counts [7], command_counts [4] (labels.COMMAND_NAMES),
    throttle_hist / brake_hist [10] over PEDAL_BINS, speed_hist [16] over
    SPEED_BINS, throttle_mean, brake_mean, steer_mean, speed_mean,
    standing_share (speed below the expert's stop_speed_mps), hard_brake_share
    (brake >= 0.8), recovery_share (samples rendered from a pose off the track),
    queue_share (standing samples rendered moved towards the leader), red_line_share (standing samples
    rendered moved back from a red stop line).
    """
    root = Path(root)
    manifest = read_manifest(root)
    stop_speed_mps = float(manifest.labels.get("expert", {}).get("stop_speed_mps", ExpertConfig().stop_speed_mps))
    columns = ("actions", "steer_class", "command", "speed_mps", "perturbation")
    parts: dict[str, dict[str, list[np.ndarray]]] = {split: {c: [] for c in columns} for split in ("train", "test")}
    image_hw = (manifest.image_height, manifest.image_width)
    for entry in manifest.shards:
        data = read_shard(root, entry, verify=verify, images=False, image_hw=image_hw)
        for c in columns:
            parts[entry.split][c].append(getattr(data, c))
    stats: dict[str, Any] = {
        "scenario": manifest.scenario,
        "seed": manifest.seed,
        "samples": manifest.samples,
        "png_bytes_per_sample": round(manifest.png_bytes_per_sample, 1),
        "per_vehicle": [
            {"vehicle": s.vehicle, "town": s.town, "edge": s.edge, "split": s.split, "samples": s.samples}
            for s in manifest.shards
        ],
    }
    for split in ("train", "test", "all"):
        chosen = ("train", "test") if split == "all" else (split,)
        arrays = {}
        for c in columns:
            pieces = [p for name in chosen for p in parts[name][c]]
            arrays[c] = np.concatenate(pieces) if pieces else np.zeros((0, *LABEL_SHAPES.get(c, ())))
        stats[split] = _label_summary(**arrays, stop_speed_mps=stop_speed_mps)
    return stats


def _label_summary(
    actions: np.ndarray,
    steer_class: np.ndarray,
    command: np.ndarray,
    speed_mps: np.ndarray,
    perturbation: np.ndarray,
    stop_speed_mps: float,
) -> dict[str, Any]:
    def mean(values: np.ndarray) -> float:
        return round(float(values.mean()), 4) if len(values) else 0.0

    return {
        "samples": int(len(actions)),
        "steer_class_counts": np.bincount(steer_class.astype(np.int64), minlength=NUM_STEER_CLASSES).tolist(),
        "command_counts": np.bincount(command.astype(np.int64), minlength=NUM_COMMANDS).tolist(),
        "throttle_hist": np.histogram(actions[:, 0], PEDAL_BINS)[0].tolist(),
        "brake_hist": np.histogram(actions[:, 2], PEDAL_BINS)[0].tolist(),
        "speed_hist": np.histogram(np.clip(speed_mps, 0.0, SPEED_BINS[-1]), SPEED_BINS)[0].tolist(),
        "throttle_mean": mean(actions[:, 0]),
        "brake_mean": mean(actions[:, 2]),
        "steer_mean": mean(actions[:, 1]),
        "speed_mean": mean(speed_mps),
        "standing_share": mean((speed_mps < stop_speed_mps).astype(np.float64)),
        "hard_brake_share": mean((actions[:, 2] >= 0.8).astype(np.float64)),
        "recovery_share": mean(np.any(perturbation[:, [LATERAL_M, YAW_DEG]] != 0, axis=1).astype(np.float64)),
        "queue_share": mean((perturbation[:, FORWARD_M] > 0).astype(np.float64)),
        "red_line_share": mean((perturbation[:, FORWARD_M] < 0).astype(np.float64)),
    }


def plot_stats(stats: dict[str, Any], out_png: Path) -> Path:
    """Figure: steer-class histogram, throttle and brake distributions, samples per vehicle."""
    plt = pyplot()

    fig, axes = plt.subplots(2, 3, figsize=(16, 7))
    order = np.argsort(STEER_CLASS_VALUES)  # plot classes left (negative) to right (positive)
    for split, offset in (("train", -0.2), ("test", 0.2)):
        counts = np.asarray(stats[split]["steer_class_counts"])[order]
        axes[0, 0].bar(np.arange(NUM_STEER_CLASSES) + offset, counts, width=0.4, label=split)
    axes[0, 0].set_xticks(range(NUM_STEER_CLASSES), [f"{v:+.3f}\n(c{k})" for k, v in zip(order, STEER_CLASS_VALUES[order])])
    axes[0, 0].set_title("steer classes (negative = left)")
    axes[0, 0].legend()
    centres = (PEDAL_BINS[:-1] + PEDAL_BINS[1:]) / 2
    for ax, name in ((axes[0, 1], "throttle"), (axes[1, 0], "brake")):
        for split, offset in (("train", -0.02), ("test", 0.02)):
            ax.bar(centres + offset, stats[split][f"{name}_hist"], width=0.04, label=split)
        ax.set_yscale("symlog")
        ax.set_xlabel(name)
        ax.set_title(f"{name} (mean train {stats['train'][f'{name}_mean']:.3f})")
        ax.legend()
    for split, offset in (("train", -0.2), ("test", 0.2)):
        axes[0, 2].bar(np.arange(NUM_COMMANDS) + offset, stats[split]["command_counts"], width=0.4, label=split)
    axes[0, 2].set_xticks(range(NUM_COMMANDS), list(COMMAND_NAMES))
    axes[0, 2].set_title("route commands")
    axes[0, 2].legend()
    speed_centres = (SPEED_BINS[:-1] + SPEED_BINS[1:]) / 2
    for split, offset in (("train", -0.2), ("test", 0.2)):
        axes[1, 2].bar(speed_centres + offset, stats[split]["speed_hist"], width=0.4, label=split)
    axes[1, 2].set_xlabel("speed [m/s]")
    axes[1, 2].set_title(f"speed (standing share train {stats['train']['standing_share']:.2f})")
    axes[1, 2].legend()
    rows = stats["per_vehicle"]
    axes[1, 1].barh(
        [f"{r['town']} {r['vehicle']} ({r['split']})" for r in rows],
        [r["samples"] for r in rows],
        color=["C0" if r["split"] == "train" else "C1" for r in rows],
    )
    axes[1, 1].invert_yaxis()
    axes[1, 1].set_title("samples per vehicle")
    fig.suptitle(f"{stats['scenario']} seed {stats['seed']}: {stats['samples']} samples")
    fig.tight_layout()
    return save_figure(fig, out_png, dpi=100)


def pick_examples(root: str | Path, split: str = "train") -> list[tuple[str, int]]:
    """(shard file, row) of the first sample of each steer class, classes ordered left to right."""
    root = Path(root)
    manifest = read_manifest(root)
    found: dict[int, tuple[str, int]] = {}
    for entry in manifest.select(split):
        data = read_shard(root, entry, verify=False, images=False, image_hw=(manifest.image_height, manifest.image_width))
        for k in range(NUM_STEER_CLASSES):
            rows = np.flatnonzero(data.steer_class == k)
            if k not in found and len(rows):
                found[k] = (entry.file, int(rows[len(rows) // 2]))
    return [found[int(k)] for k in np.argsort(STEER_CLASS_VALUES) if int(k) in found]


def write_mosaic(root: str | Path, out_png: Path, split: str = "train", min_width_px: int = 200) -> Path:
    """PNG: one row per example sample, the four cameras side by side, its label above."""
    root = Path(root)
    manifest = read_manifest(root)
    examples = pick_examples(root, split)
    if not examples:
        raise CrchflError(f"{root}: no {split} samples to show in a mosaic; generate a data set with {split} shards")
    scale = max(1, int(np.ceil(min_width_px / manifest.image_width)))
    rows = []
    for file, row in examples:
        with open_shard(root, manifest.entry(file), image_hw=(manifest.image_height, manifest.image_width)) as (f, labels):
            images = f["images"][row]
        throttle, steer, brake = labels["actions"][row]
        steer_class = int(labels["steer_class"][row])
        command = COMMAND_NAMES[int(labels["command"][row])]
        lateral_m, yaw_deg, forward_m = labels["perturbation"][row]
        tiles = [cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST) for img in images]
        strip = np.concatenate(tiles, axis=1)
        caption = np.full((22, strip.shape[1], 3), 255, np.uint8)
        text = (
            f"{file}#{row}  throttle {throttle:.2f}  steer {steer:+.3f} (class {steer_class}: "
            f"{STEER_CLASS_VALUES[steer_class]:+.3f})  brake {brake:.2f}  {command}"
            + (f"  off {lateral_m:+.2f} m {yaw_deg:+.1f} deg" if lateral_m or yaw_deg else "")
            + (f"  {forward_m:.2f} m nearer the leader" if forward_m > 0 else "")
            + (f"  {-forward_m:.2f} m back from the red line" if forward_m < 0 else "")
            + f"   [{' | '.join(CAMERA_NAMES)}]"
        )
        cv2.putText(caption, text, (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        rows.append(np.concatenate([caption, strip], axis=0))
    mosaic = np.concatenate(rows, axis=0)
    out_png = Path(out_png)
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(mosaic, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("OpenCV failed to encode the mosaic")
    atomic_write_bytes(out_png, encoded.tobytes())
    return out_png


TURN_COMMANDS = (LEFT, RIGHT, STRAIGHT)


def offered_commands(net, junction_id: str) -> set[int]:
    """The turn commands (LEFT, RIGHT, STRAIGHT) the junction's connections offer, each read off the turn from
    the incoming edge's last direction to the outgoing edge's first (route_commands.command_from_turn);
    U-turns are no command."""
    commands = set()
    for edge in net.getNode(junction_id).getIncoming():
        if edge.getFunction() == "internal":
            continue
        (ax, ay), (bx, by) = edge.getShape()[-2:]
        for out, connections in edge.getOutgoing().items():
            if out.getFunction() == "internal" or all(c.getDirection() == "t" for c in connections):
                continue
            (cx, cy), (dx, dy) = out.getShape()[:2]
            turn = math.remainder(math.atan2(dy - cy, dx - cx) - math.atan2(by - ay, bx - ax), 2 * math.pi)
            commands.add(int(command_from_turn(turn)))
    return commands


def junction_commands(net, x_m: np.ndarray, y_m: np.ndarray, command: np.ndarray) -> dict[str, Any]:
    """The samples of each turn command at each junction with a choice (sumo.turns.choice_junctions), and
    the commands those junctions offer that no sample shows.

    A sample with a turn command counts at the choice junction whose centre is nearest: its command starts
    CommandConfig.lookahead_m (25 m) before its junction and ends as the vehicle leaves it. Keys:
    ``junctions`` (id -> {left, right, straight: samples, offered: [names]}), ``offered`` (junction-command
    pairs in all), ``missing`` (["JUNCTION COMMAND", ...]: offered, no sample).
    """
    from scipy.spatial import cKDTree

    from crchfl_sumo.sumo.turns import choice_junctions

    junctions = choice_junctions(net)
    counts = np.zeros((len(junctions), len(TURN_COMMANDS)), dtype=np.int64)
    turning = np.isin(command, TURN_COMMANDS)
    if junctions and turning.any():
        centres = np.array([j.shape_m.mean(axis=0) for j in junctions])
        _, nearest = cKDTree(centres).query(np.stack([x_m[turning], y_m[turning]], axis=1))
        np.add.at(counts, (nearest, [TURN_COMMANDS.index(int(c)) for c in command[turning]]), 1)
    table, missing, offered_in_all = {}, [], 0
    for junction, row in zip(junctions, counts):
        offered = [c for c in TURN_COMMANDS if c in offered_commands(net, junction.id)]
        offered_in_all += len(offered)
        missing += [f"{junction.id} {COMMAND_NAMES[c]}" for c in offered if not row[TURN_COMMANDS.index(c)]]
        table[junction.id] = {**{COMMAND_NAMES[c]: int(n) for c, n in zip(TURN_COMMANDS, row)},
                              "offered": [COMMAND_NAMES[c] for c in offered]}
    return {"junctions": table, "offered": offered_in_all, "missing": missing}


def dataset_junction_commands(root: str | Path, scenario: str | Path | None = None) -> dict[str, Any] | None:
    """``junction_commands`` of the training split on the network of ``scenario``; without one, of the
    scenario the manifest names, or None (with a log line) where that cannot be found. A ``scenario``
    given that cannot be found raises CrchflError."""
    from crchfl_sumo.sumo.route import read_net
    from crchfl_sumo.sumo.scenario import load_scenario

    root = Path(root)
    manifest = read_manifest(root)
    if scenario is not None:
        net_path = load_scenario(scenario).net_path
    else:
        try:
            net_path = load_scenario(manifest.scenario).net_path
        except CrchflError as exc:
            log.info("no junction commands: %s (name its scenario with dataset-stats --scenario)", exc)
            return None
    xs, ys, commands = [], [], []
    for entry in manifest.select("train"):
        data = read_shard(root, entry, verify=False, images=False, image_hw=(manifest.image_height, manifest.image_width))
        xs.append(data.x_m)
        ys.append(data.y_m)
        commands.append(data.command)
    if not xs:
        return None
    return junction_commands(read_net(net_path), np.concatenate(xs), np.concatenate(ys), np.concatenate(commands))


def write_dataset_stats(root: str | Path, out_dir: str | Path | None = None,
                        scenario: str | Path | None = None) -> dict[str, Any]:
    """Stats JSON (with ``junction_commands``: dataset_junction_commands), summary figure and mosaic into
    ``out_dir`` (default: the data set folder).

    Returns the statistics with the written paths under 'files'.
    """
    root = Path(root)
    out_dir = Path(out_dir) if out_dir is not None else root
    stats = dataset_stats(root)
    stats["junction_commands"] = dataset_junction_commands(root, scenario)  # before any write: it may refuse
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {"figure": str(plot_stats(stats, out_dir / "dataset_stats.png"))}
    if stats["train"]["samples"]:
        files["mosaic"] = str(write_mosaic(root, out_dir / "dataset_mosaic.png"))
    stats["files"] = files
    write_json(out_dir / "dataset_stats.json", stats)
    log.info("wrote %s", ", ".join(files.values()))
    return stats
