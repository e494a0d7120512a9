"""`run --resume` against damaged files: stale temporaries swept, a bad federation_state.pt falls back to the one before."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import torch

from crchfl_sumo.core.atomic import TMP_MARK
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.federation.run import PREVIOUS_STATE_FILE, STATE_FILE, run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs

from helpers import PAPER_VEHICLES, Killed, SumTrainer, kill_after, result_files, run_config, write_dataset


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    dataset = write_dataset(tmp_path_factory.mktemp("data"), PAPER_VEHICLES)
    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2))
    inputs = read_inputs(config)
    whole = tmp_path_factory.mktemp("whole")
    run_federation_dir(config, inputs, whole, trainer=SumTrainer())
    return config, inputs, whole


def killed_run(setup, out: Path, step: int) -> None:
    config, inputs, _ = setup
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, out, trainer=SumTrainer(), after_checkpoint=kill_after(step))


def resume(setup, out: Path) -> dict:
    config, inputs, _ = setup
    return run_federation_dir(config, inputs, out, trainer=SumTrainer(), resume=True)


def steps_in(path: Path) -> int:
    return torch.load(path, weights_only=True)["state"]["steps"]


def test_the_checkpoint_of_the_step_before_is_kept(setup, tmp_path):
    killed_run(setup, tmp_path / "out", 3)
    assert steps_in(tmp_path / "out" / STATE_FILE) == 3
    assert steps_in(tmp_path / "out" / PREVIOUS_STATE_FILE) == 2


@pytest.mark.parametrize("damage", ["empty", "truncated", "garbage", "other payload", "missing"])
def test_a_damaged_checkpoint_resumes_from_the_previous_one_exactly(setup, tmp_path, damage, caplog):
    out = tmp_path / "out"
    killed_run(setup, out, 3)
    path = out / STATE_FILE
    data = path.read_bytes()
    if damage == "missing":  # killed between the two renames of _save_state
        path.unlink()
    else:
        path.write_bytes({"empty": b"", "truncated": data[: len(data) // 2], "garbage": b"PK\x03\x04" + bytes(100),
                          "other payload": b""}[damage])
        if damage == "other payload":
            torch.save({"format": "crchfl-sumo-federation/2", "resolved": {}, "state": {"steps": 1}, "logs": {}}, path)
    with caplog.at_level(logging.WARNING, logger="crchfl_sumo.federation.run"):
        summary = resume(setup, out)
    assert result_files(out) == result_files(setup[2])  # the same files as the uninterrupted run
    assert summary == json.loads((setup[2] / "summary.json").read_text())
    if damage != "missing":
        assert any("resuming from" in r.getMessage() and PREVIOUS_STATE_FILE in r.getMessage() for r in caplog.records)


def test_with_no_readable_checkpoint_the_resume_stops_with_a_clear_message(setup, tmp_path):
    out = tmp_path / "out"
    killed_run(setup, out, 1)  # the first step: no previous checkpoint yet
    assert not (out / PREVIOUS_STATE_FILE).exists()
    (out / STATE_FILE).write_bytes(b"")
    with pytest.raises(CrchflError, match=r"federation_state\.pt: not a readable federation checkpoint \(empty, truncated"):
        resume(setup, out)
    killed_run(setup, tmp_path / "two", 3)
    for name in (STATE_FILE, PREVIOUS_STATE_FILE):
        (tmp_path / "two" / name).write_bytes(b"\0" * 10)
    with pytest.raises(CrchflError, match="the previous checkpoint is no better") as caught:
        resume(setup, tmp_path / "two")
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda p: p["state"].pop("steps"), r"state lacks steps"),
        (lambda p: p["state"].update(bogus=1), r"state has unknown bogus"),
        (lambda p: p["state"].update(steps="3"), r"state\.steps has the wrong type"),
        (lambda p: p["state"].update(ready_s={"v": "soon"}), r"state\.ready_s has the wrong type"),
        (lambda p: p["state"].update(cloud_model={"w": torch.zeros(3).to_sparse()}), r"state\.cloud_model has the wrong"),
        (lambda p: p["state"].update(vehicle_models=[1]), r"state\.vehicle_models has the wrong"),
        (lambda p: p.update(logs={"ledger.jsonl": {"offset": -1, "lines": 0}}), "log marks"),
        (lambda p: p.update(resolved=[]), "resolved settings"),
    ],
)
def test_a_malformed_checkpoint_payload_is_refused(setup, tmp_path, change, message):
    out = tmp_path / "out"
    killed_run(setup, out, 1)
    path = out / STATE_FILE
    payload = torch.load(path, weights_only=True)
    change(payload)
    torch.save(payload, path)
    with pytest.raises(CrchflError, match=f"{STATE_FILE}: malformed federation checkpoint.*{message}"):
        resume(setup, out)


def test_stale_temporaries_are_swept_at_the_start_of_a_run_and_a_resume(setup, tmp_path):
    config, inputs, _ = setup
    out = tmp_path / "out"
    out.mkdir()
    stale = [out / f".{STATE_FILE}{TMP_MARK}abc.pt", out / f".summary.json{TMP_MARK}x.json"]
    for path in stale:
        path.write_bytes(b"half a file")
    keep = out / "notes.txt"
    keep.write_text("mine")
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, out, trainer=SumTrainer(), after_checkpoint=kill_after(2))
    assert not any(p.exists() for p in stale) and keep.read_text() == "mine"
    stale[0].write_bytes(b"left by the kill")
    resume(setup, out)
    assert not stale[0].exists()
    assert not list(out.glob(f".*{TMP_MARK}*"))


def test_a_folder_with_only_the_previous_checkpoint_still_counts_as_a_run(setup, tmp_path):
    config, inputs, _ = setup
    out = tmp_path / "out"
    killed_run(setup, out, 2)
    (out / STATE_FILE).unlink()
    with pytest.raises(CrchflError, match="already holds a run; pass --resume"):
        run_federation_dir(config, inputs, out, trainer=SumTrainer())
