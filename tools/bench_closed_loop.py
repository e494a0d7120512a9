"""Benchmark: how centralized training recipes drive, side by side on one data set and one suite.

Trains one centralized compact model per recipe on the same data set (same
seed, same epochs), then drives each on the same drive-bench episodes, and
prints per recipe the offline metrics (balanced accuracy beside always-straight,
steer error) and the closed-loop success, route completion and driving score
per task. docs/model.md ("Closed loop at the centralized level") records the
figures.

Recipes are NAME=KEY:VALUE,KEY:VALUE with keys of ModelConfig or TrainConfig,
for example  base=  speed=speed_input:true  pedals=speed_input:true,sampling:pedal_balanced
A recipe that names no ema_decay keeps `train`'s default moving average (settings.auto_ema_decay);
ema_decay:0 trains without it.

Usage: python tools/bench_closed_loop.py DATASET --out DIR [--epochs 6] [--episodes 6]
       [--tasks straight,one_turn] [--towns town01] [--train-towns TOWNS] [--jobs 2]
       [--steer-decoding argmax] [--seed S] [--bench-seed D] RECIPE...

--train-towns trains on those towns' shards only (the test split stays whole):
train on town01, drive in town02 to measure generalisation to an unseen town.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.dataset import load_samples
from crchfl_sumo.data.manifest import read_manifest
from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig, auto_ema_decay
from crchfl_sumo.learning.centralized import train_centralized

MODEL_KEYS = {f.name for f in dataclasses.fields(ModelConfig)}
TRAIN_KEYS = {f.name for f in dataclasses.fields(TrainConfig)}


def parse_recipe(text: str) -> tuple[str, dict, dict]:
    """'NAME=k:v,k:v' -> (name, ModelConfig overrides, TrainConfig overrides)."""
    name, _, body = text.partition("=")
    model, train = {}, {}
    for item in filter(None, body.split(",")):
        key, _, raw = item.partition(":")
        value = {"true": True, "false": False}.get(raw.lower(), raw)
        if isinstance(value, str):
            try:
                value = float(value) if "." in value or "e" in value else int(value)
            except ValueError:
                pass
        if key in MODEL_KEYS:
            model[key] = value
        elif key in TRAIN_KEYS:
            train[key] = value
        else:
            raise SystemExit(f"recipe {name!r}: unknown key {key!r} (ModelConfig or TrainConfig fields)")
    return name, model, train


def task_columns(results: dict) -> str:
    """' | TOWN TASK: success S, completion C, score D' for every task of a drive-bench summary's results."""
    return "".join(
        f" | {town} {task}: success {r['success_rate']:.2f}, completion {r['route_completion']:.2f}, "
        f"score {r['driving_score']:.2f}"
        for town, tasks in results.items()
        for task, r in tasks.items()
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset")
    parser.add_argument("recipes", nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--epochs", type=int, default=6)
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--tasks", default="straight,one_turn")
    parser.add_argument("--towns", default="town01", help="towns the benchmark drives")
    parser.add_argument("--train-towns", default=None, help="train on these towns' shards only (default: all)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--steer-decoding", default="argmax")
    parser.add_argument("--seed", type=int, default=0, help="seeds the training (default 0)")
    parser.add_argument("--bench-seed", type=int, default=0,
                        help="the benchmark draw: its routes, SUMO seeds and warm-ups (default 0)")
    args = parser.parse_args()
    manifest = read_manifest(Path(args.dataset))
    towns = None if args.train_towns is None else tuple(args.train_towns.split(","))
    try:
        vehicles = manifest.town_vehicles(towns, args.dataset)
    except CrchflError as error:
        raise SystemExit(str(error)) from None
    train, test = load_samples(args.dataset, "train", vehicles), load_samples(args.dataset, "test")
    config = BenchConfig(tasks=tuple(args.tasks.split(",")), steer_decoding=args.steer_decoding)
    rows = []
    for name, model_overrides, train_overrides in map(parse_recipe, args.recipes):
        folder = args.out / name
        records = train_centralized(
            train, test, args.epochs, folder,
            ModelConfig(**{"image_height": 64, "image_width": 128, "speed_horizon_s": manifest.speed_horizon_s,
                           **model_overrides}),
            TrainConfig(**{"ema_decay": auto_ema_decay(len(train), TrainConfig(**train_overrides).batch_size),
                           **train_overrides}), args.seed,
            drive_settings=manifest.drive_settings(f"{args.dataset}/manifest.json"), overwrite=True,
        )
        best = records[-1]
        summary = run_benchmark(folder / "checkpoint.pt", folder / "bench", episodes=args.episodes, jobs=args.jobs,
                                seed=args.bench_seed, towns=tuple(args.towns.split(",")), config=config)
        rows.append((name, best, summary))
    print(f"{len(train)} training samples, {args.epochs} epochs, seed {args.seed}, {args.episodes} episodes per task")
    for name, best, summary in rows:
        print(f"{name}: balanced {best['balanced_accuracy']:.3f} (always-straight "
              f"{best['always_straight']['balanced_accuracy']:.3f}), steer error {best['steer_error']:.3f}"
              + task_columns(summary["results"]))
    (args.out / "closed_loop.json").write_text(json.dumps([
        {"recipe": name, "final": best, "results": summary["results"]} for name, best, summary in rows
    ], indent=1))


if __name__ == "__main__":
    main()
