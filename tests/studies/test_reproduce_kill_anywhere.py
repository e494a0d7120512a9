"""kill -9 a reproduction (a subprocess) at seeded random moments, `--resume` until it finishes: the summary and
files of an uninterrupted reproduction (issue 18; tests/federation/test_kill_anywhere.py does this for `run`).

A tiny config: the data set (10 training samples of 48 x 64), the centralized part (one epoch) and one HFL
run on the constant clock, then the report. Kills land anywhere: in data set generation, between a shard
and the manifest, in training, between a part's files and timings.json, in the report's figures.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import crchfl_sumo
from crchfl_sumo.core.atomic import TMP_MARK

from helpers import result_files

TINY = """
name = "tiny"
scenario = "paper"
seeds = 1
schemes = ["hfl"]
ablation_seeds = 0
ablation_edge_intervals = []
centralized_epochs = 1
drive_routes = []
bench_episodes = 0

[generate.dataset]
[[generate.dataset.towns]]
town = "town01"
train_samples = [2, 2]
test_samples = [2]
[[generate.dataset.towns]]
town = "town02"
train_samples = [2, 2, 2]
test_samples = [2]

[generate.raster.camera]
height_px = 48
width_px = 64

[run.model]
image_height = 48
image_width = 64
[run.train]
device = "cpu"
[run.federation]
cloud_rounds = 2
[run.clock]
kind = "constant"
"""

RUNNER = """
import sys

import crchfl_sumo.data.generation, crchfl_sumo.federation.run, crchfl_sumo.studies.report  # the imports first:
from crchfl_sumo.cli import main  # kills should land in the work, not in the 3 s of imports

print("started", flush=True)
sys.exit(main(["reproduce", "--config", sys.argv[1], "--out", sys.argv[2], "--resume"]))
"""

# One kill series in the suite; CRCHFL_REPRODUCE_KILL_SERIES=20 runs twenty, each with its own kill moments.
SERIES = range(18, 18 + int(os.environ.get("CRCHFL_REPRODUCE_KILL_SERIES", "1")))
KILLS = 2  # per series: each costs a restart (about 3 s of imports on 2 busy cores) and the work since the last save


def _outcome(out: Path) -> dict:
    """What a reproduction must end with whatever it went through: its summary (less the running times),
    the data set's manifest (shard checksums) and every part's result files."""
    summary = json.loads((out / "summary.json").read_text())
    summary.pop("running_time_s")
    manifest = json.loads((out / "data" / "manifest.json").read_text())
    return {
        "summary": summary,
        "shards": [(s["file"], s["samples"], s["sha256"]) for s in manifest["shards"]],
        "run": result_files(out / "runs" / "hfl" / "seed-0"),
        "centralized": json.loads((out / "centralized" / "seed-0" / "summary.json").read_text()),
        "parts": sorted(json.loads((out / "timings.json").read_text())),
    }


@pytest.mark.parametrize("series", SERIES)
def test_a_reproduction_killed_anywhere_and_resumed_ends_with_the_uninterrupted_summary(tmp_path, series):
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    (tmp_path / "runner.py").write_text(RUNNER)
    repo = Path(crchfl_sumo.__file__).parent.parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(repo), str(repo / "tests")]), "OMP_NUM_THREADS": "1"}

    def start(out: Path) -> subprocess.Popen:
        process = subprocess.Popen(
            [sys.executable, str(tmp_path / "runner.py"), str(config), str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True,
        )
        assert process.stdout.readline().strip() == "started", process.stderr.read()
        return process

    process = start(tmp_path / "whole")  # uninterrupted, and as the killed ones run: the kill window
    began = time.perf_counter()
    _, stderr = process.communicate(timeout=300)  # communicate: a full pipe never stalls the child
    window_s = time.perf_counter() - began
    assert process.returncode == 0, stderr
    whole = _outcome(tmp_path / "whole")

    rng = np.random.default_rng(series)
    out = tmp_path / "killed"
    kills, finished = 0, False
    for _ in range(3 * KILLS + 2):
        process = start(out)
        if kills < KILLS:
            time.sleep(rng.uniform(0.0, window_s))
            process.send_signal(signal.SIGKILL)
        _, stderr = process.communicate(timeout=300)  # a hang fails the test instead of stalling it
        code = process.returncode
        if code == -signal.SIGKILL:
            kills += 1
        elif code == 0 and kills == 0:  # it finished before the first kill: start again from nothing
            shutil.rmtree(out)
        else:
            assert code == 0, stderr
            finished = True
            break
    assert finished and kills >= 1
    assert _outcome(out) == whole
    assert not list(out.rglob(f".*{TMP_MARK}*"))  # what the kills left was swept or replaced
