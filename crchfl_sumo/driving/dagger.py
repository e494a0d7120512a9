"""DAgger (Ross et al. 2011): the learner drives, the expert labels the states the learner visits.

A model that strays from its data (stops short of a green stop line, drifts
off the lane centre) meets states the expert's data never showed. Here the
scripted RoutePolicy, which knows the route and reads the signals, labels
every ``every``-th step of the learner's own drives with the action it would
take there, in the data set's conventions (expert.pedals, the steer's
class by labels.digitize_steer). The images are the ones the learner saw, the
command the one it was given and the speed its own. Aggregating these samples
with the data set and fine-tuning on the whole is one DAgger iteration
(``dagger_iterations``; `crchfl-sumo dagger` runs it, tools/dagger.py
measures each iteration with drive-bench).

Routes are drawn like drive-bench's episodes (drive_bench_tasks.draw_episodes), by
a seed of their own: use another seed than the benchmark's, so the learner
is not trained on the episodes it is scored on.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
import zipfile
from pathlib import Path
from typing import Sequence

import numpy as np

from crchfl_sumo.core.atomic import atomic_path
from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.json_files import write_json
from crchfl_sumo.core.numbers import MAX_EPOCHS, check_range, check_seed
from crchfl_sumo.core.result_files import MODEL_FILE, SUMMARY_FILE
from crchfl_sumo.data.dataset import load_samples
from crchfl_sumo.data.expert import ExpertConfig, target_speed_from_accel
from crchfl_sumo.data.labels import digitize_steer, signal_codes
from crchfl_sumo.data.manifest import DRIVE_SETTINGS, read_manifest
from crchfl_sumo.data.samples import FIELDS, Samples
from crchfl_sumo.driving.dagger_settings import (
    FINE_TUNE_CLASS_WEIGHTING,
    FINE_TUNE_CLASS_WEIGHTINGS,
    FINE_TUNE_LEARNING_RATE,
    KEEP_START_WEIGHTING,
    MAX_ITERATIONS,
    DaggerConfig,
)
from crchfl_sumo.driving.drive import drive
from crchfl_sumo.driving.drive_bench import SUMO_LOG_DIR, episode_log
from crchfl_sumo.driving.drive_bench_tasks import Episode, draw_episodes, task_by_name, without_traffic
from crchfl_sumo.driving.drivers import ModelDriver, single_torch_thread
from crchfl_sumo.driving.policies import Action, ModelPolicy, Observation, RoutePolicy, RoutePolicyConfig
from crchfl_sumo.learning.centralized import train_centralized
from crchfl_sumo.learning.checkpoint import load_checkpoint
from crchfl_sumo.learning.settings import TrainConfig
from crchfl_sumo.sumo.route import RouteGeometry, inside_crossing, next_signal, point_at, read_net, route_geometry
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.vision.camera import CAMERA_NAMES

log = logging.getLogger(__name__)


# The expert takes the wheel when the ego's centre leaves its lane (half a lane width out) or its
# heading is more than TAKEOVER_HEADING_DEG off the route's: beyond the data set's recovery
# samples (DatasetConfig.recovery_yaw_deg, 15 degrees), whose labels the model learned to follow.
# It hands the wheel back once the centre is within TAKEOVER_RETURN_FRACTION of a lane width of the
# centre line and the heading within half the angle.
TAKEOVER_HEADING_DEG = 15.0
TAKEOVER_RETURN_FRACTION = 0.25


def heading_error_rad(observation: Observation, route) -> float:
    """The ego's heading minus the route's at its progress, wrapped to (-pi, pi]."""
    route_heading = point_at(route, observation.progress_m)[2]
    error = float(observation.frame.heading_rad[observation.ego_row]) - route_heading
    return math.atan2(math.sin(error), math.cos(error))


class ExpertLabelled:
    """A policy that acts as ``learner`` and records what ``expert`` would do, every ``every``-th step.

    While the learner keeps its centre in the planned lane and its heading within
    ``TAKEOVER_HEADING_DEG`` of the route's, it drives and its states are labelled. Beyond either,
    the expert takes the wheel and drives until the centre is back within
    ``TAKEOVER_RETURN_FRACTION`` of a lane width of the centre line and the heading within half the
    angle; those states are not labelled (HG-DAgger, Kelly et al. 2019: the expert takes over where
    the learner fails). Such a state, a learner that turned into the wrong branch of a junction,
    is labelled with a hard recovery steer under the route's command; a few dozen such labels
    taught the "straight" head to steer left and drove a model off 20 of 20 straight routes
    (docs/model.md, "DAgger's labels").
    """

    def __init__(
        self, learner: ModelPolicy, expert: RoutePolicy, every: int = 1, corrections_only: bool = False
    ) -> None:
        if every < 1:
            raise CrchflError(f"dagger.every must be >= 1, got {every}")
        self.learner, self.expert, self.every = learner, expert, every
        self.corrections_only = corrections_only
        self.horizon = dataclasses.replace(expert.expert, speed_horizon_s=learner.model.config.speed_horizon_s)
        self.steps = 0
        self.expert_driving = False
        self.takeovers = 0
        self.images: list[np.ndarray] = []
        self.actions: list[Action] = []
        self.commands: list[int] = []
        self.speeds: list[float] = []
        self.target_speeds: list[float] = []
        self.signals: list[tuple[str, float]] = []  # (letter, distance) of the next signal, per sample
        self.yield_gaps: list[float] = []  # the nearest junction foe's distance to the conflict point, per sample

    def __call__(self, observation: Observation) -> Action:
        offset = abs(observation.offset_m)
        heading_off = abs(math.degrees(heading_error_rad(observation, self.expert.route)))
        if self.expert_driving and (offset <= TAKEOVER_RETURN_FRACTION * observation.lane_width_m
                                    and heading_off <= TAKEOVER_HEADING_DEG / 2.0):
            self.expert_driving = False
        elif not self.expert_driving and (offset > observation.lane_width_m / 2.0
                                          or heading_off > TAKEOVER_HEADING_DEG):
            self.expert_driving = True
            self.takeovers += 1
        if self.expert_driving:
            self.steps += 1
            return self.expert(observation)
        action = self.learner(observation)
        if self.steps % self.every == 0:
            self._record(observation, action)
        self.steps += 1
        return action

    def _record(self, observation: Observation, action: Action) -> None:
        expert_action, wanted = self.expert.decide(observation)
        length_m = float(observation.frame.length_m[observation.ego_row])
        if self.corrections_only:
            inside = inside_crossing(self.expert.route.crossings, observation.progress_m, length_m)
            if not is_correction(action, expert_action, inside):
                return
        self.images.append(observation.images)
        self.actions.append(expert_action)
        self.commands.append(self.learner.command(observation))
        speed_mps = float(observation.frame.speed_mps[observation.ego_row])
        self.speeds.append(speed_mps)
        # No recorded future here: the speed the expert's wanted acceleration leads to, over the
        # learner's own horizon.
        self.target_speeds.append(target_speed_from_accel(speed_mps, wanted, self.horizon))
        self.signals.append(next_signal(self.expert.route.crossings, observation.progress_m + length_m / 2.0,
                                        observation.frame.tls_states))
        gap = float(observation.frame.foe_gap_m[observation.ego_row])
        self.yield_gaps.append(math.inf if math.isnan(gap) else gap)  # NaN: not looked for; negative: in the conflict

    def arrays(self) -> dict[str, np.ndarray]:
        """The recorded samples as the numpy arrays of Samples.from_numpy (images uint8 [N, 4, H, W, 3])."""
        actions = np.asarray(self.actions, dtype=np.float32).reshape(-1, 3)
        size = self.learner.model.config
        images = (np.asarray(self.images, dtype=np.uint8) if self.images else  # else a drive with nothing kept
                  np.zeros((0, len(CAMERA_NAMES), size.image_height, size.image_width, 3), dtype=np.uint8))
        return {
            "images": images,
            "actions": actions,
            "steer_class": digitize_steer(actions[:, 1]),
            "command": np.asarray(self.commands, dtype=np.int64),
            "speed_mps": np.asarray(self.speeds, dtype=np.float32),
            "target_speed_mps": np.asarray(self.target_speeds, dtype=np.float32),
            "signal_state": signal_codes([letter for letter, _ in self.signals]).astype(np.int64),
            "signal_distance_m": np.asarray([d for _, d in self.signals], dtype=np.float32).reshape(-1),
            "yield_gap_m": np.asarray(self.yield_gaps, dtype=np.float32).reshape(-1),
        }


# What counts as the expert correcting the learner: it brakes this much harder, or steers this far apart.
CORRECTION_BRAKE = 0.1
CORRECTION_STEER = 0.1


def is_correction(learner: Action, expert: Action, inside_junction: bool = False) -> bool:
    """Would the expert step in here: brake harder than the learner, or steer elsewhere?

    Inside a junction also where the learner brakes harder than the expert: the data set's
    left-turners wait inside the junction where SUMO knows they are safe, and a learner that
    copies them stops wherever it happens to be, often in the oncoming lane (drive-bench's
    Town01 traffic failures, docs/model.md). The expert clears the junction once in it (``labeller``).
    """
    braking_apart = expert[2] - learner[2]
    return (braking_apart > CORRECTION_BRAKE or abs(expert[1] - learner[1]) > CORRECTION_STEER
            or (inside_junction and -braking_apart > CORRECTION_BRAKE))


def labeller_config(route_expert: RoutePolicyConfig, data_expert: ExpertConfig) -> RoutePolicyConfig:
    """The route expert as a labeller: it steers by the pure pursuit of the data set's expert (its look-ahead,
    and through ``data_expert`` its steering rack), so a DAgger label asks for the steer the data set's
    labels would. The reference driver's own look-ahead is shorter (4 m and 0.5 s against the data's 5 m
    and 0.8 s): its labels steered about twice as hard back to the line as the data set's recovery
    samples, and fine-tuned on both a model learned to over-steer (docs/model.md, "DAgger's labels")."""
    return dataclasses.replace(
        route_expert, lookahead_min_m=data_expert.lookahead_min_m, lookahead_time_s=data_expert.lookahead_time_s
    )


def labeller(route: RouteGeometry, config: DaggerConfig, data_expert: ExpertConfig) -> RoutePolicy:
    """The route expert that labels a learner's drive of ``route``: labeller_config's, and one that clears a
    junction once in it. Labels that wait at a turn's internal stop, as the reference driver does, drove
    no better: 3 seeds x 3 draws, success -0.8 points [-1.8, +0.1] (less than the -1.4 a fine-tune's batch
    order alone moves it), traffic -3.3 [-6.8, +0.1], not distinguishable (docs/measurements.md,
    2026-12-06, seventh)."""
    settings = labeller_config(config.expert, data_expert)
    return RoutePolicy(route, settings, expert=data_expert, wait_at_internal_stop=False)


def labelled_drives(
    driver: ModelDriver, town: str, episodes: Sequence[Episode], config: DaggerConfig, log_dir: Path | None = None
) -> list[dict]:
    """Drive ``episodes`` with the learner, labelled by the expert; each episode's arrays, in their order.
    SUMO's warnings go to ``log_dir``/TOWN-TASK-INDEX.log when given."""
    scenario = load_scenario(town)
    traffic = {name: task_by_name(name).traffic for name in config.tasks}
    net = read_net(Path(scenario.net_path))
    renderer = driver.renderer(scenario.net_path)
    parts = []
    with single_torch_thread(True):
        for episode in episodes:
            route = route_geometry(net, episode.edges)
            expert = labeller(route, config, driver.expert())
            policy = ExpertLabelled(driver.policy(route, net), expert, config.every, config.corrections_only)
            drive(
                scenario if traffic[episode.task] else without_traffic(scenario), route, policy,
                seed=episode.sumo_seed, max_s=min(config.max_s, episode.time_limit_s),
                config=dataclasses.replace(config.drive, warmup_s=episode.warmup_s), renderer=renderer,
                expert=driver.expert(), keep_frames=False,
                sumo_log=episode_log(log_dir, scenario.name, episode.task, episode.index),
            )
            parts.append(policy.arrays())
            log.info("%s %s %d: %d states labelled, the expert took the wheel %d times",
                     town, episode.task, episode.index, len(parts[-1]["actions"]), policy.takeovers)
    return parts


def collect(
    checkpoint: str | Path, towns: Sequence[str], config: DaggerConfig = DaggerConfig(), jobs: int = 1,
    log_dir: Path | None = None,
) -> Samples:
    """One round: the checkpoint drives routes of ``towns``; every visited state labelled by the expert
    (SUMO's warnings in ``log_dir`` when given)."""
    driver = ModelDriver(str(checkpoint), label=Path(checkpoint).stem)
    driver.model()  # a bad checkpoint fails here, before any drive
    tasks = [task_by_name(name) for name in config.tasks]
    calls, positions = [], []
    for t, town in enumerate(towns):
        episodes = draw_episodes(load_scenario(town), tasks, config.episodes, config.seed)
        groups = max(1, min(jobs, len(episodes)))
        for g in range(groups):
            calls.append((driver, town, episodes[g::groups], config, log_dir))
            positions.append([(t, i) for i in range(g, len(episodes), groups)])
    with Executor(BackendConfig(num_cpus=jobs)) as executor:
        groups_done = executor.map(labelled_drives, calls, isolate=jobs > 1)
    # Back in town and episode order, however they were grouped: the samples, and so the
    # fine-tuning, do not depend on --jobs.
    by_position = {pos: arrays for where, done in zip(positions, groups_done) for pos, arrays in zip(where, done)}
    return Samples.concat([Samples.from_numpy(**by_position[pos]) for pos in sorted(by_position)])


EXPERT_SAMPLES_FILE = "expert_samples.npz"


def collected_samples(
    folder: str | Path, checkpoint: str | Path, towns: Sequence[str], config: DaggerConfig, jobs: int = 1
) -> Samples:
    """One round's samples: read back from ``folder``/expert_samples.npz, else collected and kept there.

    The collection is deterministic (seeded drives, one torch thread), so a kept file is what a
    new collection would give; keeping it lets a stopped run go on without driving again.
    """
    path = Path(folder) / EXPERT_SAMPLES_FILE
    if path.is_file():
        return read_labels(path, "delete the file to collect them again")
    samples = collect(checkpoint, towns, config, jobs=jobs, log_dir=Path(folder) / SUMO_LOG_DIR)
    write_labels(path, samples)
    return samples


def write_labels(path: Path, samples: Samples) -> None:
    """Keep expert-labelled samples in ``path`` (.npz, written atomically)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temp, open(temp, "wb") as out:
        np.savez(out, **{name: getattr(samples, name).numpy() for name in FIELDS})


def read_labels(path: Path, fix: str) -> Samples:
    """The samples ``write_labels`` kept; a CrchflError naming ``path`` and ``fix`` when it cannot be read."""
    try:
        with np.load(path, allow_pickle=False) as stored:
            return Samples.from_numpy(**{name: stored[name] for name in FIELDS if name in stored.files})
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise CrchflError(f"{path}: unreadable expert samples ({exc}); {fix}") from None


def dagger_iterations(
    checkpoint: str | Path,
    train: Samples,
    test: Samples,
    out_dir: str | Path,
    towns: Sequence[str],
    config: DaggerConfig = DaggerConfig(),
    iterations: int = 1,
    epochs: int = 3,
    seed: int = 0,
    jobs: int = 1,
    learning_rate: float = FINE_TUNE_LEARNING_RATE,
    class_weighting: str = FINE_TUNE_CLASS_WEIGHTING,
) -> list[dict]:
    """DAgger from ``checkpoint``: per iteration, the current model drives, the expert labels, the model is fine-tuned.

    Iteration k (1, 2, ...) draws its routes with seed ``config.seed + k``, adds the
    labelled samples to ``train`` and to the earlier iterations' samples, and fine-tunes
    the current model on them all for ``epochs`` with the start checkpoint's training
    settings but ``learning_rate`` and ``class_weighting`` (KEEP_START_WEIGHTING: the start's), training
    seed ``seed + k``. Each iteration's folder ``out_dir``/iteration-k holds expert_samples.npz,
    metrics.jsonl and checkpoint.pt; ``out_dir``/checkpoint.pt is the last iteration's model and
    ``out_dir``/summary.json lists the iterations. A rerun goes on after the last finished epoch. Returns the
    summary's iteration records.
    """
    check_range(iterations, "dagger: iterations", 1, MAX_ITERATIONS, "a number of iterations")
    check_range(epochs, "dagger: epochs", 1, MAX_EPOCHS, "a number of epochs")
    check_seed(seed, "dagger: seed")
    check_range(learning_rate, "dagger: learning_rate", 0, 1, "a learning rate", lo_open=True)
    if class_weighting not in FINE_TUNE_CLASS_WEIGHTINGS:
        raise CrchflError(f"dagger: class_weighting {class_weighting!r} is unknown; use one of "
                          f"{', '.join(map(repr, FINE_TUNE_CLASS_WEIGHTINGS))}")
    out_dir = Path(out_dir)
    start = load_checkpoint(checkpoint)
    train_config = from_mapping(TrainConfig, start.extra.get("train_config", {}), where=f"{checkpoint}: train_config")
    # the fine-tune keeps its last step, as measured (docs/measurements.md, 2026-12-07, third): a start model
    # trained with train.ema_decay does not pass its moving average on to the fine-tune
    train_config = dataclasses.replace(train_config, learning_rate=learning_rate, ema_decay=0.0)
    if class_weighting != KEEP_START_WEIGHTING:
        train_config = dataclasses.replace(train_config, class_weighting=class_weighting)
    drive_settings = {key: start.extra[key] for key in DRIVE_SETTINGS if key in start.extra}
    current, collected, records = Path(checkpoint), [], []
    for iteration in range(1, iterations + 1):
        folder = out_dir / f"iteration-{iteration}"
        round_config = dataclasses.replace(config, seed=config.seed + iteration)
        collected.append(collected_samples(folder, current, towns, round_config, jobs))
        metrics = train_centralized(
            Samples.concat([train, *collected]), test, epochs, folder, start.model_config, train_config,
            seed + iteration, initial_state=start.state_dict if iteration == 1 else load_checkpoint(current).state_dict,
            drive_settings=drive_settings, resume=True,
        )
        current = folder / MODEL_FILE
        last = metrics[-1]
        records.append({
            "iteration": iteration,
            "route_seed": round_config.seed,
            "expert_samples": len(collected[-1]),
            "training_samples": len(train) + sum(len(c) for c in collected),
            "checkpoint": str(current),
            "accuracy": last["accuracy"],
            "balanced_accuracy": last["balanced_accuracy"],
            "always_straight": last["always_straight"],
        })
    with atomic_path(out_dir / MODEL_FILE) as temp:
        temp.write_bytes(current.read_bytes())
    summary = {
        "start_checkpoint": str(checkpoint), "towns": list(towns), "tasks": list(config.tasks),
        "episodes": config.episodes, "every": config.every, "corrections_only": config.corrections_only,
        "hold_short_m": config.expert.hold_short_m, "epochs": epochs, "learning_rate": learning_rate,
        "class_weighting": train_config.class_weighting, "seed": seed, "iterations": records,
    }
    write_json(out_dir / SUMMARY_FILE, summary)
    return records


def dagger_command(
    model: str | Path, dataset: str | Path, out_dir: str | Path, towns: Sequence[str], config: DaggerConfig,
    iterations: int = 1, epochs: int = 3, seed: int = 0, jobs: int = 1,
    learning_rate: float = FINE_TUNE_LEARNING_RATE, overwrite: bool = False,
    train_towns: Sequence[str] | None = None, class_weighting: str = FINE_TUNE_CLASS_WEIGHTING,
) -> list[dict]:
    """What `crchfl-sumo dagger` does: ``dagger_iterations`` from ``model`` on the data set it was trained on
    (checked against it first: the horizon and the camera settings; ``train_towns``: its training shards of
    those towns only, as `train --train-towns` trained it); ``overwrite`` starts afresh, without the earlier
    iterations' samples."""
    start = load_checkpoint(model)
    manifest = read_manifest(dataset)
    manifest.check_model(start.model_config, str(dataset))
    manifest.check_camera(start.extra.get("camera"), str(dataset), str(model))  # e.g. raster.route_signal
    train = load_samples(dataset, "train", manifest.town_vehicles(train_towns, str(dataset)))
    test = load_samples(dataset, "test")
    if overwrite:  # the earlier iterations' samples and models would otherwise be taken up again
        for old in sorted(Path(out_dir).glob("iteration-*")):
            shutil.rmtree(old)
    return dagger_iterations(model, train, test, out_dir, towns, config, iterations, epochs, seed, jobs,
                             learning_rate, class_weighting)
