"""Library entry points called directly with bad seeds or sizes: a CrchflError naming the argument, not a
numpy or torch traceback (issue 18). Each case fails on its argument check, before any work."""

from __future__ import annotations

import numpy as np
import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig

BAD_SEEDS = [(2**64, "outside the seed range"), (-1, "outside the seed range"), (2**31, "outside the seed range"),
             (1.5, "is not a seed"), (True, "is not a seed"), ("7", "is not a seed")]


@pytest.mark.parametrize("seed, message", BAD_SEEDS)
def test_build_model_refuses_a_bad_seed(seed, message):
    from crchfl_sumo.learning.model import build_model

    with pytest.raises(CrchflError, match=f"build_model: seed: .*{message}"):
        build_model(ModelConfig(), seed)


def test_build_model_takes_every_seed_of_the_range_and_numpy_integers():
    import torch

    from crchfl_sumo.learning.model import build_model

    small = ModelConfig(image_height=48, image_width=64)
    a, b = build_model(small, 2**31 - 1).state_dict(), build_model(small, np.int64(2**31 - 1)).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)  # the same seed either way: the same weights


def test_training_entry_points_refuse_bad_epochs_and_seeds(tmp_path):
    from crchfl_sumo.learning.centralized import train_centralized
    from crchfl_sumo.learning.training import train_vehicle, train_vehicles

    args = (None, None)  # samples: never reached, the arguments are checked first
    with pytest.raises(CrchflError, match=r"train_centralized: epochs: 100001 is out of range; give a number of"):
        train_centralized(*args, 100_001, tmp_path, ModelConfig(), TrainConfig(), 0)
    with pytest.raises(CrchflError, match="train_centralized: epochs: 0 is out of range"):
        train_centralized(*args, 0, tmp_path, ModelConfig(), TrainConfig(), 0)
    with pytest.raises(CrchflError, match="train_centralized: seed: 18446744073709551616 is outside the seed range"):
        train_centralized(*args, 1, tmp_path, ModelConfig(), TrainConfig(), 2**64)
    with pytest.raises(CrchflError, match="train_vehicle: epochs: -1 is out of range"):
        train_vehicle({}, None, -1, ModelConfig(), TrainConfig(), 0)
    with pytest.raises(CrchflError, match=r"train_vehicles: epochs: 1e\+308 is out of range"):
        train_vehicles([], [], 1e308, ModelConfig(), TrainConfig(), 0)
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_data_and_link_entry_points_refuse_a_bad_seed(tmp_path):
    from crchfl_sumo.data.generation import generate_dataset
    from crchfl_sumo.links.mobility import LinkModel
    from crchfl_sumo.planning.calibration import calibrate_command
    from crchfl_sumo.sumo.sites import EdgeSite

    with pytest.raises(CrchflError, match="generate_dataset: seed: -1 is outside the seed range"):
        generate_dataset(None, tmp_path / "data", seed=-1)
    with pytest.raises(CrchflError, match="calibrate_command: seed: 2147483648 is outside the seed range"):
        calibrate_command(tmp_path / "c.toml", seed=2**31, dataset=tmp_path / "none")
    site = EdgeSite("e", 0.0, 0.0)
    with pytest.raises(CrchflError, match="LinkModel: seed: 18446744073709551616 is outside the seed range"):
        LinkModel([site], seed=2**64)
    LinkModel([site], seed=np.random.default_rng(2**64))  # a generator of the caller's is taken as it is
    assert list(tmp_path.iterdir()) == []


def test_no_code_compares_a_schemes_name_outside_its_shape_table():
    # a scheme's behaviour is read from core.schemes.SHAPES; the studies name the paper's comparisons
    import re
    from pathlib import Path

    package = Path(__file__).resolve().parents[1] / "crchfl_sumo"
    pattern = re.compile(r"""scheme\s*(==|!=)\s*["'](crchfl|hfl|sfl)["']""")
    found = [f"{p.relative_to(package)}:{i}" for p in package.rglob("*.py") if p.parts[-2] != "studies"
             and p.name != "schemes.py" for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert found == []
