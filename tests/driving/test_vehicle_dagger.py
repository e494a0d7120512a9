"""DAgger on the federated vehicles ([dagger]): the labeller's drives and files, and a run that uses them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import FIELDS
from crchfl_sumo.driving.vehicle_dagger import VehicleLabeller, labeller_factory, round_folder, route_seed
from crchfl_sumo.federation.run import run_command, run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.federation.settings import VehicleDaggerConfig
from crchfl_sumo.learning.checkpoint import load_checkpoint

from helpers import PAPER_VEHICLES, result_files, run_config, write_dataset

DRIVER = Path(__file__).parents[1] / "fixtures" / "guard_driver.pt"
# One short straight drive a vehicle, every 5th step labelled whatever the learner did.
SHORT = VehicleDaggerConfig(every_cloud_rounds=1, episodes=1, tasks=("straight",), max_s=12.0, every=5,
                            corrections_only=False)


def test_each_vehicle_drives_its_own_model_in_its_town_and_keeps_the_labels(tmp_path):
    driver = load_checkpoint(DRIVER)
    towns = {"v1": "town01", "v2": "town02"}
    labeller = VehicleLabeller(SHORT, towns, driver.model_config, driver.extra, tmp_path, run_seed=0, jobs=2)
    labels = labeller.label(1, {v: driver.state_dict for v in towns})
    folder = round_folder(tmp_path, 1)
    assert sorted(p.name for p in folder.glob("*.npz")) == ["v1.npz", "v2.npz"]
    assert not list(folder.glob("*.pt"))  # the models the drives read are gone once they are done
    size = driver.model_config
    for vehicle in towns:
        samples = labels[vehicle]
        # 12 s of 0.1 s steps, every 5th labelled: about 24 a drive (fewer if it ended early)
        assert 5 <= len(samples) <= 25, (vehicle, len(samples))
        assert tuple(samples.images.shape[1:]) == (4, size.image_height, size.image_width, 3)
        assert set(samples.command.tolist()) <= {0, 3}  # straight routes: follow, or straight at a junction
    # A later labeller over the folder (a resumed run) reads the labels back and drives nothing: it has no models.
    again = VehicleLabeller(SHORT, towns, driver.model_config, driver.extra, tmp_path, run_seed=0)
    read = again.label(1, {})
    for vehicle in towns:
        for name in FIELDS:
            assert torch.equal(getattr(read[vehicle], name), getattr(labels[vehicle], name)), (vehicle, name)
    # A damaged or missing label file is refused, naming it.
    (folder / "v2.npz").write_bytes(b"not a zip")
    with pytest.raises(CrchflError, match="v2.npz"):
        VehicleLabeller(SHORT, towns, driver.model_config, driver.extra, tmp_path, run_seed=0).labelled(1)
    (folder / "v2.npz").unlink()
    with pytest.raises(CrchflError, match="labels of v2 are missing"):
        VehicleLabeller(SHORT, towns, driver.model_config, driver.extra, tmp_path, run_seed=0).labelled(1)


def test_every_vehicle_and_round_draws_routes_of_its_own():
    seeds = {route_seed(SHORT, run, k, i) for run in (0, 1) for k in (1, 2) for i in range(5)}
    assert len(seeds) == 20
    assert route_seed(SHORT, 0, 1, 0) == route_seed(SHORT, 0, 1, 0)


def test_unknown_tasks_and_towns_are_refused_naming_dagger(tmp_path):
    driver = load_checkpoint(DRIVER)
    with pytest.raises(CrchflError, match="dagger.tasks"):
        VehicleLabeller(VehicleDaggerConfig(tasks=("flying",)), {"v": "town01"}, driver.model_config, {}, tmp_path, 0)
    with pytest.raises(CrchflError, match=r"\[dagger\].*atlantis"):
        VehicleLabeller(SHORT, {"v": "atlantis"}, driver.model_config, {}, tmp_path, 0)


def test_a_run_with_dagger_trains_on_the_labels_and_its_resume_changes_nothing(tmp_path):
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    mapping = {**run_config(dataset, cloud_rounds=2), "dagger": {
        "every_cloud_rounds": 1, "episodes": 1, "tasks": ["straight"], "max_s": 6.0, "every": 5,
        "corrections_only": False}}
    config = from_mapping(RunConfig, mapping)
    with pytest.raises(CrchflError, match=r"\[dagger\]"):
        run_federation_dir(config, read_inputs(config), tmp_path / "refused")
    path = tmp_path / "run.toml"
    path.write_text(
        f'dataset = "{dataset}"\n[federation]\nscheme = "hfl"\nedge_interval = 1\ncloud_rounds = 2\n'
        '[ledger]\nnominal_model_mb = 10.0\n[model]\nimage_height = 48\nimage_width = 64\n'
        '[train]\ndevice = "cpu"\ndeterministic = true\n[clock]\nkind = "constant"\n'
        '[dagger]\nevery_cloud_rounds = 1\nepisodes = 1\ntasks = ["straight"]\nmax_s = 6.0\nevery = 5\n'
        'corrections_only = false\n'
    )
    out = tmp_path / "out"
    summary = run_command(path, out, labeller_factory=labeller_factory)
    # Labelled after round 1 only: round 2 ended the run.
    assert summary["dagger_rounds"] == [1]
    vehicles = [v for v, _, _ in PAPER_VEHICLES]
    assert sorted(p.stem for p in round_folder(out, 1).glob("*.npz")) == sorted(vehicles)
    assert not round_folder(out, 2).exists()
    assert json.loads((out / "config.json").read_text())["config"]["dagger"]["every_cloud_rounds"] == 1
    before = result_files(out)
    run_command(path, out, resume=True, labeller_factory=labeller_factory)
    assert result_files(out) == before
