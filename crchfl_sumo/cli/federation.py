"""The subcommand whose work lives in federation/: run."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from crchfl_sumo.cli.arguments import backend_arguments, output_folder
from crchfl_sumo.cli.progress_bars import ProgressBars


def add_run(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="run config TOML, or a built-in: crchfl, hfl, sfl")
    p.add_argument("--out", type=Path, required=True, help="results folder")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    backend_arguments(p)


def run_run(args) -> int:
    from crchfl_sumo.driving.vehicle_dagger import labeller_factory
    from crchfl_sumo.federation.run import run_command

    with output_folder(args, "run", resumable=True):
        with ProgressBars("step") as bars:  # the postfix: round, GB used / budget, loss, accuracy
            summary = run_command(args.config, args.out, args.resume, bars, args.backend, args.address,
                                  labeller_factory=labeller_factory)
    print(json.dumps(summary, indent=2))
    return 0
