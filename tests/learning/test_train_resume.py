"""`train --resume` (learning.centralized.train_centralized, resume=True): stopped after an epoch and resumed, the
training ends with the weights and records of an uninterrupted one; a damaged checkpoint.pt falls back to
checkpoint.prev.pt, the epoch before (core.atomic.read_latest, as a federated run's resume does)."""

from __future__ import annotations

import json
import logging

import pytest
import torch

from crchfl_sumo.cli import main
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.learning.checkpoint import load_checkpoint
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.centralized import train_centralized

from helpers import PAPER_VEHICLES, random_samples as _samples, write_dataset

SMALL = ModelConfig("compact", 48, 64)
CPU = TrainConfig(device="cpu", deterministic=True, sampling="class_balanced")  # balanced: the generator matters




@pytest.fixture(scope="module")
def data():
    return _samples(40, seed=20), _samples(10, seed=21)


@pytest.fixture(scope="module")
def whole(data, tmp_path_factory):
    """Three epochs without a stop: the records and the final weights."""
    out = tmp_path_factory.mktemp("whole")
    records = train_centralized(*data, 3, out, SMALL, CPU, seed=5)
    return records, load_checkpoint(out / "checkpoint.pt").state_dict


def _without_rates(records):
    return [{k: v for k, v in r.items() if k != "samples_per_s"} for r in records]  # wall-clock rates differ


def _assert_same_as_whole(records, out, whole):
    assert _without_rates(records) == _without_rates(whole[0])
    state = load_checkpoint(out / "checkpoint.pt").state_dict
    assert state.keys() == whole[1].keys() and all(torch.equal(state[k], whole[1][k]) for k in state)


def test_stopped_after_an_epoch_and_resumed_it_ends_as_the_uninterrupted_training(data, whole, tmp_path):
    train_centralized(*data, 2, tmp_path, SMALL, CPU, seed=5)  # what a kill after epoch 2's checkpoint leaves
    records = train_centralized(*data, 3, tmp_path, SMALL, CPU, seed=5, resume=True)
    _assert_same_as_whole(records, tmp_path, whole)
    assert load_checkpoint(tmp_path / "checkpoint.prev.pt").extra["epoch"] == 2
    # resumed again with nothing left to do: the same records, no training
    assert train_centralized(*data, 3, tmp_path, SMALL, CPU, seed=5, resume=True) == records


@pytest.mark.parametrize("damage", ["truncated", "empty", "missing"])
def test_a_damaged_checkpoint_resumes_from_the_epoch_before(data, whole, tmp_path, damage, caplog):
    train_centralized(*data, 2, tmp_path, SMALL, CPU, seed=5)
    path = tmp_path / "checkpoint.pt"
    if damage == "missing":  # killed between the two renames of core.atomic.atomic_path_keeping_previous
        path.unlink()
    else:
        path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2] if damage == "truncated" else b"")
    stale = tmp_path / ".checkpoint.pt.partial-abc.pt"  # what a kill inside the atomic write left
    stale.write_bytes(b"half a checkpoint")
    with caplog.at_level(logging.WARNING, logger="crchfl_sumo.core.atomic"):
        records = train_centralized(*data, 3, tmp_path, SMALL, CPU, seed=5, resume=True)
    _assert_same_as_whole(records, tmp_path, whole)  # epochs 2 and 3 trained again from epoch 1's state
    assert not stale.exists()
    if damage != "missing":
        assert any("checkpoint.prev.pt" in r.getMessage() and "resuming from" in r.getMessage() for r in caplog.records)


def test_a_resume_refuses_what_it_cannot_continue(data, tmp_path):
    train_centralized(*data, 2, tmp_path, SMALL, CPU, seed=5)
    with pytest.raises(CrchflError, match="written by a training with other settings or data"):
        train_centralized(*data, 3, tmp_path, SMALL, CPU, seed=6, resume=True)
    with pytest.raises(CrchflError, match="other settings or data"):
        train_centralized(data[0], _samples(9, seed=21), 3, tmp_path, SMALL, CPU, seed=5, resume=True)
    with pytest.raises(CrchflError, match=r"holds 2 epochs already; ask for --epochs 2 or more"):
        train_centralized(*data, 1, tmp_path, SMALL, CPU, seed=5, resume=True)
    for name in ("checkpoint.pt", "checkpoint.prev.pt"):
        (tmp_path / name).write_bytes(b"\0" * 10)
    with pytest.raises(CrchflError, match="the previous checkpoint is no better") as caught:
        train_centralized(*data, 3, tmp_path, SMALL, CPU, seed=5, resume=True)
    assert "\n" not in str(caught.value)


def test_train_resume_on_the_command_line_continues_past_a_truncated_checkpoint(tmp_path, data):
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    argv = ["train", str(dataset), "--epochs", "2", "--seed", "3", "--device", "cpu", "--deterministic"]
    assert main([*argv, "--out", str(tmp_path / "whole")]) == 0
    assert main([*argv, "--out", str(tmp_path / "cut")]) == 0
    path = tmp_path / "cut" / "checkpoint.pt"
    path.write_bytes(path.read_bytes()[:100])  # a kill left it truncated (a disk fault, not an atomic write)
    assert main([*argv, "--out", str(tmp_path / "cut"), "--resume"]) == 0  # epoch 2 again, from checkpoint.prev.pt
    a = load_checkpoint(tmp_path / "whole" / "checkpoint.pt").state_dict
    b = load_checkpoint(path).state_dict
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_train_resume_on_the_command_line_continues_to_more_epochs(tmp_path, capsys):
    """`train --epochs 2`, then `train --resume --epochs 3` into the same folder: the uninterrupted 3-epoch training."""
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    argv = ["train", str(dataset), "--seed", "3", "--device", "cpu", "--deterministic"]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main([*argv, "--epochs", "3", "--out", str(whole)]) == 0
    assert main([*argv, "--epochs", "2", "--out", str(cut)]) == 0
    marker = cut / ".crchfl-sumo-train.json"
    two_epochs = marker.read_bytes()
    capsys.readouterr()
    # without --resume, more epochs are other settings; so is any other changed setting with it
    assert main([*argv, "--epochs", "3", "--out", str(cut)]) == 2
    assert main([*argv, "--epochs", "3", "--out", str(cut), "--resume", "--seed", "4"]) == 2
    assert capsys.readouterr().err.count("holds results of `crchfl-sumo train` with other settings") == 2
    # fewer epochs than the folder holds: refused by the checkpoint, and the marker stays as it was
    assert main([*argv, "--epochs", "1", "--out", str(cut), "--resume"]) == 2
    assert "holds 2 epochs already; ask for --epochs 2 or more" in capsys.readouterr().err
    assert marker.read_bytes() == two_epochs
    # --precision may be named on a resume, but the epochs' own precision is checked: the other is refused
    trained_in = json.loads((cut / "metrics.jsonl").read_text().splitlines()[-1])["precision"]
    other = "fp32" if trained_in == "bf16" else "bf16"
    assert main([*argv, "--epochs", "3", "--out", str(cut), "--resume", "--precision", other]) == 2
    assert f"its epochs trained in {trained_in}; this training would continue in {other}" in capsys.readouterr().err
    assert marker.read_bytes() == two_epochs
    assert main([*argv, "--epochs", "3", "--out", str(cut), "--resume"]) == 0
    a = load_checkpoint(whole / "checkpoint.pt").state_dict
    b = load_checkpoint(cut / "checkpoint.pt").state_dict
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    records = [[json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()] for out in (whole, cut)]
    assert [r["epoch"] for r in records[1]] == [1, 2, 3]
    assert _without_rates(records[1]) == _without_rates(records[0])
    # the folder now holds a 3-epoch training: the same settings as the uninterrupted one's
    assert marker.read_bytes() == (whole / ".crchfl-sumo-train.json").read_bytes()
    # the same command again would start afresh over the finished checkpoint: refused without
    # --resume or --overwrite, the checkpoint untouched; --overwrite trains afresh (the same weights)
    finished = (cut / "checkpoint.pt").read_bytes()
    capsys.readouterr()
    assert main([*argv, "--epochs", "3", "--out", str(cut)]) == 2
    assert "holds a training's checkpoint; pass --resume to continue it, --overwrite" in capsys.readouterr().err
    assert (cut / "checkpoint.pt").read_bytes() == finished
    assert main([*argv, "--epochs", "3", "--out", str(cut), "--overwrite"]) == 0
    c = load_checkpoint(cut / "checkpoint.pt").state_dict
    assert all(torch.equal(a[k], c[k]) for k in a)


def test_train_resume_continues_a_folder_marked_while_precision_had_to_be_kept(tmp_path):
    # Before --precision could be named on a resume, the marker's resume fingerprint held it;
    # such a folder still resumes to more epochs.
    from crchfl_sumo.cli import build_parser
    from crchfl_sumo.cli.arguments import NOT_SETTINGS
    from crchfl_sumo.core.outputs import fingerprint

    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    argv = ["train", str(dataset), "--seed", "3", "--device", "cpu", "--deterministic", "--out", str(tmp_path / "out")]
    assert main([*argv, "--epochs", "1"]) == 0
    marker = tmp_path / "out" / ".crchfl-sumo-train.json"
    args = vars(build_parser().parse_args([*argv, "--epochs", "1"]))
    # (nor did --red-weight / --red-window-m / --class-weighting / --speed-input / --stop-head / --command-pedals /
    # --red-hold / --train-towns / --yield-weight / --yield-window-m / --ema-decay exist then; at their defaults, they are left out
    # of the settings)
    formerly = {k: v for k, v in sorted(args.items()) if k not in NOT_SETTINGS
                and k not in ("epochs", "red_weight", "red_window_m", "class_weighting", "speed_input", "stop_head",
                              "command_pedals", "red_hold", "train_towns", "yield_weight", "yield_window_m",
                              "ema_decay")}
    stored = json.loads(marker.read_text())
    assert stored["resume_fingerprint"] != fingerprint(formerly)  # today's leaves precision out
    marker.write_text(json.dumps({**stored, "resume_fingerprint": fingerprint(formerly)}))
    assert main([*argv, "--epochs", "2", "--resume"]) == 0
    assert [json.loads(line)["epoch"] for line in (tmp_path / "out" / "metrics.jsonl").read_text().splitlines()] == [1, 2]


def test_a_checkpoint_of_the_former_multi_vehicle_default_resumes(data, whole, tmp_path):
    # multi_vehicle only says how a federated run trains its vehicles; its default changed from
    # "sequential" to "auto", and a centralized training's checkpoint written before must still resume.
    import dataclasses

    train_centralized(*data, 2, tmp_path, SMALL, dataclasses.replace(CPU, multi_vehicle="sequential"), seed=5)
    records = train_centralized(*data, 3, tmp_path, SMALL, CPU, seed=5, resume=True)
    _assert_same_as_whole(records, tmp_path, whole)
    with pytest.raises(CrchflError, match="other settings or data"):  # a setting training depends on still counts
        train_centralized(*data, 4, tmp_path, SMALL, dataclasses.replace(CPU, learning_rate=1e-4), seed=5, resume=True)


def test_a_checkpoint_is_not_continued_in_another_precision(data, tmp_path):
    # The precision each epoch trained in is in its record; a resume that would train in the other one
    # ("auto" decided on another machine, or another --precision) is refused and names the fix.
    import dataclasses

    from crchfl_sumo.learning.checkpoint import save_checkpoint

    fp32 = dataclasses.replace(CPU, precision="fp32")
    train_centralized(*data, 2, tmp_path / "a", SMALL, fp32, seed=5)
    with pytest.raises(CrchflError, match=r"its epochs trained in fp32; this training would continue in bf16 .*train --precision fp32"):
        train_centralized(*data, 3, tmp_path / "a", SMALL, dataclasses.replace(CPU, precision="bf16"), seed=5, resume=True)
    whole = train_centralized(*data, 3, tmp_path / "whole", SMALL, fp32, seed=5)
    # A checkpoint written before train.precision existed (float32 then) names it nowhere: it continues in fp32.
    checkpoint = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    extra = checkpoint.extra
    del extra["train_config"]["precision"]
    for record in [extra["metrics"], *extra["resume"]["records"]]:
        record.pop("precision", None)  # the last record is the metrics too
    save_checkpoint(tmp_path / "a" / "checkpoint.pt", checkpoint.model_config, checkpoint.state_dict, extra)
    records = train_centralized(*data, 3, tmp_path / "a", SMALL, fp32, seed=5, resume=True)
    assert _without_rates(records[2:]) == _without_rates(whole[2:])
    # Between the option and "auto" the train config named the precision and the records did not.
    extra["train_config"]["precision"] = "bf16"
    save_checkpoint(tmp_path / "b" / "checkpoint.pt", checkpoint.model_config, checkpoint.state_dict, extra)
    with pytest.raises(CrchflError, match="its epochs trained in bf16; this training would continue in fp32"):
        train_centralized(*data, 3, tmp_path / "b", SMALL, fp32, seed=5, resume=True)
    state = load_checkpoint(tmp_path / "a" / "checkpoint.pt").state_dict
    expected = load_checkpoint(tmp_path / "whole" / "checkpoint.pt").state_dict
    assert all(torch.equal(state[k], expected[k]) for k in state)


def test_train_takes_the_class_weighting_and_a_folder_of_the_default_still_resumes(tmp_path):
    from crchfl_sumo.learning.checkpoint import load_checkpoint

    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    argv = ["train", str(dataset), "--seed", "3", "--device", "cpu", "--precision", "fp32"]
    assert main([*argv, "--out", str(tmp_path / "none"), "--epochs", "1", "--class-weighting", "none"]) == 0
    assert load_checkpoint(tmp_path / "none" / "checkpoint.pt").extra["train_config"]["class_weighting"] == "none"
    assert main([*argv, "--out", str(tmp_path / "none"), "--epochs", "2", "--resume"]) == 2  # another setting
    assert main([*argv, "--out", str(tmp_path / "none"), "--epochs", "2", "--resume", "--class-weighting", "none"]) == 0


def test_train_feeds_the_speed_as_speed_input_says_and_the_default_leaves_the_config_as_before(tmp_path):
    from crchfl_sumo.learning.checkpoint import load_checkpoint
    from crchfl_sumo.learning.settings import ModelConfig

    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    argv = ["train", str(dataset), "--seed", "3", "--device", "cpu", "--precision", "fp32", "--epochs", "1"]
    configs = {}
    for choice in ("none", "longitudinal", "both"):
        assert main([*argv, "--out", str(tmp_path / choice), "--speed-input", choice]) == 0
        configs[choice] = load_checkpoint(tmp_path / choice / "checkpoint.pt").model_config
    assert configs["none"] == ModelConfig("compact", 48, 64, speed_horizon_s=configs["none"].speed_horizon_s)
    assert (configs["longitudinal"].speed_input, configs["longitudinal"].steer_speed_input) == (True, False)
    assert (configs["both"].speed_input, configs["both"].steer_speed_input) == (True, True)
    # the default leaves the folder's marker as a training from before the option existed wrote it
    assert main([*argv, "--out", str(tmp_path / "plain")]) == 0
    assert (tmp_path / "plain" / ".crchfl-sumo-train.json").read_text() == \
        (tmp_path / "none" / ".crchfl-sumo-train.json").read_text()
    assert main([*argv, "--out", str(tmp_path / "longitudinal"), "--epochs", "2", "--resume"]) == 2  # another setting


def test_settings_added_later_stay_out_of_a_checkpoints_train_config_at_their_defaults():
    # a checkpoint written before yield_weight existed stores none of its keys; today's at the defaults must match it
    from crchfl_sumo.core.config import to_mapping

    assert not {"yield_weight", "yield_window_m"} & set(to_mapping(TrainConfig()))
    assert to_mapping(TrainConfig(yield_weight=4.0))["yield_weight"] == 4.0
    assert to_mapping(TrainConfig(yield_window_m=20.0))["yield_window_m"] == 20.0


EMA = TrainConfig(device="cpu", deterministic=True, sampling="class_balanced", ema_decay=0.9)


def test_with_a_moving_average_the_checkpoint_holds_the_average_and_a_resume_ends_as_the_whole(data, tmp_path):
    whole_dir, stopped_dir = tmp_path / "whole", tmp_path / "stopped"
    whole_records = train_centralized(*data, 3, whole_dir, SMALL, EMA, seed=5)
    train_centralized(*data, 2, stopped_dir, SMALL, EMA, seed=5)
    records = train_centralized(*data, 3, stopped_dir, SMALL, EMA, seed=5, resume=True)
    _assert_same_as_whole(records, stopped_dir, (whole_records, load_checkpoint(whole_dir / "checkpoint.pt").state_dict))
    checkpoint = load_checkpoint(whole_dir / "checkpoint.pt")
    resume = checkpoint.extra["resume"]
    # the drivable weights are the average, not the last step's; the last step's travel with the resume state
    assert any(not torch.equal(checkpoint.state_dict[k], resume["trained_weights"][k]) for k in checkpoint.state_dict)
    assert all(torch.equal(checkpoint.state_dict[k], resume["average"]["module." + k]) for k in checkpoint.state_dict)
    assert checkpoint.extra["train_config"]["ema_decay"] == 0.9
    # a training without the average cannot continue it
    with pytest.raises(CrchflError, match="other settings"):
        train_centralized(*data, 4, stopped_dir, SMALL, CPU, seed=5, resume=True)


def test_train_takes_the_moving_average_and_a_folder_without_it_still_resumes(tmp_path):
    import shutil

    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    argv = ["train", str(dataset), "--seed", "3", "--device", "cpu", "--precision", "fp32"]
    assert main([*argv, "--out", str(tmp_path / "ema"), "--epochs", "1", "--ema-decay", "0.99"]) == 0
    assert load_checkpoint(tmp_path / "ema" / "checkpoint.pt").extra["train_config"]["ema_decay"] == 0.99
    assert main([*argv, "--out", str(tmp_path / "ema"), "--epochs", "2", "--resume"]) == 2  # another setting
    assert main([*argv, "--out", str(tmp_path / "ema"), "--epochs", "2", "--resume", "--ema-decay", "0.99"]) == 0
    # the default averages: 30 samples in batches of 32 are one step an epoch, so the last two epochs' steps
    assert main([*argv, "--out", str(tmp_path / "plain"), "--epochs", "1"]) == 0
    assert load_checkpoint(tmp_path / "plain" / "checkpoint.pt").extra["train_config"]["ema_decay"] == 0.5
    # 0 turns it off, and the key stays out of the checkpoint, as before it existed
    assert main([*argv, "--out", str(tmp_path / "off"), "--epochs", "1", "--ema-decay", "0"]) == 0
    assert "ema_decay" not in load_checkpoint(tmp_path / "off" / "checkpoint.pt").extra["train_config"]
    # a folder trained before the default (no average; its marker that of the default's command line) resumes at
    # the default without one; a folder of the default resumes with its own
    marker = ".crchfl-sumo-train.json"
    shutil.copy(tmp_path / "plain" / marker, tmp_path / "off" / marker)
    for folder, decay in (("off", None), ("plain", 0.5)):
        assert main([*argv, "--out", str(tmp_path / folder), "--epochs", "2", "--resume"]) == 0
        checkpoint = load_checkpoint(tmp_path / folder / "checkpoint.pt")
        assert (checkpoint.extra["epoch"], checkpoint.extra["train_config"].get("ema_decay")) == (2, decay)


def test_trains_default_moving_average_spans_at_most_the_last_two_epochs():
    from crchfl_sumo.learning.settings import auto_ema_decay

    assert auto_ema_decay(12_584, 32) == 0.998  # the paper data set: 394 steps an epoch, 1 - 0.5 / 394 > 0.998
    assert auto_ema_decay(5_856, 32) == 1 - 0.5 / 183  # its Town01 shards: 183 steps an epoch
    assert auto_ema_decay(30, 32) == 0.5 and auto_ema_decay(64, 32) == 0.75
