"""The data set generation pipeline: simulate, label, render, write shards.

1. Run the scenario once and keep every step's Frame (small: arrays per
   vehicle). Each planned vehicle is sampled every ``sample_period_s`` from
   its departure until it has its sample count; the run goes on
   ``FUTURE_S`` more seconds so the last samples have a path ahead to label.
   It also goes on until each of them has driven ``CommandConfig.path_ahead_m``
   past its last sample, so that the last samples' route commands are known
   (recording.py).
2. Per shard (one vehicle): build its track from all frames, label every
   step with the expert (expert.py) and its route command (commands.py),
   keep the sampled steps, draw which of them become recovery samples
   (recovery.py; seeded by the data set seed and the shard's place in the
   plan).
3. Render the four camera images (raster.py) from the track's pose or the
   perturbed one, frame by frame: all the samples of a frame in one call, for
   as many shards at a time as ``RENDER_GROUP_BYTES`` of images hold
   (rendering.py); then write each shard (shards.py) and its manifest entry
   (manifest.py).

Shards already finished by an earlier run with the same settings are
skipped (their rendering is the expensive part; the simulation is rerun,
and with the same seed it reproduces the same frames). Which vehicles are
sampled is the scenario's choice: each town lists its ``data_vehicles`` and
``test_vehicles`` (scenario.toml), started in different parts of the town.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from crchfl_sumo.core.config import from_mapping, read_toml, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_seed
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.data.expert import (
    ExpertConfig,
    Track,
    expert_labels,
    is_standing,
    target_speeds,
    tracks_from_frames,
)
from crchfl_sumo.data.labels import SIGNAL_RED, digitize_steer, signal_codes
from crchfl_sumo.data.manifest import Manifest, label_schema
from crchfl_sumo.data.recording import record_run, steps_per_sample
from crchfl_sumo.data.recovery import (
    FORWARD_M,
    draw_perturbations,
    draw_queue_shifts,
    draw_red_line_shifts,
    gap_ahead,
    recovery_steer,
)
from crchfl_sumo.data.rendering import RenderJob, render_groups, render_samples
from crchfl_sumo.data.route_commands import CommandConfig, track_commands, track_lane_changes
from crchfl_sumo.data.settings import PAPER_TOWNS, DatasetConfig, PlannedShard, TownSplit, shard_plan
from crchfl_sumo.data.shards import DatasetWriter, ShardData
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.sumo.outputs import sumo_output_files, sumo_output_options
from crchfl_sumo.sumo.route import LaneChange, read_net
from crchfl_sumo.sumo.scenario import DEFAULT_COVERAGE_RADIUS_M, Scenario, SumoConfig, configured_scenario
from crchfl_sumo.sumo.sites import EdgeSite
from crchfl_sumo.sumo.turns import choice_junctions
from crchfl_sumo.vision.raster import RasterConfig, Renderer, neighbourhood_m
from crchfl_sumo.vision.world import WorldConfig, build_world

log = logging.getLogger(__name__)

RECOVERY_STREAM = 15  # the recovery draws' own random stream: SeedSequence([seed, RECOVERY_STREAM, shard])


def assign_vehicles(scenario: Scenario, plan: Sequence[PlannedShard]) -> dict[str, str]:
    """Shard file -> vehicle id, from the scenario towns' data/test vehicle lists."""
    towns = {t.name: t for t in scenario.towns}
    wanted = Counter((shard.town, shard.split) for shard in plan)
    assigned = {}
    for shard in plan:
        town = towns.get(shard.town)
        if town is None:
            raise CrchflError(
                f"dataset.towns: scenario '{scenario.name}' has no town '{shard.town}' "
                f"(it has: {', '.join(sorted(towns))}); name one of those"
            )
        vehicles = town.data_vehicles if shard.split == "train" else town.test_vehicles
        key = "data_vehicles" if shard.split == "train" else "test_vehicles"
        if shard.index >= len(vehicles):
            if not (town.data_vehicles or town.test_vehicles):
                # A plain .sumocfg: its one town is the whole network, with no vehicles named.
                fix = (f"put a scenario.toml beside {scenario.sumocfg_path.name} whose [[towns]] name {key}: "
                       "vehicles that stay in the simulation for the whole run, e.g. on looping routes "
                       "(docs/scenarios.md), and pass its folder")
            elif scenario.injected:
                fix = ("ask for fewer, or add more ([sumo] data_vehicles and test_vehicles of the dataset and run "
                       "configs, docs/scenarios.md)")
            else:
                fix = "ask for fewer or name more"
            raise CrchflError(
                f"dataset.towns.{shard.town}: {wanted[shard.town, shard.split]} {shard.split} vehicles wanted, "
                f"scenario '{scenario.name}' names {len(vehicles)} in its town's {key}; {fix}"
            )
        assigned[shard.file] = vehicles[shard.index]
    return assigned


def nearest_site(sites: Sequence[EdgeSite], x_m: np.ndarray, y_m: np.ndarray) -> str:
    """The edge site nearest to most of the given positions ('' without sites)."""
    if not sites or len(x_m) == 0:
        return ""
    sx = np.array([s.x_m for s in sites])
    sy = np.array([s.y_m for s in sites])
    nearest = np.hypot(x_m[:, None] - sx, y_m[:, None] - sy).argmin(axis=1)
    return sites[int(np.bincount(nearest, minlength=len(sites)).argmax())].name


def generate_dataset(
    scenario: Scenario,
    out_dir: str | Path,
    seed: int = 0,
    sizes: DatasetConfig = DatasetConfig(),
    raster: RasterConfig = RasterConfig(),
    world: WorldConfig = WorldConfig(),
    expert: ExpertConfig = ExpertConfig(),
    progress: Progress | None = None,
    timings_s: dict[str, float] | None = None,
    command: CommandConfig = CommandConfig(),
    vehicles_per_call: int | None = None,
    sumo_outputs: Mapping[str, Path] | None = None,
) -> Manifest:
    """Generate (or finish) the data set of ``scenario`` in ``out_dir``; returns its manifest.

    ``sumo_outputs`` (sumo.outputs.sumo_output_files): SUMO's own files of the simulation run it makes
    (a resumed generation's: of the run for its unfinished shards; none when none is left).

    ``timings_s``, when given, receives the wall seconds spent in each stage:
    simulate, world (static world build), label, render, write.
    ``vehicles_per_call`` caps the samples of a frame rendered in one call
    (render_samples; None: all of them, 1: one by one).
    """
    seed = check_seed(seed, "generate_dataset: seed")
    clock = _StageClock(timings_s)
    plan = shard_plan(sizes)
    vehicles = assign_vehicles(scenario, plan)
    steps_per_sample(scenario, sizes.sample_period_s)  # refused before anything is written
    header = Manifest(
        scenario=scenario.name,
        seed=int(seed),
        sample_period_s=sizes.sample_period_s,
        image_height=raster.camera.height_px,
        image_width=raster.camera.width_px,
        camera={"raster": to_mapping(raster), "world": to_mapping(world)},
        labels={
            **label_schema(),
            "expert": to_mapping(expert),
            "command": to_mapping(command),
            "lane_change_s": sizes.lane_change_s,
            "recovery": {
                "share": sizes.recovery_share,
                "lateral_m": sizes.recovery_lateral_m,
                "yaw_deg": sizes.recovery_yaw_deg,
                "queue_share": sizes.recovery_queue_share,
                # only where set: the header of a data set without red-line samples stays as written before
                **({"red_share": sizes.recovery_red_share} if sizes.recovery_red_share else {}),
            },
            # only where not 1: the header of a data set that samples standing vehicles like moving ones stays as before
            **({"standing_sample_every": sizes.standing_sample_every} if sizes.standing_sample_every != 1 else {}),
        },
        compression=sizes.compression,
    )
    writer = DatasetWriter(Path(out_dir), header)
    pending = [p for p in plan if not writer.is_done(p.file)]
    if not pending:
        log.info("%s: all %d shards already finished", out_dir, len(plan))
        return writer.manifest
    log.info("%d of %d shards to write", len(pending), len(plan))
    needed = {vehicles[p.file]: p.samples for p in pending}
    net = read_net(Path(scenario.net_path))
    lane_change_s = sizes.lane_change_s if multi_lane(net) else 0.0
    with clock("simulate"), sumo_output_options(sumo_outputs) as options:
        frames, sampled = record_run(
            scenario, seed, needed, sizes.sample_period_s, progress, neighbourhood_m(raster), command.path_ahead_m,
            sumo_options=(*options, "--lanechange.duration", f"{lane_change_s:g}") if lane_change_s else options,
            standing_every=sizes.standing_sample_every, stop_speed_mps=expert.stop_speed_mps,
        )
    with clock("label"):
        tracks = tracks_from_frames(frames)
        junctions = choice_junctions(net)
    with clock("world"):
        renderer = Renderer(build_world(scenario.net_path, world), raster)
    total = sum(needed.values())
    done = 0
    for group in render_groups(pending, renderer.shape):
        labelled = []
        for shard in group:
            vehicle = vehicles[shard.file]
            track = tracks[vehicle]
            frame_rows = sampled[vehicle]
            rows = np.searchsorted(track.t_s, [frames[i].t_s for i in frame_rows])
            with clock("label"):
                rng = np.random.default_rng(np.random.SeedSequence([int(seed), RECOVERY_STREAM, plan.index(shard)]))
                gap_m = None if sizes.recovery_queue_share == 0 else np.array(
                    [gap_ahead(frames[i], vehicle, expert.stop_speed_mps) for i in frame_rows]
                )
                red_line_m = None if sizes.recovery_red_share == 0 else red_line_distances(
                    [frames[i] for i in frame_rows], vehicle
                )
                changes = track_lane_changes(track, net, lane_change_s)
                labels = sample_labels(track, rows, junctions, sizes, expert, command, rng, gap_m, changes, red_line_m)
            labelled.append((shard, vehicle, rows, labels, RenderJob(vehicle, frame_rows, labels.perturbation)))
        with clock("render"):
            images = render_samples(
                renderer, frames, [job for *_, job in labelled], vehicles_per_call,
                lambda rendered: report(progress, "render", done + rendered, total),
            )
        for (shard, vehicle, rows, labels, _), shard_images in zip(labelled, images):
            track = tracks[vehicle]
            data = ShardData(
                images=shard_images,
                actions=labels.actions,
                steer_class=labels.steer_class,
                command=labels.command,
                speed_mps=labels.speed_mps,
                target_speed_mps=labels.target_speed_mps,
                perturbation=labels.perturbation,
                t_s=track.t_s[rows],
                x_m=track.x_m[rows],
                y_m=track.y_m[rows],
                heading_rad=track.heading_rad[rows],
                **signal_columns([frames[i] for i in sampled[vehicle]], vehicle, labels.perturbation[:, FORWARD_M]),
            )
            edge = nearest_site(scenario.edge_sites, data.x_m, data.y_m)
            with clock("write"):
                writer.add(shard.file, data, vehicle=vehicle, town=shard.town, edge=edge, split=shard.split)
            done += len(rows)
            report(progress, "write", done, total)
    return writer.manifest


def multi_lane(net) -> bool:
    """Has the network an edge of two lanes or more? Only there does a data run set SUMO's
    --lanechange.duration: on the towns' single lanes it still changed SUMO's driving (measured: the same
    seed's tracks parted after 36 s), and they have no lane to change to."""
    return any(edge.getLaneNumber() > 1 for edge in net.getEdges(withInternal=False))


def signal_columns(frames: Sequence[Frame], vehicle: str, forward_m: np.ndarray) -> dict[str, np.ndarray]:
    """Per sample (one frame each): the next signal's state code and stop-line distance, and the yield gap
    (ShardData's signal_state, signal_distance_m, yield_gap_m). A sample drawn ``forward_m`` ahead of its
    track (a queue sample; a red-line sample's is negative) is that much nearer the stop line."""
    rows = [frame.index_of(vehicle) for frame in frames]
    state, distance = _next_signals(frames, rows)
    return {
        "signal_state": state,
        "signal_distance_m": np.maximum(distance - np.asarray(forward_m, dtype=np.float64), 0.0).astype(np.float32),
        "yield_gap_m": np.array([frame.foe_gap_m[r] for frame, r in zip(frames, rows)], dtype=np.float32),
    }


def red_line_distances(frames: Sequence[Frame], vehicle: str) -> np.ndarray:
    """Per sample (one frame each) the distance to the stop line of a next signal that shows red; inf otherwise."""
    state, distance = _next_signals(frames, [frame.index_of(vehicle) for frame in frames])
    return np.where(state == SIGNAL_RED, distance, np.inf)


def _next_signals(frames: Sequence[Frame], rows: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Per frame the state code (int8) and stop-line distance (float64, inf: none) of the next signal of the
    vehicle in row ``rows[i]`` of frame i."""
    state = signal_codes([frame.tls_ahead_state[r] for frame, r in zip(frames, rows)])
    return state, np.array([frame.tls_ahead_dist_m[r] for frame, r in zip(frames, rows)], dtype=np.float64)


@dataclass(frozen=True)
class SampleLabels:
    """The labels of one vehicle's samples (R of them): what its shard stores besides images and pose."""

    actions: np.ndarray  # float32 [R, 3]
    steer_class: np.ndarray  # int64 [R]
    command: np.ndarray  # int64 [R]
    speed_mps: np.ndarray  # float32 [R]
    target_speed_mps: np.ndarray  # float32 [R]; a recovery sample keeps its track's, a queue or red-line sample's is 0
    perturbation: np.ndarray  # float32 [R, 3] (lateral_m, yaw_deg, forward_m)


def sample_labels(
    track: Track,
    rows: np.ndarray,
    junctions,
    sizes: DatasetConfig,
    expert: ExpertConfig,
    command: CommandConfig,
    rng: np.random.Generator,
    gap_m: np.ndarray | None = None,
    lane_changes: Sequence[LaneChange] = (),
    red_line_m: np.ndarray | None = None,
) -> SampleLabels:
    """Labels of the samples at track rows ``rows``, recovery draws included (``rng`` draws them).

    ``gap_m`` [R]: each sample's gap to a standing leader ahead (recovery.gap_ahead; inf for
    none), which queue samples need; None: no sample has one. ``lane_changes``: the track's
    (route_commands.track_lane_changes). ``red_line_m`` [R]: each sample's distance to a red stop line
    (red_line_distances), which red-line samples need; None: no sample has one.
    """
    actions, _ = expert_labels(track, expert)
    actions = actions[rows]
    standing = is_standing(track.speed_mps[rows], track.accel_mps2[rows], expert)
    # float32 before labelling: the steer label is worked out from the pose the images are drawn from
    perturbation = draw_perturbations(
        ~standing, sizes.recovery_share, sizes.recovery_lateral_m, sizes.recovery_yaw_deg, rng
    ).astype(np.float32)
    recovered = np.flatnonzero(np.any(perturbation != 0, axis=1))
    actions[recovered, 1] = recovery_steer(track, rows[recovered], perturbation[recovered], expert)
    queue_shifts = draw_queue_shifts(standing, gap_m, sizes.recovery_queue_share, rng)
    perturbation[:, FORWARD_M] = draw_red_line_shifts(standing, red_line_m, queue_shifts, sizes.recovery_red_share, rng)
    target_speed = target_speeds(track, expert)[rows]
    # too close to the leader to go, or before a red line: stay, whatever the queue or the light does next
    target_speed[perturbation[:, FORWARD_M] != 0] = 0.0
    return SampleLabels(
        actions=actions,
        steer_class=digitize_steer(actions[:, 1]),
        command=track_commands(track.x_m, track.y_m, junctions, command, lane_changes)[rows],
        speed_mps=track.speed_mps[rows].astype(np.float32),
        target_speed_mps=target_speed,
        perturbation=perturbation,
    )


@dataclass(frozen=True)
class GenerateConfig:
    """Settings of `crchfl-sumo dataset` (TOML: top-level ``seed``, ``[dataset]``,
    ``[raster]`` (with ``[raster.camera]``), ``[world]``, ``[expert]``, ``[command]``, ``[sumo]`` (the
    scenario as a run's [sumo] changes it: its vehicles added where it names none, its sites, traffic))."""

    seed: int = 0
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    raster: RasterConfig = field(default_factory=RasterConfig)
    world: WorldConfig = field(default_factory=WorldConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    command: CommandConfig = field(default_factory=CommandConfig)
    sumo: SumoConfig = field(default_factory=SumoConfig)


def load_generate_config(path: str | Path | None, seed: int | None = None) -> GenerateConfig:
    """The config file's settings (defaults without one); ``seed`` overrides the file's."""
    config = GenerateConfig() if path is None else from_mapping(GenerateConfig, read_toml(path), where=str(path))
    if seed is not None:
        config = dataclasses.replace(config, seed=int(seed))
    return config


class _StageClock:
    """``with clock("stage"):`` adds the block's wall seconds to ``timings_s[stage]`` (no-op without)."""

    def __init__(self, timings_s: dict[str, float] | None):
        self._timings_s = timings_s

    @contextlib.contextmanager
    def __call__(self, stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            if self._timings_s is not None:
                self._timings_s[stage] = self._timings_s.get(stage, 0.0) + time.perf_counter() - start


# A town of a scenario other than the paper's, whose data set config names no towns: samples a vehicle
# (at the paper's 0.25 s, 2 minutes of driving each).
DEFAULT_TRAIN_SAMPLES = 500
DEFAULT_TEST_SAMPLES = 250


def sizes_for(sizes: DatasetConfig, scenario: Scenario) -> DatasetConfig:
    """``sizes`` for ``scenario``: as given, unless they are the default (the paper's towns) and the scenario
    lacks those towns; then each of its towns' data and test vehicles gets DEFAULT_TRAIN_SAMPLES and
    DEFAULT_TEST_SAMPLES."""
    names = {town.name for town in scenario.towns}
    if sizes.towns != PAPER_TOWNS or {split.town for split in PAPER_TOWNS} <= names:
        return sizes
    towns = tuple(
        TownSplit(town.name, (DEFAULT_TRAIN_SAMPLES,) * len(town.data_vehicles),
                  (DEFAULT_TEST_SAMPLES,) * len(town.test_vehicles))
        for town in scenario.towns if town.data_vehicles or town.test_vehicles
    )
    return dataclasses.replace(sizes, towns=towns)


def run_dataset_command(
    scenario_name: str,
    out_dir: Path,
    seed: int | None = None,
    config_path: Path | None = None,
    progress: Progress | None = None,
    sumo_outputs: Sequence[str] = (),
) -> Manifest:
    """What `crchfl-sumo dataset SCENARIO --out DIR [--seed S] [--config TOML] [--sumo-output NAMES]` does."""
    files = sumo_output_files(sumo_outputs, out_dir)  # an unknown name is refused before anything runs
    config = load_generate_config(config_path, seed)
    scenario = configured_scenario(scenario_name, config.sumo, DEFAULT_COVERAGE_RADIUS_M)
    return generate_dataset(
        scenario,
        out_dir,
        config.seed,
        sizes_for(config.dataset, scenario),
        config.raster,
        config.world,
        config.expert,
        progress,
        command=config.command,
        sumo_outputs=files,
    )
