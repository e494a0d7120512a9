"""kill -9 a run (a subprocess) at seeded random moments, resume until it finishes: the files of an uninterrupted run.

The chosen-step resume tests (test_run.py) raise inside the process after a
checkpoint; this one kills the process wherever it is: inside an atomic write,
between a log append and its checkpoint, between the two renames that keep
federation_state.prev.pt. The trainer is the cheap SumTrainer (the files do not
depend on what learning does; test_run.py pins the torch trainer's resume).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import crchfl_sumo
from crchfl_sumo.core.atomic import TMP_MARK
from crchfl_sumo.core.config import from_mapping, toml_text
from crchfl_sumo.federation.run import run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs

from helpers import PAPER_VEHICLES, SumTrainer, result_files, run_config, write_dataset

RUNNER = """
import sys
from pathlib import Path

from crchfl_sumo.federation.run import run_federation_dir
from crchfl_sumo.federation.run_config import load_run_config
from crchfl_sumo.federation.run_data import read_inputs
from helpers import SumTrainer

config = load_run_config(Path(sys.argv[1]))
inputs = read_inputs(config)
print("started", flush=True)
run_federation_dir(config, inputs, Path(sys.argv[2]), trainer=SumTrainer(), resume=True)
"""


# One kill series in the suite; CRCHFL_KILL_SERIES=20 runs twenty, each with its own kill moments (#18's 20/20).
SERIES = range(18, 18 + int(os.environ.get("CRCHFL_KILL_SERIES", "1")))


@pytest.mark.parametrize("series", SERIES)
def test_a_run_killed_anywhere_and_resumed_ends_with_the_uninterrupted_files(tmp_path, series):
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    mapping = run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=6)  # 13 steps
    (tmp_path / "run.toml").write_text(toml_text(mapping))
    (tmp_path / "runner.py").write_text(RUNNER)
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)
    start = time.perf_counter()
    run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    window_s = time.perf_counter() - start  # kill moments spread over about the whole run

    repo = Path(crchfl_sumo.__file__).parent.parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(repo), str(repo / "tests")]), "OMP_NUM_THREADS": "1"}
    rng = np.random.default_rng(series)
    out = tmp_path / "killed"
    kills, finished = 0, False
    for _ in range(12):
        process = subprocess.Popen(
            [sys.executable, str(tmp_path / "runner.py"), str(tmp_path / "run.toml"), str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True,
        )
        assert process.stdout.readline().strip() == "started", process.stderr.read()
        if kills < 4:
            time.sleep(rng.uniform(0.0, window_s))
            process.send_signal(signal.SIGKILL)
        code = process.wait(timeout=300)  # a hang fails the test instead of stalling it
        stderr = process.stderr.read()
        process.stdout.close()
        process.stderr.close()
        if code == -signal.SIGKILL:
            kills += 1
        elif code == 0 and kills == 0:  # it finished before the first kill: start again from nothing
            shutil.rmtree(out)
        else:
            assert code == 0, stderr
            finished = True
            break
    assert finished and kills >= 1
    assert result_files(out) == result_files(tmp_path / "whole")
    a = torch.load(tmp_path / "whole" / "final_model.pt", weights_only=True)["state_dict"]
    b = torch.load(out / "final_model.pt", weights_only=True)["state_dict"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert not list(out.glob(f".*{TMP_MARK}*"))  # what the kills left was swept
