"""A user's own network by import path (`[model] class`, docs/own_model.md): the documented example
trains in a run, checkpoints, loads as itself and drives a benchmark episode; a missing import path is
refused in one line with status 2."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from crchfl_sumo.cli import main
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.driving.drive import DriveConfig
from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark
from crchfl_sumo.federation.run import run_command
from crchfl_sumo.learning.checkpoint import load_checkpoint, load_model
from crchfl_sumo.learning.model import build_model, network_class
from crchfl_sumo.learning.settings import ModelConfig

from helpers import PAPER_VEHICLES, write_dataset

DOC = Path(__file__).resolve().parents[2] / "docs" / "own_model.md"


@pytest.fixture()
def example(tmp_path, monkeypatch) -> str:
    """The documented example module, written as the doc says, importable from a folder on the path."""
    code = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)[0]
    folder = tmp_path / "user_code"
    folder.mkdir()
    (folder / "tiny_driver.py").write_text(code)
    monkeypatch.syspath_prepend(str(folder))
    return "tiny_driver:TinyDriver"


def test_the_documented_example_trains_in_a_run_and_drives_the_benchmark(example, tmp_path, ladder):
    assert len(re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)[0].splitlines()) <= 30
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    config = tmp_path / "run.toml"
    config.write_text(
        f'dataset = "{dataset}"\n[federation]\nscheme = "hfl"\nedge_interval = 1\ncloud_rounds = 2\n'
        f'[ledger]\nnominal_model_mb = 10.0\n[model]\nimage_height = 48\nimage_width = 64\nclass = "{example}"\n'
        '[train]\ndevice = "cpu"\nprecision = "fp32"\n[clock]\nkind = "constant"\n'
    )
    summary = run_command(config, tmp_path / "run")
    assert summary["cloud_rounds"] == 2 and summary["model"]["class"] == example
    checkpoint = load_checkpoint(tmp_path / "run" / "best_model.pt")
    assert checkpoint.model_config.class_path == example
    model = load_model(tmp_path / "run" / "best_model.pt")
    assert type(model).__name__ == "TinyDriver" and model.config == checkpoint.model_config
    # it learned: the run's weights are not the seeded initial ones
    initial = build_model(checkpoint.model_config, seed=0).state_dict()
    assert any(not (initial[k] == v).all() for k, v in checkpoint.state_dict.items())
    bench = run_benchmark(tmp_path / "run" / "best_model.pt", tmp_path / "bench", episodes=1,
                          towns=(str(ladder / "ladder.sumocfg"),),
                          config=BenchConfig(tasks=("straight",), drive=DriveConfig(stuck_s=3.0)))
    (episode,) = json.loads((tmp_path / "bench" / "episodes.json").read_text())
    assert episode["end_reason"] in ("stuck", "left the route", "completed", "time limit")
    assert bench["results"]["ladder"]["straight"]["episodes"] == 1


def test_a_missing_or_wrong_import_path_is_refused_naming_model_class(example, tmp_path, capsys):
    with pytest.raises(CrchflError, match="model.class: 'tiny driver' is no import path"):
        from_mapping(ModelConfig, {"class": "tiny driver"}, "run.toml.model")
    with pytest.raises(CrchflError, match="module 'no_such_package' of 'no_such_package:Net' is not importable"):
        network_class("no_such_package:Net")
    with pytest.raises(CrchflError, match="'tiny_driver:COMMANDS' names no class"):
        network_class("tiny_driver:COMMANDS")
    with pytest.raises(CrchflError, match="'torch:Tensor' is not a torch.nn.Module class"):
        network_class("torch:Tensor")
    # on the command line: one line, status 2, for a run and for a checkpoint that names a lost class
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    config = tmp_path / "run.toml"
    config.write_text(f'dataset = "{dataset}"\n[model]\nimage_height = 48\nimage_width = 64\n'
                      'class = "no_such_package:Net"\n[clock]\nkind = "constant"\n')
    assert main(["run", str(config), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "model.class" in err and "PYTHONPATH" in err and "Traceback" not in err
    from crchfl_sumo.learning.checkpoint import save_checkpoint

    model = build_model(ModelConfig(image_height=48, image_width=64, class_path=example), seed=0)
    save_checkpoint(tmp_path / "m.pt", ModelConfig(image_height=48, image_width=64, class_path="gone_now:Net"),
                    model.state_dict())
    assert main(["drive-bench", str(tmp_path / "m.pt"), "--out", str(tmp_path / "b"), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert "gone_now" in err and "Traceback" not in err
