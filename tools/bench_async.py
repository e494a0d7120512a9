"""Synchronous against asynchronous edges on one scenario, seed by seed, under one budget.

    python tools/bench_async.py --out DIR [--scenario scale200] [--data DIR] [--samples 32] [--seeds 3]
                                [--budget-gb 6] [--buffer 5] [--staleness-exponent 0.5] [--jobs 2]
                                [--bench-episodes 5]

1. Data: unless --data names one, a data set of the scenario: --samples training samples for every
   data vehicle (the clients), 50 per test vehicle, 64 x 128 (scale200: 200 clients, 8 edges).
2. Runs: HFL on SUMO's clock, compact model charged at its real size (physical rule), one local
   epoch per edge aggregation, cloud_interval 1, --budget-gb; once with aggregation "sync" and once
   "async" (async_buffer --buffer) for each seed, --jobs runs at a time (one torch thread each).
   A finished run is read back, not run again.
3. With --bench-episodes N > 0, each run's best model drives drive-bench in town01 (N episodes per
   task; scale200's towns are copies of Town01).

Prints, per arm, the mean over seeds with its t-based 95 % interval: final balanced accuracy, cloud
rounds, edge aggregations, simulated time at the end, stragglers, wasted MB and (with 3) the driving
score and success; the paired differences async - sync; and

    async time to sync's final balanced accuracy: <ratio> [lo, hi] (n = N), reached in N of S seeds; per seed [...]

the simulated time at which async first reaches the balanced accuracy of sync's last evaluation,
over the simulated time of that evaluation, per seed (a seed where async never reaches it counts
as not reached, and the ratio is over the seeds that did).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_scale import dataset_sizes  # noqa: E402


def generate(scenario: str, data_dir: Path, samples: int, seed: int) -> None:
    from crchfl_sumo.data.generation import generate_dataset
    from crchfl_sumo.sumo.scenario import load_scenario

    generate_dataset(load_scenario(scenario), data_dir, seed=seed, sizes=dataset_sizes(scenario, samples, 50))


def config_mapping(args: argparse.Namespace, data_dir: Path, aggregation: str, seed: int) -> dict:
    return {
        "scenario": args.scenario,
        "dataset": str(data_dir),
        "federation": {"scheme": "hfl", "edge_interval": 1, "cloud_interval": 1, "seed": seed,
                       "aggregation": aggregation, "async_buffer": args.buffer,
                       "staleness_exponent": args.staleness_exponent},
        "ledger": {"rule": "physical", "model_size": "real", "sample_size": "measured", "budget_gb": args.budget_gb},
        "model": {"size": "compact"},
        "train": {"device": "cpu"},
        "clock": {"kind": "sumo"},
    }


def run_one(job: tuple[dict, str]) -> dict:
    """Child process: one run (resumed where it stopped)."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)
    from crchfl_sumo.core.config import from_mapping
    from crchfl_sumo.federation.run import run_federation_dir
    from crchfl_sumo.federation.run_config import RunConfig
    from crchfl_sumo.federation.run_data import read_inputs

    mapping, out = job
    config = from_mapping(RunConfig, mapping, where="bench_async")
    return run_federation_dir(config, read_inputs(config), Path(out), resume=True)


def bench_one(job: tuple[str, str, int]) -> dict:
    """Child process: drive-bench of one run's best model."""
    os.environ["OMP_NUM_THREADS"] = "1"
    from crchfl_sumo.driving.drive_bench import run_benchmark

    model, out, episodes = job
    summary = Path(out) / "summary.json"
    if summary.is_file():  # driven before
        return json.loads(summary.read_text())
    return run_benchmark(Path(model), Path(out), episodes=episodes, towns=("town01",))


def evaluations(run_dir: Path) -> list[tuple[float, float]]:
    """(simulated time, balanced accuracy) of every cloud evaluation of a run, in order."""
    lines = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [(m["sim_time_s"], m["balanced_accuracy"]) for m in lines
            if m["stage"] == "III" and m.get("balanced_accuracy") is not None]


def reach_ratio(sync: list[tuple[float, float]], asyn: list[tuple[float, float]]) -> float | None:
    """When async first reaches sync's last balanced accuracy, over when sync had it (None: never, or sync
    made no evaluation)."""
    if not sync:
        return None
    t_sync, target = sync[-1]
    t_async = next((t for t, ba in asyn if ba >= target), None)
    return None if t_async is None else t_async / t_sync


def interval(values: list[float]) -> str:
    from crchfl_sumo.studies.statistics import mean_std

    values = [v for v in values if v is not None and not math.isnan(v)]
    if not values:
        return "-"
    stats = mean_std(values)
    lo, hi = stats["ci95"] if stats["ci95"] else (math.nan, math.nan)
    return f"{stats['mean']:.3f} [{lo:.3f}, {hi:.3f}] (n = {len(values)})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--scenario", default="scale200")
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--samples", type=int, default=32)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--budget-gb", type=float, default=6.0)
    parser.add_argument("--buffer", type=int, default=5)
    parser.add_argument("--staleness-exponent", type=float, default=0.5)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--bench-episodes", type=int, default=0)
    args = parser.parse_args()
    data_dir = args.data or args.out / "data"
    if not (data_dir / "manifest.json").exists():
        generate(args.scenario, data_dir, args.samples, seed=0)
    arms = ("sync", "async")
    runs = {(arm, s): args.out / f"{arm}_s{s}" for arm in arms for s in range(args.seeds)}
    jobs = [(config_mapping(args, data_dir, arm, s), str(out)) for (arm, s), out in runs.items()]
    context = multiprocessing.get_context("spawn")
    with context.Pool(args.jobs) as pool:
        summaries = dict(zip(runs, pool.map(run_one, jobs, chunksize=1)))
        benches = {}
        if args.bench_episodes:
            bench_jobs = [(str(out / "best_model.pt"), str(out / "bench"), args.bench_episodes) for out in runs.values()]
            benches = dict(zip(runs, pool.map(bench_one, bench_jobs, chunksize=1)))
    from crchfl_sumo.core.intervals import paired_difference

    def figure(arm: str, s: int) -> dict:
        summary, run_dir = summaries[(arm, s)], runs[(arm, s)]
        evals = evaluations(run_dir)
        row = {
            "final balanced accuracy": evals[-1][1] if evals else math.nan,
            "cloud rounds": summary["cloud_rounds"],
            "edge aggregations": summary["edge_aggregations"],
            "simulated s at the end": evals[-1][0] if evals else math.nan,
            "stragglers": summary["stragglers"],
            "wasted MB": summary["wasted_bytes"] / 1e6,
        }
        if benches:
            cells = [c for tasks in benches[(arm, s)]["results"].values() for c in tasks.values()]
            row["driving score"] = sum(c["driving_score"] for c in cells) / len(cells)
            row["success"] = sum(c["success_rate"] for c in cells) / len(cells)
        return row

    rows = {(arm, s): figure(arm, s) for arm, s in runs}
    seeds = range(args.seeds)
    print(f"{args.scenario}, HFL, {args.budget_gb:g} GB, async_buffer {args.buffer}, "
          f"staleness exponent {args.staleness_exponent:g}, {args.seeds} seeds")
    for key in rows[("sync", 0)]:
        sync = [rows[("sync", s)][key] for s in seeds]
        asyn = [rows[("async", s)][key] for s in seeds]
        diff = paired_difference(sync, asyn) if len(sync) > 1 else None  # async - sync
        words = "" if diff is None or diff["ci95"] is None else (
            f"; async - sync {diff['mean']:+.3f} [{diff['ci95'][0]:+.3f}, {diff['ci95'][1]:+.3f}], p {diff['p']:.3f}")
        print(f"  {key}: sync {interval(sync)}; async {interval(asyn)}{words}")
    ratios = [reach_ratio(evaluations(runs[("sync", s)]), evaluations(runs[("async", s)])) for s in seeds]
    reached = [r for r in ratios if r is not None]
    print(f"async time to sync's final balanced accuracy: {interval(reached)}, reached in {len(reached)} of "
          f"{args.seeds} seeds; per seed {[None if r is None else round(r, 3) for r in ratios]}")


if __name__ == "__main__":
    main()
