"""Benchmark: does DAgger help? Iterations of expert-labelled drives, retraining and drive-bench, side by side.

Starting from a trained checkpoint (crchfl-sumo train), each iteration
  1. lets the current model drive routes drawn with the DAgger seed (not the
     benchmark's), the scripted expert labelling every visited state
     (crchfl_sumo.driving.dagger),
  2. adds those samples to everything collected so far and to the data set's
     training split, and fine-tunes the current model on the aggregate
     (driving.dagger.dagger_iterations, as `crchfl-sumo dagger` does),
  3. scores the new model on the same drive-bench episodes as the start model.
Prints one line per model: balanced accuracy on the data set's test split and
the closed-loop success, completion and driving score per task.

Usage: python tools/dagger.py CHECKPOINT DATASET --out DIR [--iterations 1] [--episodes 4]
       [--epochs 3] [--dagger-tasks straight,one_turn,navigation] [--towns town01]
       [--bench-episodes 6] [--tasks straight,one_turn] [--bench-towns TOWNS] [--jobs 2]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench_closed_loop import task_columns  # tools/ is on the path when this script runs

from crchfl_sumo.data.dataset import load_samples
from crchfl_sumo.data.manifest import read_manifest
from crchfl_sumo.driving.dagger import dagger_iterations
from crchfl_sumo.driving.dagger_settings import FINE_TUNE_LEARNING_RATE, DaggerConfig
from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark
from crchfl_sumo.learning.checkpoint import load_checkpoint, load_model
from crchfl_sumo.learning.training import evaluate


def bench_line(name: str, summary: dict, balanced: float) -> str:
    return f"{name}: balanced {balanced:.3f}" + task_columns(summary["results"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("dataset")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--iterations", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=DaggerConfig().episodes, help="DAgger drives per task and town")
    parser.add_argument("--epochs", type=int, default=3, help="fine-tuning epochs per iteration")
    parser.add_argument("--bench-episodes", type=int, default=6)
    parser.add_argument("--dagger-tasks", default=",".join(DaggerConfig().tasks), help="suites the DAgger drives use")
    parser.add_argument("--tasks", default="straight,one_turn", help="suites the benchmark scores")
    parser.add_argument("--towns", default="town01", help="towns the DAgger drives use")
    parser.add_argument("--bench-towns", default=None, help="towns the benchmark scores (default: --towns)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--learning-rate", type=float, default=FINE_TUNE_LEARNING_RATE,
                        help=f"fine-tuning learning rate (default {FINE_TUNE_LEARNING_RATE:g})")
    parser.add_argument("--all-states", action="store_true",
                        help="label every visited state (default: only where the expert brakes harder or "
                        "steers elsewhere)")
    parser.add_argument("--no-start-bench", action="store_true", help="skip scoring the start model")
    args = parser.parse_args()
    towns = tuple(args.towns.split(","))
    bench_towns = towns if args.bench_towns is None else tuple(args.bench_towns.split(","))
    bench = BenchConfig(tasks=tuple(args.tasks.split(",")))
    train, test = load_samples(args.dataset, "train"), load_samples(args.dataset, "test")
    checkpoint = args.checkpoint
    start = load_checkpoint(checkpoint)
    read_manifest(Path(args.dataset)).check_model(start.model_config, args.dataset)
    lines = []
    if not args.no_start_bench:
        lines.append(bench_line("start", run_benchmark(checkpoint, args.out / "bench-0", episodes=args.bench_episodes,
                                                       jobs=args.jobs, towns=bench_towns, config=bench),
                                evaluate(load_model(checkpoint), test).balanced_accuracy))
        print(lines[-1], flush=True)
    config = DaggerConfig(tasks=tuple(args.dagger_tasks.split(",")), episodes=args.episodes,
                          corrections_only=not args.all_states)
    records = dagger_iterations(checkpoint, train, test, args.out, towns, config, args.iterations, args.epochs,
                                args.seed, args.jobs, args.learning_rate)
    for record in records:
        folder = Path(record["checkpoint"]).parent
        if (folder / "bench" / "summary.json").is_file():  # scored in an earlier run with the same --out
            summary = json.loads((folder / "bench" / "summary.json").read_text())
        else:
            summary = run_benchmark(record["checkpoint"], folder / "bench", episodes=args.bench_episodes,
                                    jobs=args.jobs, towns=bench_towns, config=bench)
        lines.append(bench_line(f"iteration {record['iteration']} (+{record['training_samples'] - len(train)} "
                                "expert-labelled samples)", summary, record["balanced_accuracy"]))
        print(lines[-1], flush=True)
    (args.out / "dagger.txt").write_text("\n".join(lines) + "\n")
    print(json.dumps({"dagger_samples": [record["expert_samples"] for record in records]}))


if __name__ == "__main__":
    main()
