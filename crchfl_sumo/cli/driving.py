"""The subcommands whose work lives in driving/: drive, drive-compare, drive-bench and dagger."""

from __future__ import annotations

import argparse
from pathlib import Path

from crchfl_sumo.cli.arguments import (
    comma_list,
    leave_out_at_default,
    output_folder,
    overwrite_argument,
    sumo_output_argument,
)
from crchfl_sumo.cli.progress_bars import ProgressBars
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_DRIVE_S, MAX_EPOCHS, MAX_JOBS, integer_arg, number_arg, seed_arg


def _decoding_arguments(p: argparse.ArgumentParser) -> None:
    """How a model's outputs become actions: --steer-decoding and --brake-gain."""
    from crchfl_sumo.learning.settings import DEFAULT_BRAKE_GAIN, DEFAULT_STEER_DECODING, STEER_DECODINGS

    p.add_argument("--steer-decoding", choices=STEER_DECODINGS, default=DEFAULT_STEER_DECODING,
                   help="a model's steer: 'argmax' (the paper's DAC: the likeliest class's value), 'expected' "
                        "(the class values weighted by probability), 'mode' (the same over the likeliest class and "
                        "its neighbours) or 'auto' (argmax for the paper's 7 classes, mode for a finer steer head); "
                        f"default {DEFAULT_STEER_DECODING}")
    p.add_argument("--brake-gain", type=number_arg(0, 100, "a gain", lo_open=True), default=DEFAULT_BRAKE_GAIN,
                   help="a target-speed model reaches a lower target in its speed horizon / this "
                        f"(1 = as the labels were made; default {DEFAULT_BRAKE_GAIN:g})")


def _towns_argument(p: argparse.ArgumentParser) -> None:
    from crchfl_sumo.driving.drive_bench_tasks import DEFAULT_TOWNS

    towns = ",".join(DEFAULT_TOWNS)
    p.add_argument("--towns", default=towns,
                   help=f"built-in scenarios or .sumocfg paths, separated by commas (default {towns})")


def add_drive(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="checkpoint.pt of a trained model, or 'reference' for the scripted route driver")
    p.add_argument("--route", required=True,
                   help="named route (scenarios/drive_routes.toml) or edge ids separated by commas")
    p.add_argument("--scenario", default=None, help="built-in scenario or .sumocfg (named routes bring their own)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    overwrite_argument(p)
    p.add_argument("--seed", type=seed_arg, default=0, help="simulation seed (default 0)")
    p.add_argument("--max-s", type=number_arg(0, MAX_DRIVE_S, "simulated seconds", lo_open=True), default=150.0,
                   help="simulated seconds at most (default 150)")
    p.add_argument("--warmup-s", type=number_arg(0, MAX_DRIVE_S, "simulated seconds"), default=20.0,
                   help="traffic runs this long before the ego starts (default 20)")
    p.add_argument("--no-video", action="store_true", help="skip drive.mp4")
    sumo_output_argument(p, "the drive", " (the ego is in them as 'ego')")
    _decoding_arguments(p)


def run_drive(args) -> int:
    from crchfl_sumo.driving.drive import DriveConfig
    from crchfl_sumo.driving.route_drive import drive_route

    with output_folder(args, "drive"):
        m = drive_route(
            None if args.model == "reference" else args.model, args.scenario, args.route, args.out,
            args.seed, args.max_s, DriveConfig(warmup_s=args.warmup_s), video=not args.no_video,
            steer_decoding=args.steer_decoding, brake_gain=args.brake_gain,
            sumo_outputs=comma_list(args.sumo_output),
        )
    print(
        f"{m['route']}: {m['end_reason']}, completion {100 * m['completion']:.0f}%, collisions {m['collisions']}, "
        f"lane departures {m['lane_departures']}, off-road {m['off_road_events']}, "
        f"red lights {m['red_light_violations']}, mean speed {m['mean_speed_mps']:.1f} m/s -> {args.out}"
    )
    return 0


def add_drive_compare(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", type=Path, help="folders written by `crchfl-sumo drive` (same route)")
    p.add_argument("--labels", nargs="+", default=None, help="one label per folder (default: folder names)")
    p.add_argument("--out", type=Path, required=True, help="output PNG")
    overwrite_argument(p, file=True)


def run_drive_compare(args) -> int:
    from crchfl_sumo.core.outputs import prepare_output_file
    from crchfl_sumo.driving.plots import compare_runs

    prepare_output_file(args.out, f"{args.command} --out", replace=args.overwrite)
    print(f"-> {compare_runs(args.runs, args.labels, args.out)}")
    return 0


def add_drive_bench(p: argparse.ArgumentParser) -> None:
    from crchfl_sumo.driving.drive_bench_tasks import TASK_NAMES

    p.add_argument("model", help="checkpoint.pt of a trained model, or 'reference' for the scripted route driver")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    overwrite_argument(p)
    p.add_argument("--episodes", type=integer_arg(1, 10_000, "a number of episodes"), default=5,
                   help="episodes per task and town (default 5)")
    p.add_argument("--jobs", type=integer_arg(1, MAX_JOBS, "a number of processes"), default=1,
                   help="episode groups run at a time, each in its own process (default 1)")
    p.add_argument("--seed", type=seed_arg, default=0, help="draws the routes, SUMO seeds and warm-ups (default 0)")
    _towns_argument(p)
    p.add_argument("--tasks", default=",".join(TASK_NAMES),
                   help=f"tasks separated by commas (default {','.join(TASK_NAMES)})")
    p.add_argument("--max-route-m", type=number_arg(0, 1e6, "metres", lo_open=True), default=600.0,
                   help="longest route drawn (default 600)")
    p.add_argument("--min-route-m", type=number_arg(0, 1e6, "metres"), default=0.0,
                   help="shortest route drawn (default 0: any)")
    p.add_argument("--navigation-turns", default="2,1000",
                   help="fewest and most turns of a navigation route, FEWEST,MOST (default 2,1000)")
    _decoding_arguments(p)


def run_drive_bench(args) -> int:
    from crchfl_sumo.driving.drive_bench import BenchConfig, results_table, run_benchmark
    from crchfl_sumo.driving.drive_bench_tasks import TaskConfig

    with output_folder(args, "drive-bench"):
        towns, tasks = comma_list(args.towns), comma_list(args.tasks)
        turns = comma_list(args.navigation_turns)
        if len(turns) != 2 or not all(t.isdigit() for t in turns):
            raise CrchflError(f"--navigation-turns: {args.navigation_turns!r}; give FEWEST,MOST, for example 2,1000")
        routes = TaskConfig(max_route_m=args.max_route_m, min_route_m=args.min_route_m,
                            navigation_turns=(int(turns[0]), int(turns[1])))
        with ProgressBars("episode") as bars:
            summary = run_benchmark(
                args.model, args.out, args.episodes, args.jobs, args.seed, towns,
                BenchConfig(tasks=tasks, routes=routes, steer_decoding=args.steer_decoding, brake_gain=args.brake_gain),
                bars,
            )
    print(results_table(summary))
    print(f"SUMO's warnings: {summary['sumo_warnings']}, in {args.out / 'sumo-logs'}")
    print(f"{summary['wall_s']:.0f} s wall -> {args.out}")
    return 0


def add_dagger(p: argparse.ArgumentParser) -> None:
    from crchfl_sumo.driving.dagger_settings import (
        FINE_TUNE_CLASS_WEIGHTING,
        FINE_TUNE_CLASS_WEIGHTINGS,
        FINE_TUNE_LEARNING_RATE,
        KEEP_START_WEIGHTING,
        MAX_ITERATIONS,
        DaggerConfig,
    )
    from crchfl_sumo.driving.drive_bench_tasks import TASK_NAMES

    p.add_argument("model", help="checkpoint.pt of a trained model (crchfl-sumo train)")
    p.add_argument("dataset", type=Path, help="the data set it was trained on (manifest.json and shards)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: iteration-K/ (expert_samples.npz, metrics.jsonl, checkpoint.pt), "
                   "checkpoint.pt (the last iteration's model), summary.json")
    overwrite_argument(p)
    p.add_argument("--iterations", type=integer_arg(1, MAX_ITERATIONS, "a number of iterations"), default=1,
                   help="drive, label and fine-tune this many times (default 1)")
    defaults = DaggerConfig()
    p.add_argument("--episodes", type=integer_arg(1, 10_000, "a number of episodes"), default=defaults.episodes,
                   help=f"drives per task and town in each iteration (default {defaults.episodes})")
    p.add_argument("--tasks", default=",".join(defaults.tasks),
                   help=f"drive-bench tasks the drives are drawn from, separated by commas (of {','.join(TASK_NAMES)}; "
                   f"default {','.join(defaults.tasks)})")
    _towns_argument(p)
    p.add_argument("--epochs", type=integer_arg(1, MAX_EPOCHS, "a number of epochs"), default=3,
                   help="fine-tuning epochs per iteration (default 3)")
    p.add_argument("--route-seed", type=seed_arg, default=defaults.seed,
                   help=f"iteration K draws its routes with this + K (default {defaults.seed}; drive-bench "
                   "uses 0: keep them apart so the model is not scored on the routes it was taught)")
    p.add_argument("--seed", type=seed_arg, default=0, help="iteration K fine-tunes with seed this + K (default 0)")
    p.add_argument("--learning-rate", type=number_arg(0, 1, "a learning rate", lo_open=True),
                   default=FINE_TUNE_LEARNING_RATE,
                   help=f"fine-tuning learning rate (default {FINE_TUNE_LEARNING_RATE:g})")
    p.add_argument("--class-weighting", choices=FINE_TUNE_CLASS_WEIGHTINGS,
                   default=FINE_TUNE_CLASS_WEIGHTING,
                   help=f"steer class weights of the fine-tuning (default {FINE_TUNE_CLASS_WEIGHTING}; "
                   f"{KEEP_START_WEIGHTING}: the start model's, as before 2026-12-06; docs/model.md)")
    p.add_argument("--all-states", action="store_true",
                   help="label every visited state (default: only those where the expert brakes harder or steers "
                   "elsewhere than the model)")
    p.add_argument("--jobs", type=integer_arg(1, MAX_JOBS, "a number of processes"), default=1,
                   help="drives run at a time, each group in its own process (default 1)")
    p.add_argument("--resume", action="store_true",
                   help="continue in --out after its last finished epoch (the same command line; --iterations may be "
                   "raised). The same command line again also continues")
    p.add_argument("--train-towns", type=comma_list, default=None,
                   help="fine-tune on these towns' training shards only (and the labels), separated by commas: "
                   "those the model was trained on with `train --train-towns` (default: every town)")


def run_dagger(args) -> int:
    from crchfl_sumo.driving.dagger import dagger_command
    from crchfl_sumo.driving.dagger_settings import KEEP_START_WEIGHTING, DaggerConfig

    train_towns, class_weighting = args.train_towns, args.class_weighting
    # a folder started before the option resumes with --class-weighting start (what it fine-tuned with)
    leave_out_at_default(args, ((("train_towns",), train_towns is None),
                                (("class_weighting",), class_weighting == KEEP_START_WEIGHTING)))
    with output_folder(args, "dagger", extendable=("iterations",)):  # --resume --iterations N goes on to N
        config = DaggerConfig(tasks=comma_list(args.tasks), episodes=args.episodes, seed=args.route_seed,
                              corrections_only=not args.all_states)
        records = dagger_command(args.model, args.dataset, args.out, comma_list(args.towns), config,
                                 args.iterations, args.epochs, args.seed, args.jobs, args.learning_rate, args.overwrite,
                                 train_towns=train_towns, class_weighting=class_weighting)
    for record in records:
        straight = record["always_straight"]
        print(
            f"iteration {record['iteration']}: +{record['expert_samples']} expert-labelled samples "
            f"({record['training_samples']} in all), accuracy {record['accuracy']:.3f} "
            f"(always straight {straight['accuracy']:.3f}), balanced accuracy {record['balanced_accuracy']:.3f} "
            f"(always straight {straight['balanced_accuracy']:.3f})"
        )
    print(f"-> {args.out / 'checkpoint.pt'}")
    return 0
