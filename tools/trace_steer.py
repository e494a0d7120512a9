"""Trace: one drive-bench episode of a model again, logging each step's steer head beside DAgger's labeller.

Why a driver fails where it does (docs/measurements.md, 2026-12-06, seventh: the models turn early and cut
the towns' left turns). The episode is drawn again from a benchmark folder's episodes.json: the same route,
SUMO seed and warm-up, so its metrics match the benchmark's. Per step, the trace holds the simulated
time, the ego's progress and offset from the route's centre line (+ left), its speed and command, the
action the model took, the model's three likeliest steer bins with their probabilities, and the action
DAgger's labeller (crchfl_sumo.driving.dagger.labeller) would take from the same state.

Writes one JSON object a step to --out (JSON lines). Prints the episode's metrics, then the steps where
the model's steer and the labeller's differ by more than --gap (default 0.2).

Usage: python tools/trace_steer.py MODEL.pt BENCH_DIR --town town01 --task navigation_traffic --index 2
       --out trace.jsonl [--steer-decoding auto] [--brake-gain 2] [--gap 0.2]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from crchfl_sumo.core.result_files import EPISODES_FILE
from crchfl_sumo.driving.dagger import labeller
from crchfl_sumo.driving.dagger_settings import DaggerConfig
from crchfl_sumo.driving.drive_bench import BenchConfig, drive_episodes
from crchfl_sumo.driving.drive_bench_tasks import Episode
from crchfl_sumo.driving.drivers import driver_for
from crchfl_sumo.learning.model import steer_values
from crchfl_sumo.learning.settings import DEFAULT_BRAKE_GAIN, DEFAULT_STEER_DECODING


def bench_episode(bench_dir: Path, town: str, task: str, index: int) -> Episode:
    """The episode (town, task, index) as the benchmark in ``bench_dir`` drew it."""
    records = json.loads((bench_dir / EPISODES_FILE).read_text())
    for record in records:
        if (record["town"], record["task"], record["index"]) == (town, task, index):
            fields = {f.name: record[f.name] for f in dataclasses.fields(Episode)}
            return Episode(**{**fields, "edges": tuple(fields["edges"])})
    raise SystemExit(f"{bench_dir / EPISODES_FILE} has no episode {town} {task} {index}")


@dataclasses.dataclass
class TracedDriver:
    """A model driver whose policy also logs, each step, the steer head and the labeller's action."""

    driver: object
    steps: list = dataclasses.field(default_factory=list)
    renders: bool = True

    def renderer(self, net_path):
        return self.driver.renderer(net_path)

    def expert(self):
        return self.driver.expert()

    def policy(self, route, net):
        model_policy = self.driver.policy(route, net)
        expert = labeller(route, DaggerConfig(), self.driver.expert())
        values = steer_values(model_policy.model.config)

        def traced(observation):
            action = model_policy(observation)
            frame, row = observation.frame, observation.ego_row
            command = model_policy.command(observation)
            images = torch.from_numpy(np.ascontiguousarray(observation.images)).unsqueeze(0)
            speed = float(frame.speed_mps[row])
            with torch.no_grad():
                model_policy.model.eval()
                _, logits = model_policy.model(images, torch.tensor([command]), torch.tensor([speed]))
            probabilities = torch.softmax(logits[0].float(), -1).numpy()
            top = np.argsort(-probabilities)[:3]
            self.steps.append({
                "t_s": round(float(frame.t_s), 2), "progress_m": round(observation.progress_m, 2),
                "offset_m": round(observation.offset_m, 3), "speed_mps": round(speed, 2), "command": int(command),
                "action": [round(float(v), 3) for v in action],
                "steer_bins": [[round(float(values[i]), 2), round(float(probabilities[i]), 3)] for i in top],
                "labeller": [round(float(v), 3) for v in expert(observation)],
            })
            return action

        return traced


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("bench_dir", type=Path)
    parser.add_argument("--town", required=True)
    parser.add_argument("--task", required=True)
    parser.add_argument("--index", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--steer-decoding", default=DEFAULT_STEER_DECODING)
    parser.add_argument("--brake-gain", type=float, default=DEFAULT_BRAKE_GAIN)
    parser.add_argument("--gap", type=float, default=0.2)
    args = parser.parse_args()
    episode = bench_episode(args.bench_dir, args.town, args.task, args.index)
    config = BenchConfig(steer_decoding=args.steer_decoding, brake_gain=args.brake_gain)
    traced = TracedDriver(driver_for(args.model, args.steer_decoding, args.brake_gain))
    (record,) = drive_episodes(traced, episode.town, [episode], config)
    args.out.write_text("".join(json.dumps(step) + "\n" for step in traced.steps))
    print(f"{episode.town} {episode.task} {episode.index}: end {record['end_reason']}, success {record['success']}, "
          f"collisions {record['collisions']}, max offset {record['max_abs_offset_m']:.2f} m -> {args.out}")
    for step in traced.steps:
        if abs(step["action"][1] - step["labeller"][1]) > args.gap:
            print(f"t {step['t_s']:7.2f} s  progress {step['progress_m']:7.2f} m  offset {step['offset_m']:+.2f} m  "
                  f"v {step['speed_mps']:.2f}  steer {step['action'][1]:+.2f}  labeller {step['labeller'][1]:+.2f}  "
                  f"bins {step['steer_bins']}")


if __name__ == "__main__":
    main()
