"""DAgger on the federated vehicles ([dagger], federation.settings.VehicleDaggerConfig).

Each vehicle carries the route expert. After the cloud rounds [dagger] names, every vehicle drives the
model it holds on routes of its own town, and the expert labels the states that model visits, as
`crchfl-sumo dagger` does for one model (driving/dagger.py: ExpertLabelled; by default only the states
where the expert would step in). The labels stay on the vehicle: the loop adds them to its local data
from then on (federation/services.py, ``StepServices.training_data``). Only models cross the links, charged as before.

In the run folder:

  dagger/round-K/VEHICLE.npz   a vehicle's labels of round K (a resumed run reads them back instead of
                               driving again: the drives are seeded, so they would give the same)
  dagger/round-K/sumo-logs/    SUMO's warnings of the drives

Each vehicle's drives run in a process of their own (the run's SUMO clock holds this process's
libsumo), ``jobs`` at a time. A vehicle's routes are drawn like drive-bench's episodes from [dagger]
``tasks`` by a seed of the run's seed, [dagger] ``seed``, the round and the vehicle.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Mapping

import numpy as np

from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.driving.dagger import labelled_drives, read_labels, write_labels
from crchfl_sumo.driving.dagger_settings import DaggerConfig
from crchfl_sumo.driving.drive_bench import SUMO_LOG_DIR
from crchfl_sumo.driving.drive_bench_tasks import draw_episodes, task_by_name
from crchfl_sumo.driving.drivers import ModelDriver
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import RunData
from crchfl_sumo.federation.settings import VehicleDaggerConfig
from crchfl_sumo.learning.checkpoint import save_checkpoint
from crchfl_sumo.learning.model import State
from crchfl_sumo.learning.settings import ModelConfig
from crchfl_sumo.sumo.scenario import load_scenario

log = logging.getLogger(__name__)

DAGGER_DIR = "dagger"  # in a run folder


def round_folder(run_dir: Path, cloud_round: int) -> Path:
    return Path(run_dir) / DAGGER_DIR / f"round-{cloud_round}"


def route_seed(config: VehicleDaggerConfig, run_seed: int, cloud_round: int, vehicle_index: int) -> int:
    """The seed of one vehicle's routes in one round: every vehicle and round drives routes of its own."""
    words = np.random.SeedSequence([config.seed, run_seed, cloud_round, vehicle_index]).generate_state(1)
    return int(words[0]) % 2**31


def drive_config(config: VehicleDaggerConfig) -> DaggerConfig:
    """[dagger] as the drives' settings (the expert and the drive as `crchfl-sumo dagger` has them)."""
    for name in config.tasks:
        try:
            task_by_name(name)
        except CrchflError as exc:
            raise CrchflError(f"dagger.tasks: {exc}") from None
    return DaggerConfig(tasks=tuple(config.tasks), episodes=config.episodes, seed=config.seed, every=config.every,
                        max_s=config.max_s, corrections_only=config.corrections_only)


class VehicleLabeller:
    """The loop's Labeller (federation.state.Labeller): each vehicle's drives, labelled by its route expert.

    towns: vehicle -> the town it drives in (its shard's), in the run's vehicle order;
    model_config, drive_settings: what makes a state dict a drivable checkpoint (the data set's
    camera and expert settings); run_dir: the run folder; jobs: drives in parallel (0: all CPUs).
    """

    def __init__(
        self, config: VehicleDaggerConfig, towns: Mapping[str, str], model_config: ModelConfig,
        drive_settings: Mapping | None, run_dir: Path, run_seed: int, jobs: int = 0,
    ) -> None:
        self.config, self.drives = config, drive_config(config)
        self.towns = dict(towns)
        self._scenarios = {}  # each town read once: every round draws its routes from it
        for town in sorted(set(self.towns.values())):
            try:
                self._scenarios[town] = load_scenario(town)
            except CrchflError as exc:
                raise CrchflError(f"[dagger]: the vehicles of town {town!r} cannot drive there ({exc})") from None
        self._tasks = [task_by_name(name) for name in self.drives.tasks]
        self.model_config, self.drive_settings = model_config, dict(drive_settings or {})
        self.run_dir, self.run_seed, self.jobs = Path(run_dir), run_seed, jobs
        self._rounds: dict[int, dict[str, Samples]] = {}

    def label(self, cloud_round: int, models: Mapping[str, State]) -> dict[str, Samples]:
        folder = round_folder(self.run_dir, cloud_round)
        if cloud_round in self._rounds or all((folder / f"{v}.npz").is_file() for v in self.towns):
            return self.labelled(cloud_round)
        calls, model_files = [], []
        for i, (vehicle, town) in enumerate(self.towns.items()):
            path = folder / f"{vehicle}.model.pt"  # the model the vehicle drives, for the drive's process
            save_checkpoint(path, self.model_config, models[vehicle], {**self.drive_settings, "vehicle": vehicle})
            model_files.append(path)
            episodes = draw_episodes(self._scenarios[town], self._tasks, self.drives.episodes,
                                     route_seed(self.config, self.run_seed, cloud_round, i))
            calls.append((ModelDriver(str(path), label=vehicle), town, episodes, self.drives, folder / SUMO_LOG_DIR))
        with Executor(BackendConfig(num_cpus=self.jobs)) as executor:
            done = executor.map(labelled_drives, calls, isolate=True)  # isolated: this process runs the clock's SUMO
        labels = {}
        for vehicle, parts, path in zip(self.towns, done, model_files, strict=True):
            labels[vehicle] = Samples.concat([Samples.from_numpy(**arrays) for arrays in parts])
            write_labels(folder / f"{vehicle}.npz", labels[vehicle])
            path.unlink()
        log.info("dagger round %d: %s labelled states", cloud_round,
                 ", ".join(f"{v} {len(s)}" for v, s in labels.items()))
        self._rounds[cloud_round] = labels
        return labels

    def labelled(self, cloud_round: int) -> dict[str, Samples]:
        if cloud_round not in self._rounds:
            folder = round_folder(self.run_dir, cloud_round)
            fix = "the run cannot go on without its labels: delete the run folder and start it again"
            missing = [v for v in self.towns if not (folder / f"{v}.npz").is_file()]
            if missing:
                raise CrchflError(f"{folder}: the labels of {', '.join(missing)} are missing; {fix}")
            self._rounds[cloud_round] = {v: read_labels(folder / f"{v}.npz", fix) for v in self.towns}
        return self._rounds[cloud_round]


def labeller_factory(config: RunConfig, inputs: RunData, run_dir: Path) -> VehicleLabeller:
    """The run's labeller (federation.run.LabellerFactory): the vehicles drive in their shards' towns."""
    towns = inputs.towns or {}
    missing = [v for v in inputs.vehicles if v not in towns]
    if missing:
        raise CrchflError(f"[dagger]: the data set does not say where {', '.join(missing)} drove")
    return VehicleLabeller(config.dagger, {v: towns[v] for v in inputs.vehicles}, config.model,
                           inputs.drive_settings, run_dir, config.federation.seed, config.backend.num_cpus)
