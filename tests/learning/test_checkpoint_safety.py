"""What a checkpoint file may hold: weights only (no code runs), a checked payload, weights that fit the config."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch

from crchfl_sumo.core.config import to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.learning.checkpoint import CHECKPOINT_FORMAT, load_checkpoint, load_model, save_checkpoint
from crchfl_sumo.learning.model import build_model
from crchfl_sumo.learning.settings import ModelConfig

CONFIG = ModelConfig(image_height=48, image_width=64, steer_bins=7)  # the hand-made tensors below have 7 values


class RunsCode:
    """Unpickling this runs os.system: what a hostile checkpoint holds."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture(scope="module")
def weights():
    return build_model(CONFIG, seed=0).state_dict()


def payload(weights, **changes):
    data = {"format": CHECKPOINT_FORMAT, "model_config": to_mapping(CONFIG), "state_dict": dict(weights), "extra": {}}
    data.update(changes)
    return {k: v for k, v in data.items() if v is not None}


def test_a_pickle_that_would_run_code_is_refused_in_one_line_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "evil.pt"
    torch.save({"format": CHECKPOINT_FORMAT, "model_config": RunsCode(marker)}, path)
    with pytest.raises(CrchflError) as caught:
        load_checkpoint(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: holds objects other than tensors and plain values")
    assert "\n" not in message and "\x1b" not in message and "weights_only" not in message
    assert not marker.exists()
    # the same file through pickle itself would have run the command: the test's pickle is real
    import pickle
    import zipfile

    with zipfile.ZipFile(path) as archive:
        pickle.loads(archive.read(next(n for n in archive.namelist() if n.endswith("data.pkl"))))
    assert marker.exists()


@pytest.mark.parametrize("cut", [0, 10, 200, -30])
def test_an_empty_or_truncated_checkpoint_is_refused(tmp_path, weights, cut):
    good = tmp_path / "good.pt"
    save_checkpoint(good, CONFIG, weights)
    path = tmp_path / "bad.pt"
    path.write_bytes(good.read_bytes()[:cut])
    with pytest.raises(CrchflError, match=r"bad\.pt: not a readable checkpoint \(empty, truncated or damaged"):
        load_checkpoint(path)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"model_config": None}, "checkpoint's model_config is missing, not a table of settings"),
        ({"state_dict": None}, "checkpoint's state_dict is missing"),
        ({"extra": None}, "checkpoint's extra is missing"),
        ({"extra": [1, 2]}, "checkpoint's extra is list, not a table"),
        ({"state_dict": [1]}, "checkpoint's state_dict is list"),
        ({"state_dict": {"a": 1.0}}, "state_dict holds something other than named tensors"),
        ({"model_config": {"image_height": 4096, "image_width": 8192}}, "4096 x 8192 is too large; use at most 1080 x 1920"),
        ({"model_config": {"size": 3}}, "model_config.size: 3 is not one of 'compact', 'paper'"),
        ({"model_config": {"image_height": "48"}}, "image_height: expected an integer"),
        ({"format": "other"}, "not a crchfl-sumo checkpoint"),
        ({"extra": {"camera": [1]}}, "extra.camera: expected a table of raster and world settings, got list"),
        ({"extra": {"camera": {"raster": {"camera": {"height_px": 4096, "width_px": 8192}}}}}, "4096x8192 is too large"),
        ({"extra": {"expert": {"lookahead_min_m": 1e308}}},
         r"extra\.expert\.lookahead_min_m: 1e\+308 is out of range; give metres in \(0, 100\]"),
        ({"extra": {"expert": {"max_steer_angle_deg": 2**63 - 1}}}, r"extra\.expert\.max_steer_angle_deg: .* out of range"),
    ],
)
def test_a_payload_with_missing_or_wrong_parts_is_refused_naming_the_file(tmp_path, weights, changes, message):
    path = tmp_path / "m.pt"
    torch.save(payload(weights, **changes), path)
    with pytest.raises(CrchflError, match=message) as caught:
        load_model(path)
    assert str(caught.value).startswith(str(path))


def _with(weights, name, value):
    return {**weights, name: value}


NAME = "branch_steer.heads.0.2.bias"  # the last layer of the first steer head: 7 values


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda w: _with(w, NAME, torch.full((7,), float("nan"))), f"weight {NAME} holds NaN or inf"),
        (lambda w: _with(w, NAME, torch.full((7,), float("inf"))), "holds NaN or inf"),
        (lambda w: _with(w, NAME, torch.full((7,), 1e30)), "holds 1e\\+30, beyond the 1e\\+06"),
        (lambda w: _with(w, NAME, torch.zeros(7).to_sparse()), "stored as a torch.sparse_coo tensor, not a dense one"),
        (lambda w: _with(w, NAME, torch.zeros(8)), r"torch.float32 \[8\], the model config needs torch.float32 \[7\]"),
        (lambda w: _with(w, NAME, torch.zeros(7, dtype=torch.float64)), "is torch.float64 \\[7\\]"),
        (lambda w: {k: v for k, v in w.items() if k != NAME}, f"missing {NAME}"),
        (lambda w: _with(w, "extra.weight", torch.zeros(1)), "unexpected extra.weight"),
    ],
)
def test_weights_are_checked_against_a_fresh_model_of_the_config(tmp_path, weights, change, message):
    path = tmp_path / "m.pt"
    torch.save(payload(change(weights)), path)
    with pytest.raises(CrchflError, match=message) as caught:
        load_model(path)
    assert str(caught.value).startswith(f"{path}: ")


def test_a_valid_checkpoint_still_loads(tmp_path, weights):
    path = tmp_path / "m.pt"
    save_checkpoint(path, CONFIG, weights, {"epoch": 1})
    model = load_model(path)
    assert all(torch.equal(model.state_dict()[k], weights[k]) for k in weights)


def test_data_sets_and_model_files_the_package_writes_pass_the_expert_bounds(tmp_path, weights):
    """A manifest's labels.expert as `dataset` records it (today's defaults, a progressive rack, a block from before
    the rack had keys), and the model file a training keeps it in (Manifest.drive_settings), still load."""
    from helpers import PAPER_VEHICLES, write_dataset

    from crchfl_sumo.data.expert import LINEAR_RACK, ExpertConfig
    from crchfl_sumo.data.manifest import MANIFEST_NAME, read_manifest

    data = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    defaults = to_mapping(ExpertConfig())
    before_the_rack = {k: v for k, v in defaults.items() if k not in LINEAR_RACK}
    for i, expert in enumerate([defaults, {**defaults, "steer_knee": 0.275, "sharp_steer_gain": 2.0}, before_the_rack]):
        raw = json.loads((data / MANIFEST_NAME).read_text())
        raw["labels"]["expert"] = expert
        (data / MANIFEST_NAME).write_text(json.dumps(raw))
        manifest = read_manifest(data)
        where = str(data / MANIFEST_NAME)
        assert to_mapping(manifest.expert(where)) == {**defaults, **LINEAR_RACK, **expert}
        path = tmp_path / f"model{i}.pt"
        save_checkpoint(path, CONFIG, weights, manifest.drive_settings(where))
        assert load_checkpoint(path).extra["expert"] == to_mapping(manifest.expert(where))
