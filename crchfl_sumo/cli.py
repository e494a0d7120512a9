"""`crchfl-sumo <subcommand>`: parses arguments, calls the library, prints results.

Thin on purpose: every subcommand is a pair (add its arguments, run it) and the
work happens in the library modules. A CrchflError is printed as one line on
stderr with exit status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from contextlib import nullcontext
from pathlib import Path

from crchfl_sumo import __version__
from crchfl_sumo.core.cpus import available_cpus, choose_wait_policy, settle_native_libraries
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import (
    MAX_DRIVE_S,
    MAX_EPOCHS,
    MAX_JOBS,
    MAX_SIMULATED_S,
    integer_arg,
    number_arg,
    seed_arg,
)
from crchfl_sumo.core.result_files import RESULTS_MD_FILE
from crchfl_sumo.learning.settings import ARCHS, MAX_RED_WEIGHT, MAX_RED_WINDOW_M, PRECISIONS, TrainConfig


class _Parser(argparse.ArgumentParser):
    """An argument error as a CrchflError: one line naming the subcommand and argument, exit 2 (see main)."""

    def error(self, message: str):
        command = self.prog.removeprefix("crchfl-sumo").strip()
        if "; give " not in message:  # argparse's own messages (a missing or unknown argument) do not say the fix
            message += f"; see `{self.prog} --help`"
        if message.startswith("argument "):  # "argument --duration-s: ..." -> "simulate --duration-s: ..."
            raise CrchflError(f"{command} {message.removeprefix('argument ')}".strip())
        raise CrchflError(f"{command}: {message}" if command else message)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="crchfl-sumo",
        description="Hierarchical federated learning for end-to-end driving on SUMO.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, help_text, add_arguments, run in _commands():
        command = sub.add_parser(name, help=help_text, description=help_text)
        add_arguments(command)
        command.set_defaults(run=run)
    return parser


def _commands():
    """(name, help, add_arguments, run) for each subcommand, in the order --help lists them."""
    return [
        ("reproduce", "the paper's experiments B and D with closed-loop drives: runs, figures, report.md, summary.json",
         _add_reproduce, _run_reproduce),
        ("report", "rebuild the figures, report.md and summary.json of a reproduce results folder",
         _add_report, _run_report),
        ("simulate", "run a scenario with edge association and link rates; write trace, summary, plots",
         _add_simulate, _run_simulate),
        ("render", "draw one vehicle's four camera images and a top-down map: PNG per step and an MP4",
         _add_render, _run_render),
        ("dataset", "generate the driving data set (per-vehicle HDF5 shards); rerun the same command to resume",
         _add_dataset, _run_dataset),
        ("dataset-stats", "label statistics, summary figure and example mosaic of a data set",
         _add_dataset_stats, _run_dataset_stats),
        ("train", "centralized training on all shards of a data set (the federated schemes' upper bound)",
         _add_train, _run_train),
        ("drive", "a model (or 'reference') drives an ego along a route in SUMO: metrics, map, action frames, video",
         _add_drive, _run_drive),
        ("drive-compare", "several drives of one route side by side (the paper's Fig. 5)",
         _add_drive_compare, _run_drive_compare),
        ("drive-bench", "closed-loop benchmark of a model or 'reference': CoRL2017 tasks, success, driving score",
         _add_drive_bench, _run_drive_bench),
        ("dagger", "DAgger: a model drives, the route expert labels what it sees, the model is fine-tuned on it",
         _add_dagger, _run_dagger),
        ("run", "federated training (CRCHFL, HFL or SFL) on SUMO's clock: metrics, ledger, checkpoints, summary",
         _add_run, _run_run),
        ("sweep", "a grid of runs over config settings (mobility studies): a table and plots against each parameter",
         _add_sweep, _run_sweep),
        ("mobility-study", "the built-in mobility study: speed, density, edge sites, handover policy one at a time; "
         "a table and a figure per factor", _add_mobility_study, _run_mobility_study),
        ("calibrate", "fit alpha, gamma, d of problem P from short pilot runs (docs/calibration.md)",
         _add_calibrate, _run_calibrate),
        ("plan", "solve the resource allocation (problem P) for a communication budget",
         _add_plan, _run_plan),
    ]


class ProgressBars:
    """The library's progress updates (core.progress) as tqdm bars: one bar a stage, its details beside it.

    Without a terminal (a log file, CI), where bars are not drawn, a plain line goes to stderr instead: at
    each new stage, at a stage's end, and at most every ``PLAIN_EVERY_S`` seconds in between.
    The CLI owns all progress display; use as a context manager so the last bar closes.
    """

    PLAIN_EVERY_S = 60.0

    def __init__(self, unit: str, stream=None) -> None:
        from tqdm import tqdm

        self._tqdm = tqdm
        self._unit = unit
        self._stage: str | None = None
        self._bar = None
        self._stream = stream if stream is not None else sys.stderr
        self._plain = not (hasattr(self._stream, "isatty") and self._stream.isatty())
        self._last_line_s = -math.inf
        self._ended = False  # the current stage's last line is out

    def __call__(self, update) -> None:
        if self._plain:
            self._line(update)
            return
        if update.stage != self._stage or self._bar is None or update.done < self._bar.n:
            self.close()
            self._bar = self._tqdm(total=update.total, unit=self._unit, desc=update.stage, dynamic_ncols=True,
                             leave=False, disable=None)
            self._stage = update.stage
        self._bar.update(update.done - self._bar.n)
        if update.detail:
            self._bar.set_postfix(update.detail)

    def _line(self, update) -> None:
        now = time.monotonic()
        new_stage = update.stage != self._stage
        finished = update.total is not None and update.done >= update.total and (new_stage or not self._ended)
        if new_stage or finished or now - self._last_line_s >= self.PLAIN_EVERY_S:
            of = "" if update.total is None else f"/{update.total}"
            detail = "".join(f", {k} {v}" for k, v in update.detail.items())
            print(f"{update.stage}: {update.done}{of} {self._unit}{detail}", file=self._stream, flush=True)
            self._stage, self._last_line_s = update.stage, now
            self._ended = update.total is not None and update.done >= update.total

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "ProgressBars":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# Arguments that change where or how fast a command runs, not what its results are.
_NOT_SETTINGS = {"run", "command", "verbose", "out", "overwrite", "resume", "jobs", "backend", "address", "no_video"}


def _overwrite_argument(p: argparse.ArgumentParser, file: bool = False) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out if it exists" if file else
                   "write into --out even if it holds earlier results (files of the same names are replaced)")


def _output_folder(
    args, command: str, out: Path | None = None, resumable: bool = False, beside=(), extendable=(), formerly_kept=()
):
    """``with`` this around a command's work: core.outputs.output_dir checks --out (or ``out``) with its settings.

    ``extendable``: arguments a ``--resume`` may change (train's --epochs); every other setting it must keep.
    ``formerly_kept``: (argument, its choices) of extendable arguments that earlier versions kept, so
    that their folders still resume (whatever value they were run with).
    """
    from crchfl_sumo.core.outputs import fingerprint, output_dir

    settings = {k: v for k, v in sorted(vars(args).items()) if k not in _NOT_SETTINGS}
    config = getattr(args, "config", None)
    files = [config] if config is not None and Path(config).is_file() else []
    kept = {k: v for k, v in settings.items() if k not in extendable}
    earlier = tuple(fingerprint({**kept, name: value}, files) for name, choices in formerly_kept for value in choices)
    return output_dir(
        args.out if out is None else out, command, fingerprint(settings, files), flag=f"{args.command} --out",
        replace=getattr(args, "overwrite", False), resumable=resumable, beside=beside,
        resume_fingerprint=fingerprint(kept, files) if extendable else None, earlier_resume_fingerprints=earlier,
        resuming=getattr(args, "resume", False),
    )


def _towns_argument(p: argparse.ArgumentParser) -> None:
    from crchfl_sumo.driving.bench_tasks import DEFAULT_TOWNS

    towns = ",".join(DEFAULT_TOWNS)
    p.add_argument("--towns", default=towns,
                   help=f"built-in scenarios or .sumocfg paths, separated by commas (default {towns})")


def _comma_list(text: str) -> tuple[str, ...]:
    """'a, b,,c' -> ('a', 'b', 'c'): the names of a comma-separated option."""
    return tuple(name.strip() for name in text.split(",") if name.strip())


def _scenario_names() -> str:
    """The built-in scenarios as --help lists them (the packaged folders, so the list never goes stale)."""
    from crchfl_sumo.core.resources import builtin_names

    return ", ".join(builtin_names())


def _scenario_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help=f"built-in scenario name ({_scenario_names()}), a folder laid out as one, "
                        "or a .sumocfg path")


# --- reproduce and report -----------------------------------------------------------------------


def _add_reproduce(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="reduced size, about 2 minutes on 2 cores (docs/reproduce.md)")
    p.add_argument("--out", type=Path, default=None, help="results folder (default results/quick or results/full)")
    p.add_argument("--seeds", type=integer_arg(1, 100, "a number of seeds per scheme"), default=None,
                   help="seeds per scheme (default: quick 1, full 3)")
    p.add_argument("--resume", action="store_true", help="finish the reproduction in --out; finished parts are kept")
    p.add_argument("--config", type=Path, default=None, help="a reproduce TOML instead of the preset")
    p.add_argument("--scenario", default=None,
                   help="run it in this scenario (a built-in name, a folder or a .sumocfg): the preset's samples "
                   "shared among its vehicles, the benchmark in it (docs/reproduce.md)")
    p.add_argument("--jobs", type=integer_arg(1, MAX_JOBS, "a number of processes"), default=1,
                   help="parts run at a time, each in its own process (default 1; the number of cores is fastest)")
    _backend_arguments(p, "where the parts run: processes of this machine (local, --jobs at a time) or Ray tasks "
                          "of one CPU each (every node must see --out at the same path)")


def _run_reproduce(args) -> int:
    from crchfl_sumo.studies.report import format_summary
    from crchfl_sumo.studies.reproduce import reproduce_command

    with ProgressBars("part") as bars:
        out, summary = reproduce_command(args.quick, args.out, args.seeds, args.resume, args.config, bars, args.jobs,
                                         args.backend, args.address, args.scenario)
    print(format_summary(summary, out))
    return 0


def _add_report(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="results folder of `crchfl-sumo reproduce`")


def _run_report(args) -> int:
    from crchfl_sumo.core.outputs import check_writable
    from crchfl_sumo.studies.report import format_summary, report_command

    check_writable(args.dir, f"report {args.dir}")  # the figures and report.md are rewritten there
    print(format_summary(report_command(args.dir), args.dir))
    return 0


# --- simulate -----------------------------------------------------------------------------------


def _add_simulate(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", default=None,
                   help=f"built-in scenario name ({_scenario_names()}), a folder laid out as one or a .sumocfg path; "
                   "or none, with --net")
    p.add_argument("--net", type=Path, default=None,
                   help="a bare SUMO network (.net.xml or .net.xml.gz) instead of a scenario: OUT/NAME.sumocfg is "
                   "written for it")
    p.add_argument("--routes", default="", help="with --net: route files, separated by commas")
    p.add_argument("--duration-s", type=number_arg(0, MAX_SIMULATED_S, "simulated seconds", lo_open=True),
                   default=None,
                   help="simulated seconds (default: the .sumocfg's <end> less <begin>; without an end 300)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    _overwrite_argument(p)
    p.add_argument("--seed", type=seed_arg, default=None, help="seed (overrides the config's; 0 .. 2**31 - 1)")
    p.add_argument("--config", type=Path, default=None,
                   help="TOML with seed, [[edge_sites]], [channel], [mobility] (docs/links.md)")
    p.add_argument("--sumo-output", default="",
                   help="SUMO's own outputs to write as OUT/sumo-NAME.xml, separated by commas: fcd, tripinfo, summary")


def _run_simulate(args) -> int:
    from crchfl_sumo.studies.simulate import run_simulate_command, sumo_output_files

    outputs, routes = _comma_list(args.sumo_output), tuple(Path(r) for r in _comma_list(args.routes))
    sumo_output_files(outputs, args.out)  # an unknown name is refused before --out is touched
    if (args.scenario is None) == (args.net is None):
        raise CrchflError("simulate: give a SCENARIO or --net NET.net.xml (with --routes R1,R2), not both or neither")
    if routes and args.net is None:
        raise CrchflError("simulate --routes: route files go with --net; a scenario names its own")
    with _output_folder(args, "simulate"):
        with ProgressBars("step") as bars:
            summary = run_simulate_command(args.scenario, args.duration_s, args.out, args.seed, args.config, bars,
                                           outputs, net=args.net, routes=routes)
    print(
        f"{summary['scenario']}: {summary['vehicles']} vehicles, {summary['steps']} steps, "
        f"{summary['handovers']} handovers, coverage {100 * summary['coverage_fraction']:.1f}%, "
        f"mean rate {summary['mean_rate_bps'] / 1e6:.2f} Mbit/s, "
        f"teleports {summary['teleports']}, collisions {summary['collisions']} -> {args.out}"
    )
    return 0


# --- render -------------------------------------------------------------------------------------


def _add_render(p: argparse.ArgumentParser) -> None:
    _scenario_argument(p)
    p.add_argument("--vehicle", required=True, help="id of the vehicle whose cameras are drawn")
    p.add_argument("--duration-s", type=number_arg(0, MAX_DRIVE_S, "simulated seconds", lo_open=True), default=60.0,
                   help="simulated seconds (default 60)")
    p.add_argument("--out", type=Path, required=True, help="output folder (step_*.png, run.mp4)")
    _overwrite_argument(p)
    p.add_argument("--every-n", type=integer_arg(1, 100_000, "a whole number of steps"), default=1,
                   help="draw every n-th step (default 1)")
    p.add_argument("--seed", type=seed_arg, default=0, help="simulation seed (default 0)")
    p.add_argument("--scale", type=integer_arg(1, 8, "a whole factor"), default=3,
                   help="camera tiles enlarged this many times (1 .. 8, default 3)")


def _run_render(args) -> int:
    from crchfl_sumo.vision.mosaic import render_vehicle

    with _output_folder(args, "render"):
        result = render_vehicle(args.scenario, args.vehicle, args.duration_s, args.out, args.every_n, args.seed,
                                args.scale)
    print(f"{len(result.png_paths)} mosaics of {args.vehicle} over {result.frames_seen} steps -> {args.out}")
    return 0


# --- dataset ------------------------------------------------------------------------------------


def _add_dataset(p: argparse.ArgumentParser) -> None:
    _scenario_argument(p)
    p.add_argument("--out", type=Path, required=True, help="data set folder (rerun the same command to resume)")
    p.add_argument("--seed", type=seed_arg, default=None, help="seed (overrides the config's; 0 .. 2**31 - 1)")
    p.add_argument("--config", type=Path, default=None,
                   help="TOML: seed, [dataset], [raster], [world], [expert] (docs/dataset.md)")


def _run_dataset(args) -> int:
    from crchfl_sumo.data.generation import run_dataset_command

    with _output_folder(args, "dataset", resumable=True):
        with ProgressBars("sample") as bars:
            manifest = run_dataset_command(args.scenario, args.out, args.seed, args.config, bars)
    print(
        f"{manifest.scenario}: {len(manifest.shards)} shards, {manifest.samples} samples, "
        f"{manifest.png_bytes_per_sample:.0f} PNG bytes/sample -> {args.out}"
    )
    return 0


def _add_dataset_stats(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="data set folder (with manifest.json)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: DIR)")
    _overwrite_argument(p)


def _run_dataset_stats(args) -> int:
    from crchfl_sumo.data.stats import write_dataset_stats

    if not args.dir.is_dir():
        raise CrchflError(f"{args.dir}: no data set folder there; give the folder `crchfl-sumo dataset` wrote")
    beside = args.out is None or args.out.resolve() == args.dir.resolve()
    with _output_folder(args, "dataset-stats", out=args.dir if args.out is None else args.out,
                       beside=("dataset",) if beside else ()):
        stats = write_dataset_stats(args.dir, args.out)
        files = ", ".join(f"{k}: {v}" for k, v in stats["files"].items())
    print(f"{stats['samples']} samples; steer classes (train) {stats['train']['steer_class_counts']}; {files}")
    return 0


# --- train --------------------------------------------------------------------------------------


def _add_train(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="data set folder (manifest.json and shards)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: metrics.jsonl, checkpoint.pt (checkpoint.prev.pt: the epoch before)")
    _overwrite_argument(p)
    p.add_argument("--epochs", type=integer_arg(1, MAX_EPOCHS, "a number of epochs"), default=10,
                   help="epochs over all training shards (default 10)")
    p.add_argument("--size", choices=("compact", "paper"), default="compact", help="model size (default compact)")
    p.add_argument("--arch", choices=ARCHS, default="cil",
                   help="cil (default: normalised, one steer head per route command) or paper (the paper's network)")
    p.add_argument("--seed", type=seed_arg, default=0, help="seed of initialisation and shuffling (default 0)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto", help="default: cuda if present")
    p.add_argument("--deterministic", action="store_true", help="deterministic algorithms (bit-exact reruns)")
    p.add_argument("--precision", choices=PRECISIONS, default=TrainConfig.precision,
                   help=f"forward pass in float32, under bfloat16 autocast, or auto: bf16 where the device has "
                   f"bfloat16 arithmetic, else fp32 (default {TrainConfig.precision}; docs/model.md measures both)")
    p.add_argument("--resume", action="store_true",
                   help="continue the training in --out after its last checkpointed epoch (the same command line; "
                   "--epochs may be raised, and --precision named to continue in the precision the epochs trained in)")
    p.add_argument("--red-weight", type=number_arg(1, MAX_RED_WEIGHT, "a draw multiplier (1 = off)"),
                   default=TrainConfig.red_weight,
                   help="draw samples at a red or yellow signal within --red-window-m this many times as often "
                   f"(default {TrainConfig.red_weight:g}: off; needs a data set of format 5)")
    p.add_argument("--red-window-m", type=number_arg(0, MAX_RED_WINDOW_M, "metres before a stop line", lo_open=True),
                   default=TrainConfig.red_window_m,
                   help=f"metres before a stop line that --red-weight covers (default {TrainConfig.red_window_m:g})")


def _run_train(args) -> int:
    from crchfl_sumo.learning.centralized import train_command

    # --resume --epochs N continues to N; --precision may change too (the checkpoint checks it against the
    # precision its epochs trained in), which folders marked while it was kept still allow
    config = TrainConfig(device=args.device, deterministic=args.deterministic, precision=args.precision,
                         red_weight=args.red_weight, red_window_m=args.red_window_m)  # refused before any file
    if args.red_weight == TrainConfig.red_weight:  # off: a folder trained before these options existed still resumes
        del args.red_weight, args.red_window_m
    with _output_folder(args, "train", extendable=("epochs", "precision"), formerly_kept=(("precision", PRECISIONS),)):
        with ProgressBars("sample") as bars:
            last = train_command(args.dataset, args.out, args.epochs, args.size, args.arch, config, args.seed,
                                 resume=args.resume, overwrite=args.overwrite, progress=bars)
        straight = last["always_straight"]
    print(
        f"epoch {last['epoch']}: test loss {last['loss']:.4f}, accuracy {last['accuracy']:.3f} "
        f"(always straight {straight['accuracy']:.3f}), balanced accuracy {last['balanced_accuracy']:.3f} "
        f"(always straight {straight['balanced_accuracy']:.3f}) -> {args.out}"
    )
    return 0


# --- drive --------------------------------------------------------------------------------------


def _add_drive(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="checkpoint.pt of a trained model, or 'reference' for the scripted route driver")
    p.add_argument("--route", required=True,
                   help="named route (scenarios/drive_routes.toml) or edge ids separated by commas")
    p.add_argument("--scenario", default=None, help="built-in scenario or .sumocfg (named routes bring their own)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    _overwrite_argument(p)
    p.add_argument("--seed", type=seed_arg, default=0, help="simulation seed (default 0)")
    p.add_argument("--max-s", type=number_arg(0, MAX_DRIVE_S, "simulated seconds", lo_open=True), default=150.0,
                   help="simulated seconds at most (default 150)")
    p.add_argument("--warmup-s", type=number_arg(0, MAX_DRIVE_S, "simulated seconds"), default=20.0,
                   help="traffic runs this long before the ego starts (default 20)")
    p.add_argument("--no-video", action="store_true", help="skip drive.mp4")
    _decoding_arguments(p)


def _decoding_arguments(p: argparse.ArgumentParser) -> None:
    """How a model's outputs become actions: --steer-decoding and --brake-gain."""
    from crchfl_sumo.learning.settings import DEFAULT_BRAKE_GAIN, DEFAULT_STEER_DECODING, STEER_DECODINGS

    p.add_argument("--steer-decoding", choices=STEER_DECODINGS, default=DEFAULT_STEER_DECODING,
                   help="a model's steer: 'argmax' (the paper's DAC: the likeliest class's value), 'expected' "
                        "(the class values weighted by probability) or 'auto' (argmax for the paper's 7 classes, "
                        f"expected for a finer steer head); default {DEFAULT_STEER_DECODING}")
    p.add_argument("--brake-gain", type=number_arg(0, 100, "a gain", lo_open=True), default=DEFAULT_BRAKE_GAIN,
                   help="a target-speed model reaches a lower target in its speed horizon / this "
                        f"(1 = as the labels were made; default {DEFAULT_BRAKE_GAIN:g})")


def _run_drive(args) -> int:
    from crchfl_sumo.driving.drive import DriveConfig
    from crchfl_sumo.driving.route_drive import drive_route

    with _output_folder(args, "drive"):
        m = drive_route(
            None if args.model == "reference" else args.model, args.scenario, args.route, args.out,
            args.seed, args.max_s, DriveConfig(warmup_s=args.warmup_s), video=not args.no_video,
            steer_decoding=args.steer_decoding, brake_gain=args.brake_gain,
        )
    print(
        f"{m['route']}: {m['end_reason']}, completion {100 * m['completion']:.0f}%, collisions {m['collisions']}, "
        f"lane departures {m['lane_departures']}, off-road {m['off_road_events']}, "
        f"red lights {m['red_light_violations']}, mean speed {m['mean_speed_mps']:.1f} m/s -> {args.out}"
    )
    return 0


def _add_drive_compare(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", type=Path, help="folders written by `crchfl-sumo drive` (same route)")
    p.add_argument("--labels", nargs="+", default=None, help="one label per folder (default: folder names)")
    p.add_argument("--out", type=Path, required=True, help="output PNG")
    _overwrite_argument(p, file=True)


def _run_drive_compare(args) -> int:
    from crchfl_sumo.core.outputs import prepare_output_file
    from crchfl_sumo.driving.plots import compare_runs

    prepare_output_file(args.out, f"{args.command} --out", replace=args.overwrite)
    print(f"-> {compare_runs(args.runs, args.labels, args.out)}")
    return 0


def _add_drive_bench(p: argparse.ArgumentParser) -> None:
    from crchfl_sumo.driving.bench_tasks import TASK_NAMES

    p.add_argument("model", help="checkpoint.pt of a trained model, or 'reference' for the scripted route driver")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    _overwrite_argument(p)
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


def _run_drive_bench(args) -> int:
    from crchfl_sumo.driving.bench import BenchConfig, results_table, run_benchmark
    from crchfl_sumo.driving.bench_tasks import TaskConfig

    with _output_folder(args, "drive-bench"):
        towns, tasks = _comma_list(args.towns), _comma_list(args.tasks)
        turns = _comma_list(args.navigation_turns)
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


def _add_dagger(p: argparse.ArgumentParser) -> None:
    from crchfl_sumo.driving.bench_tasks import TASK_NAMES
    from crchfl_sumo.driving.dagger_settings import FINE_TUNE_LEARNING_RATE, MAX_ITERATIONS, DaggerConfig

    p.add_argument("model", help="checkpoint.pt of a trained model (crchfl-sumo train)")
    p.add_argument("dataset", type=Path, help="the data set it was trained on (manifest.json and shards)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: iteration-K/ (expert_samples.npz, metrics.jsonl, checkpoint.pt), "
                   "checkpoint.pt (the last iteration's model), summary.json")
    _overwrite_argument(p)
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
    p.add_argument("--all-states", action="store_true",
                   help="label every visited state (default: only those where the expert brakes harder or steers "
                   "elsewhere than the model)")
    p.add_argument("--jobs", type=integer_arg(1, MAX_JOBS, "a number of processes"), default=1,
                   help="drives run at a time, each group in its own process (default 1)")
    p.add_argument("--resume", action="store_true",
                   help="continue in --out after its last finished epoch (the same command line; --iterations may be "
                   "raised). The same command line again also continues")


def _run_dagger(args) -> int:
    from crchfl_sumo.driving.dagger import dagger_command
    from crchfl_sumo.driving.dagger_settings import DaggerConfig

    with _output_folder(args, "dagger", extendable=("iterations",)):  # --resume --iterations N goes on to N
        config = DaggerConfig(tasks=_comma_list(args.tasks), episodes=args.episodes, seed=args.route_seed,
                              corrections_only=not args.all_states)
        records = dagger_command(args.model, args.dataset, args.out, _comma_list(args.towns), config,
                                 args.iterations, args.epochs, args.seed, args.jobs, args.learning_rate, args.overwrite)
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


# --- run ----------------------------------------------------------------------------------------


def _add_run(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="run config TOML, or a built-in: crchfl, hfl, sfl")
    p.add_argument("--out", type=Path, required=True, help="results folder")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    _backend_arguments(p)


def _backend_arguments(
    p: argparse.ArgumentParser,
    what: str = "where training runs: in this process (local) or as Ray tasks; overrides [backend] kind",
) -> None:
    p.add_argument("--backend", choices=("local", "ray"), default=None, help=what)
    p.add_argument("--address", default=None,
                   help="Ray cluster to join: 'auto' (this machine's) or HOST:PORT; default: start a local Ray runtime")


def _run_run(args) -> int:
    from crchfl_sumo.driving.vehicle_dagger import labeller_factory
    from crchfl_sumo.federation.run import run_command

    with _output_folder(args, "run", resumable=True):
        with ProgressBars("step") as bars:  # the postfix: round, GB used / budget, loss, accuracy
            summary = run_command(args.config, args.out, args.resume, bars, args.backend, args.address,
                                  labeller_factory=labeller_factory)
    print(json.dumps(summary, indent=2))
    return 0


# --- sweep --------------------------------------------------------------------------------------


def _add_sweep(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="base run config TOML, or a built-in: crchfl, hfl, sfl")
    p.add_argument("--param", action="append", default=[], metavar="PATH=V1,V2,...",
                   help="a dotted config key and its values, e.g. sumo.scale=0.5,1,2 (repeat for a grid)")
    p.add_argument("--out", type=Path, required=True, help="sweep folder (rerun the same command to resume)")
    p.add_argument("--seeds", type=integer_arg(1, 100, "a number of seeds a point"), default=1,
                   help="runs a point, federation.seed the config's +0, +1, ...: the table gives each point's "
                   "means with their 95 %% intervals (default 1: one run a point)")
    _backend_arguments(p)


def _run_sweep(args) -> int:
    from crchfl_sumo.studies.sweep import sweep_command

    # checks --out after --param
    rows = sweep_command(args.config, args.param, args.out, args.backend, args.address, args.seeds)
    print((args.out / RESULTS_MD_FILE).read_text(encoding="utf-8"), end="")
    print(f"{len(rows)} runs -> {args.out}")
    return 0


# --- mobility-study -----------------------------------------------------------------------------


def _add_mobility_study(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="the quick preset: within 15 minutes on 2 cores (docs/sweep.md)")
    p.add_argument("--config", type=Path, default=None, help="a study preset TOML instead of the built-in one")
    p.add_argument("--out", type=Path, required=True, help="study folder (rerun the same command to resume)")
    p.add_argument("--jobs", type=integer_arg(0, MAX_JOBS, "a number of processes (0: all CPUs)"), default=0,
                   help="runs at a time, each in its own process (default 0: all CPUs)")
    _backend_arguments(p)


def _run_mobility_study(args) -> int:
    from crchfl_sumo.studies.mobility_study import mobility_study_command

    rows = mobility_study_command(args.quick, args.out, args.config, args.jobs, args.backend, args.address)
    print((args.out / RESULTS_MD_FILE).read_text(encoding="utf-8"), end="")
    seeds = max((r["seeds"] for r in rows), default=0)
    print(f"{len({r['point'] for r in rows})} points x {seeds} seed(s) -> {args.out}")
    return 0


# --- calibrate ----------------------------------------------------------------------------------


def _add_calibrate(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("calibration.toml"),
                   help="calibration file to write; it is a valid `plan --config` (default calibration.toml)")
    _overwrite_argument(p, file=True)
    p.add_argument("--seed", type=seed_arg, default=0, help="seed of the pilot data, models and shuffling (default 0)")
    p.add_argument("--scenario", default="paper", help="scenario the pilot data set is generated in (default paper)")
    p.add_argument("--dataset", type=Path, default=None, help="use this data set instead of generating OUT.data/")


def _run_calibrate(args) -> int:
    from crchfl_sumo.core.outputs import prepare_output_file
    from crchfl_sumo.planning.calibration import calibrate_command

    prepare_output_file(args.out, f"{args.command} --out", replace=args.overwrite)
    pilot_data = args.out.with_name(args.out.name + ".data")  # generated (and reused) beside the file
    with _output_folder(args, "dataset", out=pilot_data, resumable=True) if args.dataset is None else nullcontext():
        fit = calibrate_command(args.out, args.seed, args.scenario, args.dataset)
    print(f"alpha {fit.alpha:.3f}  gamma {fit.gamma:.3f}  d {fit.d:.2f} -> {args.out}")
    return 0


# --- plan ---------------------------------------------------------------------------------------


def _add_plan(p: argparse.ArgumentParser) -> None:
    from crchfl_sumo.accounting.ledger import MAX_SIZE
    from crchfl_sumo.planning.settings import MAX_INTERVAL

    p.add_argument("--budget-gb", type=number_arg(0, MAX_SIZE, "a budget in GB", lo_open=True), default=None,
                   help="communication budget [GB, 1 GB = 1024**3 B]; overrides [ledger] budget_gb (default 20)")
    p.add_argument("--config", type=Path, default=None, help="TOML file; its [ledger] and [allocation] tables are read")
    p.add_argument("--json", action="store_true", help="print the plan as JSON")
    p.add_argument("--fix-edge-interval", type=integer_arg(2, MAX_INTERVAL, "an edge interval"), default=None,
                   metavar="N",
                   help="fix edge_interval (the paper's ablation: 2, 3, 4)")
    p.add_argument("--scenario", default=None,
                   help="measure the wireless rate on this scenario's mobility (its data vehicles' edge links) "
                        "instead of taking [allocation] wireless_rate_bps")
    p.add_argument("--seed", type=seed_arg, default=0, help="SUMO and channel seed of --scenario (default 0)")


def _run_plan(args) -> int:
    from crchfl_sumo.planning.plan_command import plan_command

    out = plan_command(args.budget_gb, args.config, args.json, args.fix_edge_interval, args.scenario, args.seed)
    print(json.dumps(out, indent=2) if args.json else out)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
        # Before any command imports torch (OpenMP reads it once); --jobs 0 is a part per CPU.
        choose_wait_policy(parts=getattr(args, "jobs", 1) or available_cpus())
        settle_native_libraries()  # OpenCV's threads, numpy's hugepages; spawned parts inherit them
        return int(args.run(args) or 0)
    except CrchflError as exc:
        print(f"crchfl-sumo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("crchfl-sumo: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like: not an error
        sys.stdout = open(os.devnull, "w")
        return 0


if __name__ == "__main__":
    sys.exit(main())
