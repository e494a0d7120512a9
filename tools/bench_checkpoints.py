"""Benchmark: two drivers in closed loop, side by side on the same drive-bench episodes, with intervals.

The guard for any change of recipe, precision, decoding or speed lever: offline accuracy is no
evidence that a driver drives. Each checkpoint (or "reference") drives every benchmark draw
(--seeds: at least two, one of them never used while tuning); the episodes of A and B are paired
(same draw, town, task and route), and per cell and over all the tool prints success with its
Wilson 95 % interval, driving score with its t interval, and B - A paired by episode with its
95 % interval, saying "not distinguishable" where that interval covers 0
(crchfl_sumo.driving.drive_bench_compare). Each drive-bench folder is kept under --out.

Prints, last, the two named lines:
    closed-loop success B-A: +X points [LO, HI] (p P)
    closed-loop driving score B-A: +X [LO, HI] (p P)

Usage: python tools/bench_checkpoints.py A.pt B.pt --out DIR [--seeds 0,8461] [--episodes 10]
       [--towns town01,town02] [--tasks straight,one_turn,navigation,navigation_traffic] [--jobs 1]
       [--labels A,B]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark
from crchfl_sumo.driving.drive_bench_compare import ALL, compare_episodes, comparison_table


def drive_all(model: str, out: Path, seeds: list[int], episodes: int, towns: tuple, config: BenchConfig, jobs: int):
    """Every draw's episode records of one driver, each tagged with its draw."""
    records = []
    for seed in seeds:
        folder = out / f"draw-{seed}"
        if not (folder / "episodes.json").is_file():  # a rerun reuses finished draws
            run_benchmark(None if model == "reference" else model, folder, episodes=episodes, jobs=jobs, seed=seed,
                          towns=towns, config=config)
        records += [{**r, "draw": seed} for r in json.loads((folder / "episodes.json").read_text())]
    return records


def named_line(what: str, difference: dict, scale: float) -> str:
    ci = difference["ci95"]
    interval = f" [{scale * ci[0]:+.1f}, {scale * ci[1]:+.1f}]" if ci else ""
    p = f" (p {difference['p']:.3g})" if difference["p"] is not None else ""
    return f"closed-loop {what} B-A: {scale * difference['mean']:+.1f}{' points' if what == 'success' else ''}{interval}{p}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", help="checkpoint A (the code or recipe before), or 'reference'")
    parser.add_argument("b", help="checkpoint B (the change), or 'reference'")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", default="0,8461", help="benchmark draws, separated by commas (default 0,8461)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per task and town and draw")
    parser.add_argument("--towns", default="town01,town02")
    parser.add_argument("--tasks", default="straight,one_turn,navigation,navigation_traffic")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--labels", default="A,B")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    towns = tuple(args.towns.split(","))
    label_a, label_b = args.labels.split(",")
    config = BenchConfig(tasks=tuple(args.tasks.split(",")))
    a = drive_all(args.a, args.out / "a", seeds, args.episodes, towns, config, args.jobs)
    b = drive_all(args.b, args.out / "b", seeds, args.episodes, towns, config, args.jobs)
    comparison = compare_episodes(a, b)
    table = comparison_table(comparison, label_a, label_b)
    (args.out / "comparison.json").write_text(json.dumps({"a": args.a, "b": args.b, "seeds": seeds,
                                                          "cells": comparison}, indent=1) + "\n")
    (args.out / "comparison.md").write_text(table)
    print(f"A = {args.a}, B = {args.b}; draws {seeds}, {args.episodes} episodes per task, town and draw")
    print(table)
    print(named_line("success", comparison[ALL]["success_difference"], 100))
    print(named_line("driving score", comparison[ALL]["driving_score_difference"], 100))


if __name__ == "__main__":
    main()
