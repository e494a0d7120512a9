"""Benchmark: `reproduce` with its parts one after the other (--jobs 1) and N at a time, side by side.

    python tools/bench_reproduce.py [--jobs 2] [--config TOML] [--keep DIR]

Runs the quick preset (or ``--config``) twice into fresh folders, each as
its own `crchfl-sumo reproduce` process: first ``--jobs 1``, then
``--jobs N``. Prints both commands' wall time, their ratio, the elapsed and
summed part times from each timings.json, and whether the two reproductions
agree (cloud rounds, bytes and best accuracy of every scheme) and the
largest relative difference of their final losses (the thread counts
differ, so float sums run in another order). The first process keeps
torch's default threads, the jobs of the second get ``cpu_count // N``
each: this compares the two ways of filling the machine's cores.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run(out: Path, jobs: int, config: str | None) -> float:
    command = [sys.executable, "-m", "crchfl_sumo.cli", "reproduce", "--out", str(out), "--jobs", str(jobs)]
    command += ["--config", config] if config else ["--quick"]
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def compare(a: dict, b: dict) -> tuple[bool, float]:
    """Whether cloud rounds, bytes and best accuracies are equal; the largest relative final-loss difference."""
    same, worst = True, 0.0
    for name, one in a["schemes"].items():
        two = b["schemes"][name]
        same &= all(one[key]["values"] == two[key]["values"] for key in ("cloud_rounds", "consumed_bytes", "best_accuracy"))
        for x, y in zip(one["final_loss"]["values"], two["final_loss"]["values"]):
            worst = max(worst, abs(x - y) / abs(x))
    return same, worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--config", default=None, help="a reproduce TOML (default: the quick preset)")
    parser.add_argument("--keep", type=Path, default=None, help="write the two results folders here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        walls, summaries = [], []
        for jobs in (1, args.jobs):
            out = root / f"jobs-{jobs}"
            walls.append(run(out, jobs, args.config))
            summaries.append(json.loads((out / "summary.json").read_text()))
            total = summaries[-1]["running_time_s"]["total"]
            print(f"--jobs {jobs}: {walls[-1]:7.1f} s wall for the command; parts: {total['elapsed_s']:.1f} s elapsed, "
                  f"{total['wall_s']:.1f} s summed wall, {total['cpu_s']:.1f} s summed CPU")
        print(f"ratio jobs 1 / jobs {args.jobs}: {walls[0] / walls[1]:.2f} x")
        same, worst = compare(*summaries)
        print(f"same cloud rounds, bytes and best accuracies: {same}; final losses differ by at most {100 * worst:.2f} %")


if __name__ == "__main__":
    main()
