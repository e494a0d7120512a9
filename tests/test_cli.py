"""The command line: every subcommand is listed, user errors exit 2 without a traceback."""

import json
import subprocess
import sys

import pytest

from crchfl_sumo.cli import build_parser, main

from helpers import PAPER_VEHICLES, write_dataset

COMMANDS = ["reproduce", "report", "calibrate", "simulate", "render", "dataset", "dataset-stats", "train", "drive", "drive-compare", "run", "plan", "sweep"]


def test_help_lists_every_subcommand():
    text = build_parser().format_help()
    for name in COMMANDS:
        assert name in text


def test_version_prints_the_package_version():
    from crchfl_sumo import __version__

    done = subprocess.run([sys.executable, "-m", "crchfl_sumo.cli", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == f"crchfl-sumo {__version__}"


def test_train_writes_metrics_and_a_loadable_checkpoint(tmp_path, capsys):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    assert main(["train", str(data), "--out", str(tmp_path / "t"), "--epochs", "2", "--seed", "3"]) == 0
    lines = (tmp_path / "t" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["epoch"] for line in lines] == [1, 2]
    assert "epoch 2" in capsys.readouterr().out
    from crchfl_sumo.learning.checkpoint import load_checkpoint

    config = load_checkpoint(tmp_path / "t" / "checkpoint.pt").model_config
    assert config.image_height == 48
    assert not config.stop_head  # a data set without signal states: no stop head by default


def test_train_stop_head_command_pedals_and_red_hold_reach_the_checkpoint(tmp_path):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5, signals=True)
    assert main(["train", str(data), "--out", str(tmp_path / "t"), "--epochs", "1", "--stop-head",
                 "--command-pedals", "--red-hold"]) == 0
    from crchfl_sumo.learning.checkpoint import load_checkpoint

    config = load_checkpoint(tmp_path / "t" / "checkpoint.pt").model_config
    assert config.stop_head and config.command_pedals and config.red_hold
    assert main(["train", str(data), "--out", str(tmp_path / "u"), "--epochs", "1", "--no-stop-head"]) == 0
    config = load_checkpoint(tmp_path / "u" / "checkpoint.pt").model_config
    assert config.stop_head is False and not config.command_pedals and not config.red_hold
    assert main(["train", str(data), "--out", str(tmp_path / "v"), "--epochs", "1"]) == 0
    assert load_checkpoint(tmp_path / "v" / "checkpoint.pt").model_config.stop_head is True  # signal states: on


def test_train_refuses_signal_labels_from_a_data_set_without_signal_states(tmp_path, capsys):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    for flag in ("--stop-head", "--red-hold"):
        assert main(["train", str(data), "--out", str(tmp_path / "t"), "--epochs", "1", flag]) == 2
        err = capsys.readouterr().err
        assert "no signal states" in err and flag in err and "Traceback" not in err
        assert not (tmp_path / "t" / "checkpoint.pt").exists()


def _town01_copy(data, root):
    """The data set with its training shards of town01 only (files copied, manifest cut): what --train-towns town01
    should train on."""
    import shutil

    root.mkdir()
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["shards"] = [s for s in manifest["shards"] if s["split"] == "test" or s["town"] == "town01"]
    manifest["samples"] = sum(s["samples"] for s in manifest["shards"])
    for shard in manifest["shards"]:
        shutil.copy(data / shard["file"], root / shard["file"])
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root


def test_train_towns_trains_on_those_towns_shards_only(tmp_path, capsys):
    import torch

    from crchfl_sumo.learning.checkpoint import load_checkpoint

    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    common = ["--epochs", "1", "--seed", "1", "--deterministic", "--precision", "fp32"]
    assert main(["train", str(data), "--out", str(tmp_path / "t"), "--train-towns", "town01", *common]) == 0
    assert main(["train", str(_town01_copy(data, tmp_path / "d01")), "--out", str(tmp_path / "c"), *common]) == 0
    assert main(["train", str(data), "--out", str(tmp_path / "all"), *common]) == 0
    weights = {name: load_checkpoint(tmp_path / name / "checkpoint.pt").state_dict for name in ("t", "c", "all")}
    assert all(torch.equal(weights["t"][k], weights["c"][k]) for k in weights["c"])  # the same 12 samples
    assert not all(torch.equal(weights["t"][k], weights["all"][k]) for k in weights["all"])  # not all 30
    capsys.readouterr()
    assert main(["train", str(data), "--out", str(tmp_path / "x"), "--train-towns", "town01,town09"]) == 2
    err = capsys.readouterr().err
    assert "--train-towns town01,town09: no train shard of town09" in err and "town01, town02" in err
    assert "Traceback" not in err and not (tmp_path / "x" / "checkpoint.pt").exists()


def test_dagger_refuses_train_towns_the_data_set_lacks_before_driving(tmp_path, capsys):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    assert main(["train", str(data), "--out", str(tmp_path / "t"), "--epochs", "1"]) == 0
    capsys.readouterr()
    assert main(["dagger", str(tmp_path / "t" / "checkpoint.pt"), str(data), "--out", str(tmp_path / "d"),
                 "--train-towns", "town03"]) == 2
    err = capsys.readouterr().err
    assert "no train shard of town03" in err and "Traceback" not in err
    assert not list((tmp_path / "d").glob("iteration-*"))


def test_train_on_a_missing_data_set_exits_2(tmp_path, capsys):
    assert main(["train", str(tmp_path / "none"), "--out", str(tmp_path / "t")]) == 2
    assert "manifest" in capsys.readouterr().err


def test_train_refuses_a_red_or_yield_weight_out_of_range_before_writing(tmp_path, capsys):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    for flag, value in (("--red-weight", "0.5"), ("--red-weight", "nan"), ("--red-window-m", "0"),
                        ("--yield-weight", "0.5"), ("--yield-weight", "inf"), ("--yield-window-m", "51"),
                        ("--ema-decay", "1"), ("--ema-decay", "-0.1")):
        assert main(["train", str(data), "--out", str(tmp_path / "t"), flag, value]) == 2
        assert flag in capsys.readouterr().err  # named with its range
    assert not (tmp_path / "t").exists()


def test_dataset_stats_writes_beside_its_data_set_and_refuses_another_commands_folder(tmp_path, capsys):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(6, 6, 6, 6, 6), test_samples=5)
    assert main(["dataset-stats", str(data)]) == 0  # the default --out: the data set folder itself
    assert main(["dataset-stats", str(data)]) == 0  # again, the same settings
    capsys.readouterr()
    trained = tmp_path / "t"
    trained.mkdir()
    (trained / ".crchfl-sumo-train.json").write_text('{"command": "train", "fingerprint": ""}')
    assert main(["dataset-stats", str(data), "--out", str(trained)]) == 2
    assert "dataset-stats --out" in capsys.readouterr().err and sorted(p.name for p in trained.iterdir()) == [
        ".crchfl-sumo-train.json"]
    # the scenario whose junctions are counted: an unknown one is refused, naming it, before anything is written
    assert main(["dataset-stats", str(data), "--out", str(tmp_path / "s"), "--scenario", "no_such_town"]) == 2
    assert "no_such_town" in capsys.readouterr().err and not (tmp_path / "s").exists()
    assert main(["dataset-stats", str(data), "--out", str(tmp_path / "s"), "--scenario", "town02"]) == 0
    out = capsys.readouterr().out
    assert "junction turn commands (train):" in out and "of the 24 the junctions offer" in out


def test_run_with_an_unknown_key_exits_2_naming_it(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text('scenario = "paper"\ndataset = "d"\n[federation]\nschem = "hfl"\n')
    assert main(["run", str(config), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "schem" in err and "Traceback" not in err


def test_console_script_exits_2_on_user_error(tmp_path):
    # The installed entry point, as a user runs it: one line on stderr, status 2.
    result = subprocess.run(
        [sys.executable, "-m", "crchfl_sumo.cli", "simulate", "nowhere", "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2
    assert result.stderr.startswith("crchfl-sumo: error: nowhere: not a built-in scenario")
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("argv", [["train", "x", "--out", "y", "--epochs", "0"]])
def test_bad_numbers_exit_2(argv, capsys):
    assert main(argv) == 2
    assert "train --epochs: 0 is out of range; give a number of epochs in 1 .. 100000" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["drive-compare", "{missing}"], ["calibrate", "--dataset", "{missing}"]])
def test_one_file_commands_refuse_an_existing_output_unless_overwrite(tmp_path, capsys, command):
    argv = [a.replace("{missing}", str(tmp_path / "missing")) for a in command]
    out = tmp_path / "result.out"
    out.write_bytes(b"earlier result")
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{command[0]} --out {out}: the file exists" in err and "--overwrite" in err
    # with --overwrite the check passes and the command fails later, on its missing input, before writing
    assert main([*argv, "--out", str(out), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "the file exists" not in err and "missing" in err
    assert out.read_bytes() == b"earlier result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.out"]  # no temporary left beside it


def test_progress_without_a_terminal_prints_plain_lines_now_and_then(monkeypatch):
    import io

    from crchfl_sumo.cli.progress_bars import ProgressBars
    from crchfl_sumo.core.progress import Update

    clock = iter([0.0, 1.0, 2.0, 61.0, 62.0, 63.0, 64.0, 65.0])
    monkeypatch.setattr("crchfl_sumo.cli.progress_bars.time.monotonic", lambda: next(clock))
    stream = io.StringIO()  # not a terminal
    with ProgressBars("episode", stream=stream) as bars:
        for update in (Update("simulate", 1, 10), Update("simulate", 2, 10), Update("simulate", 3, 10),
                       Update("simulate", 4, 10, {"success": "3/4"}), Update("simulate", 10, 10),
                       Update("simulate", 10, 10), Update("render", 0, None), Update("render", 5, None)):
            bars(update)
    # a new stage, a minute later, a stage's end (once), the next stage; nothing else
    assert stream.getvalue().splitlines() == [
        "simulate: 1/10 episode", "simulate: 4/10 episode, success 3/4", "simulate: 10/10 episode", "render: 0 episode",
    ]
