"""Benchmark: how far a model's steer classes alone limit the drive, with the scripted reference driver.

The reference driver (drive.RoutePolicy) knows the route and the traffic and
scores 100 % on every task. Here its steer goes through a model's quantiser
first: the nearest value of a steer head's classes, as a head's argmax would
give. So the benchmark shows what the classes cost a perfect driver, apart
from anything a network learns. docs/model.md ("The steer classes limit the
turns") records the figures.

Quantisers (names on the command line): analogue (none), paper7 (the paper's 7
classes), rack (the 7 classes through a progressive rack: expert.steer_knee
0.275, sharp_steer_gain 2), bins13 (the paper's 0.15 steps on to +-0.875),
binsN (N classes evenly spaced over [-1, 1], labels.steer_bin_values).

Usage: python tools/bench_steer_classes.py --out DIR [--episodes 6] [--towns town01,town02] QUANTISER...
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.data.labels import STEER_CLASS_VALUES, nearest_bin, steer_bin_values
from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark
from crchfl_sumo.driving.drive_bench_tasks import TASK_NAMES
from crchfl_sumo.driving.policies import RoutePolicy

RACK = {"steer_knee": 0.275, "sharp_steer_gain": 2.0}
EXTENDED_PAPER = np.concatenate([-np.arange(0.875, 0, -0.15), [0.0], np.arange(0.125, 0.9, 0.15)]).astype(np.float32)


class Quantised:
    """A policy whose steer is replaced by the nearest of ``values``."""

    def __init__(self, policy, values: np.ndarray | None) -> None:
        self.policy, self.values = policy, values

    def __call__(self, observation):
        throttle, steer, brake = self.policy(observation)
        if self.values is not None:
            steer = float(self.values[int(nearest_bin(steer, self.values))])
        return throttle, steer, brake


@dataclass
class QuantisedReference:
    """The benchmark's driver protocol (drive_bench.run_benchmark): the reference, steering through ``values``."""

    label: str
    values: np.ndarray | None
    rack: dict = field(default_factory=dict)
    renders: bool = False

    def expert(self) -> ExpertConfig:
        return ExpertConfig(**self.rack)

    def policy(self, route, net):
        return Quantised(RoutePolicy(route, expert=self.expert()), self.values)


def quantiser(name: str) -> QuantisedReference:
    if name == "analogue":
        return QuantisedReference(name, None)
    if name in ("paper7", "rack"):
        return QuantisedReference(name, STEER_CLASS_VALUES, RACK if name == "rack" else {})
    if name == "bins13":
        return QuantisedReference(name, EXTENDED_PAPER)
    if name.startswith("bins") and name[4:].isdigit():
        return QuantisedReference(name, steer_bin_values(int(name[4:])))
    raise SystemExit(f"unknown quantiser {name!r}: analogue, paper7, rack, bins13 or binsN")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("quantisers", nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--towns", default="town01,town02")
    parser.add_argument("--jobs", type=int, default=1)
    args = parser.parse_args()
    towns = tuple(args.towns.split(","))
    for name in args.quantisers:
        driver = quantiser(name)
        run_benchmark(None, args.out / name, episodes=args.episodes, jobs=args.jobs, towns=towns,
                      config=BenchConfig(), driver=driver)
        episodes = json.loads((args.out / name / "episodes.json").read_text())
        cells = []
        for town in towns:
            for task in TASK_NAMES:
                group = [e for e in episodes if e["town"] == town and e["task"] == task]
                cells.append(f"{town} {task} {sum(e['success'] for e in group)}/{len(group)}")
            mine = [e for e in episodes if e["town"] == town]
            cells.append(f"{town} max offset {max(e['max_abs_offset_m'] for e in mine):.2f} m, "
                         f"lane departures {sum(e['lane_departures'] for e in mine)}")
        print(f"{name}: " + " | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
