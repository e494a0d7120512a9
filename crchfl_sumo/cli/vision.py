"""The subcommand whose work lives in vision/: render."""

from __future__ import annotations

import argparse
from pathlib import Path

from crchfl_sumo.cli.arguments import output_folder, overwrite_argument, scenario_argument
from crchfl_sumo.core.numbers import MAX_DRIVE_S, integer_arg, number_arg, seed_arg


def add_render(p: argparse.ArgumentParser) -> None:
    scenario_argument(p)
    p.add_argument("--vehicle", required=True, help="id of the vehicle whose cameras are drawn")
    p.add_argument("--duration-s", type=number_arg(0, MAX_DRIVE_S, "simulated seconds", lo_open=True), default=60.0,
                   help="simulated seconds (default 60)")
    p.add_argument("--out", type=Path, required=True, help="output folder (step_*.png, run.mp4)")
    overwrite_argument(p)
    p.add_argument("--every-n", type=integer_arg(1, 100_000, "a whole number of steps"), default=1,
                   help="draw every n-th step (default 1)")
    p.add_argument("--seed", type=seed_arg, default=0, help="simulation seed (default 0)")
    p.add_argument("--scale", type=integer_arg(1, 8, "a whole factor"), default=3,
                   help="camera tiles enlarged this many times (1 .. 8, default 3)")


def run_render(args) -> int:
    from crchfl_sumo.vision.mosaic import render_vehicle

    with output_folder(args, "render"):
        result = render_vehicle(args.scenario, args.vehicle, args.duration_s, args.out, args.every_n, args.seed,
                                args.scale)
    print(f"{len(result.png_paths)} mosaics of {args.vehicle} over {result.frames_seen} steps -> {args.out}")
    return 0
