"""Benchmark: does DAgger help? Iterations of expert-labelled drives, retraining and drive-bench, side by side.

Starting from a trained checkpoint (crchfl-sumo train), each iteration
  1. lets the current model drive routes drawn with the DAgger seed (not the
     benchmark's), the scripted expert labelling every visited state
     (crchfl_sumo.driving.dagger),
  2. adds those samples to everything collected so far and to the data set's
     training split, and fine-tunes the current model on the aggregate,
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

import numpy as np
from bench_closed_loop import task_columns  # tools/ is on the path when this script runs

from crchfl_sumo.core.atomic import atomic_path
from crchfl_sumo.data.dataset import load_samples
from crchfl_sumo.data.samples import FIELDS, Samples
from crchfl_sumo.data.shards import DRIVE_SETTINGS, read_manifest
from crchfl_sumo.driving.bench import BenchConfig, run_benchmark
from crchfl_sumo.driving.dagger import DaggerConfig, collect
from crchfl_sumo.learning.checkpoint import load_checkpoint, load_model
from crchfl_sumo.learning.settings import TrainConfig
from crchfl_sumo.learning.training import evaluate, train_centralized


def expert_samples(folder: Path, checkpoint: Path, towns: tuple[str, ...], config: DaggerConfig, jobs: int) -> Samples:
    """One iteration's expert-labelled samples: read back from FOLDER/expert_samples.npz, else collected and kept there.

    A rerun with more --iterations and the same --out goes on from the last finished iteration.
    The collection is deterministic (seeded drives, one torch thread), so an earlier run's
    iteration without the file is collected again from its start checkpoint.
    """
    path = folder / "expert_samples.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as stored:
            return Samples.from_numpy(**{name: stored[name] for name in FIELDS})
    samples = collect(checkpoint, towns, config, jobs=jobs)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temp, open(temp, "wb") as out:
        np.savez(out, **{name: getattr(samples, name).numpy() for name in FIELDS})
    return samples


def bench_line(name: str, summary: dict, balanced: float) -> str:
    return f"{name}: balanced {balanced:.3f}" + task_columns(summary["results"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("dataset")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--iterations", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=4, help="DAgger drives per task and town")
    parser.add_argument("--epochs", type=int, default=3, help="fine-tuning epochs per iteration")
    parser.add_argument("--bench-episodes", type=int, default=6)
    parser.add_argument("--dagger-tasks", default=",".join(DaggerConfig().tasks), help="suites the DAgger drives use")
    parser.add_argument("--tasks", default="straight,one_turn", help="suites the benchmark scores")
    parser.add_argument("--towns", default="town01", help="towns the DAgger drives use")
    parser.add_argument("--bench-towns", default=None, help="towns the benchmark scores (default: --towns)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
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
    collected: list[Samples] = []
    for iteration in range(1, args.iterations + 1):
        folder = args.out / f"iteration-{iteration}"
        config = DaggerConfig(tasks=tuple(args.dagger_tasks.split(",")), episodes=args.episodes, seed=1000 + iteration)
        collected.append(expert_samples(folder, checkpoint, towns, config, args.jobs))
        if (folder / "bench" / "summary.json").is_file():  # finished in an earlier run with the same --out
            summary = json.loads((folder / "bench" / "summary.json").read_text())
            records = [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]
        else:
            records = train_centralized(
                Samples.concat([train, *collected]), test, args.epochs, folder, start.model_config, TrainConfig(),
                args.seed + iteration, initial_state=load_checkpoint(checkpoint).state_dict,
                drive_settings={k: start.extra[k] for k in DRIVE_SETTINGS if k in start.extra},
            )
            summary = run_benchmark(folder / "checkpoint.pt", folder / "bench", episodes=args.bench_episodes,
                                    jobs=args.jobs, towns=bench_towns, config=bench)
        checkpoint = folder / "checkpoint.pt"
        lines.append(bench_line(f"iteration {iteration} (+{sum(len(c) for c in collected)} expert-labelled samples)",
                                summary, records[-1]["balanced_accuracy"]))
        print(lines[-1], flush=True)
    (args.out / "dagger.txt").write_text("\n".join(lines) + "\n")
    print(json.dumps({"dagger_samples": [len(c) for c in collected]}))


if __name__ == "__main__":
    main()
