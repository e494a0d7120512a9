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

Two recipes trained with several seeds: give each side's checkpoints separated by commas, the
k-th of A and of B trained with the same seed. Every model drives the same draws; the tool prints
each model's success, strict success, driving score and red lights per km, and per figure B - A
paired by seed (crchfl_sumo.driving.drive_bench_compare.compare_models), then every cell over all
seeds paired by episode (seed, draw, town, task and route), ending with the named lines
    closed-loop success B-A over seeds: +X points [LO, HI] (p P)
    closed-loop strict success B-A over seeds: ...
    closed-loop driving score B-A over seeds: ...
    closed-loop red lights per km B-A over seeds: ...
    closed-loop success B-A by episode over seeds: +X points [LO, HI] (p P)
    closed-loop driving score B-A by episode over seeds: ...
A draw folder that already holds an episodes.json is read, not driven again: benchmarks run
elsewhere can be compared by placing them as OUT/{a,b}/model-K/draw-SEED/episodes.json.

Usage: python tools/bench_checkpoints.py A.pt[,A2.pt,...] B.pt[,B2.pt,...] --out DIR [--seeds 0,8461]
       [--episodes 10] [--towns town01,town02] [--tasks straight,one_turn,navigation,navigation_traffic]
       [--jobs 1] [--labels A,B]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark
from crchfl_sumo.core.intervals import distinguishable
from crchfl_sumo.driving.drive_bench_compare import ALL, MODEL_FIGURES, compare_episodes, compare_models, comparison_table


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


def _estimate(difference: dict, scale: float, digits: int, unit: str = "") -> str:
    """A paired difference as "+X[unit] [LO, HI] (p P)"."""
    ci = difference["ci95"]
    interval = f" [{scale * ci[0]:+.{digits}f}, {scale * ci[1]:+.{digits}f}]" if ci else ""
    p = f" (p {difference['p']:.3g})" if difference["p"] is not None else ""
    return f"{scale * difference['mean']:+.{digits}f}{unit}{interval}{p}"


def named_lines(pooled: dict, where: str = "") -> str:
    """The two named lines of the pooled cell (compare_episodes' ALL): success and driving score B - A."""
    return "\n".join(f"closed-loop {what} B-A{where}: {_estimate(pooled[key], 100, 1, unit)}"
                     for what, key, unit in (("success", "success_difference", " points"),
                                             ("driving score", "driving_score_difference", "")))


# How each MODEL_FIGURES figure is printed: its name in the named lines, the scale and the unit.
_PRINTED = {"success": ("success", 100, " points"), "strict_success": ("strict success", 100, " points"),
            "driving_score": ("driving score", 100, ""), "red_lights_per_km": ("red lights per km", 1, "")}


def seeds_table(comparison: dict, labels: tuple[str, str]) -> str:
    """Each model's figures, side by side by seed, and B - A paired by seed."""
    lines = ["| model (seed order) | " + " | ".join(f"{_PRINTED[f][0]} {x}" for f in MODEL_FIGURES for x in labels) + " |",
             "| --- |" + " --- |" * (2 * len(MODEL_FIGURES))]
    for k, (ma, mb) in enumerate(zip(comparison["a"]["models"], comparison["b"]["models"])):
        cells = [f"{_PRINTED[f][1] * m[f]:.2f}" for f in MODEL_FIGURES for m in (ma, mb)]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def seeds_line(figure: str, difference: dict) -> str:
    name, scale, unit = _PRINTED[figure]
    words = "" if distinguishable(difference["ci95"]) else ", not distinguishable"
    return f"closed-loop {name} B-A over seeds: {_estimate(difference, scale, 2, unit)}{words}"


def compare_seeds(models_a: list[str], models_b: list[str], args, seeds, towns, config) -> None:
    """Several models a side: each drives every draw; the comparison model by model, paired by seed."""
    a = [drive_all(m, args.out / "a" / f"model-{k}", seeds, args.episodes, towns, config, args.jobs)
         for k, m in enumerate(models_a)]
    b = [drive_all(m, args.out / "b" / f"model-{k}", seeds, args.episodes, towns, config, args.jobs)
         for k, m in enumerate(models_b)]
    comparison = compare_models(a, b)
    labels = tuple(args.labels.split(","))
    table = seeds_table(comparison, labels)
    (args.out / "comparison.json").write_text(json.dumps({"a": models_a, "b": models_b, "seeds": seeds,
                                                          **comparison}, indent=1) + "\n")
    cells = comparison_table(comparison["by_episode"], *labels)
    (args.out / "comparison.md").write_text(table + "\n" + cells)
    print(f"A = {models_a}, B = {models_b}; draws {seeds}, {args.episodes} episodes per task, town and draw")
    for side, label in zip("ab", labels):
        c = comparison[side]
        lo, hi = c["success_ci95"]
        print(f"{label}: success {100 * c['success_rate']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}] of {c['episodes']}")
    print(table)
    print(cells)
    for figure in MODEL_FIGURES:
        print(seeds_line(figure, comparison["differences"][figure]))
    print(named_lines(comparison["by_episode"][ALL], " by episode over seeds"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", help="checkpoint A (the code or recipe before), or 'reference'; several: one per seed")
    parser.add_argument("b", help="checkpoint B (the change), or 'reference'; several: one per seed, as A's")
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
    models_a, models_b = args.a.split(","), args.b.split(",")
    if len(models_a) > 1 or len(models_b) > 1:
        compare_seeds(models_a, models_b, args, seeds, towns, config)
        return
    a = drive_all(args.a, args.out / "a", seeds, args.episodes, towns, config, args.jobs)
    b = drive_all(args.b, args.out / "b", seeds, args.episodes, towns, config, args.jobs)
    comparison = compare_episodes(a, b)
    table = comparison_table(comparison, label_a, label_b)
    (args.out / "comparison.json").write_text(json.dumps({"a": args.a, "b": args.b, "seeds": seeds,
                                                          "cells": comparison}, indent=1) + "\n")
    (args.out / "comparison.md").write_text(table)
    print(f"A = {args.a}, B = {args.b}; draws {seeds}, {args.episodes} episodes per task, town and draw")
    print(table)
    print(named_lines(comparison[ALL]))


if __name__ == "__main__":
    main()
