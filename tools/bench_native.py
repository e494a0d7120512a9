"""Benchmark: the product's native-library settings against the libraries' own defaults, whole commands.

Every command turns off OpenCV's worker threads and numpy's MADV_HUGEPAGE on
large arrays (crchfl_sumo.core.cpus.settle_native_libraries). This runs whole
commands in fresh processes, in turn (settled, library, settled, ...), and
compares:
  settled  the product as it is (neither variable set by the caller),
  library  OPENCV_FOR_THREADS_NUM=0 and NUMPY_MADVISE_HUGEPAGE=1, which the
           product keeps as the user's own: OpenCV's and numpy's defaults.
Commands: `crchfl-sumo dataset paper` (the paper split, 14,665 samples) and
`crchfl-sumo train` for one epoch on that data set (loading it, then torch).
Prints each run's wall and CPU seconds, the medians, and per command
`settled/library wall = X.XX` and `settled/library cpu = X.XX` (medians of
the ratios of the pairs; below 1 the settled product is faster).

    python tools/bench_native.py [--rounds 3] [--commands dataset,train]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from crchfl_sumo.core.cpus import NATIVE_SETTINGS

LIBRARY_DEFAULTS = {"OPENCV_FOR_THREADS_NUM": "0", "NUMPY_MADVISE_HUGEPAGE": "1"}


def timed_run(argv: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s of the child and its children) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3, help="pairs of runs per command")
    parser.add_argument("--commands", default="dataset,train", help="comma list of: dataset, train")
    args = parser.parse_args()
    cli = [sys.executable, "-m", "crchfl_sumo.cli"]
    plain = {k: v for k, v in os.environ.items() if k not in NATIVE_SETTINGS}
    envs = {"settled": plain, "library": {**plain, **LIBRARY_DEFAULTS}}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        commands = {
            "dataset": lambda out: cli + ["dataset", "paper", "--out", str(out), "--seed", "1"],
            "train": lambda out: cli + ["train", str(data), "--out", str(out), "--epochs", "1"],
        }
        wanted = args.commands.split(",")
        if "train" in wanted:
            subprocess.run(commands["dataset"](data), check=True, stdout=subprocess.DEVNULL)
        for name in wanted:
            runs: dict[str, list[tuple[float, float]]] = {mode: [] for mode in envs}
            for r in range(args.rounds):
                for mode, env in envs.items():
                    out = Path(tmp) / f"{name}-{mode}-{r}"
                    runs[mode].append(timed_run(commands[name](out), env))
                    shutil.rmtree(out, ignore_errors=True)
                    wall, cpu = runs[mode][-1]
                    print(f"{name:8s} {mode:8s} round {r}: wall {wall:6.1f} s, cpu {cpu:6.1f} s", flush=True)
            for k, figure in enumerate(("wall", "cpu")):
                medians = {mode: statistics.median(run[k] for run in runs[mode]) for mode in envs}
                ratio = statistics.median(s[k] / b[k] for s, b in zip(runs["settled"], runs["library"]))
                print(f"{name}: median {figure} settled {medians['settled']:.1f} s, library {medians['library']:.1f} s")
                print(f"{name}: settled/library {figure} = {ratio:.2f}")


if __name__ == "__main__":
    main()
