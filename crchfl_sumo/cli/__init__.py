"""`crchfl-sumo <subcommand>`: parses arguments, calls the library, prints results.

Thin on purpose: every subcommand is a pair (add its arguments, run it) in the module of this package
named after the subpackage its work lives in (cli/driving.py: drive, drive-compare, drive-bench, dagger);
arguments.py holds what they share, progress_bars.py draws the library's progress. This module builds
the parser from the table in _commands and runs a command line. A CrchflError is printed as one line on
stderr with exit status 2; anything else is a bug and keeps its traceback.

May import: every subpackage. No library module imports the command line.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from crchfl_sumo import __version__
from crchfl_sumo.cli import data, driving, federation, learning, planning, studies, vision
from crchfl_sumo.core.cpus import available_cpus, choose_wait_policy, settle_native_libraries
from crchfl_sumo.core.errors import CrchflError


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
         studies.add_reproduce, studies.run_reproduce),
        ("report", "rebuild the figures, report.md and summary.json of a reproduce results folder",
         studies.add_report, studies.run_report),
        ("simulate", "run a scenario with edge association and link rates; write trace, summary, plots",
         studies.add_simulate, studies.run_simulate),
        ("render", "draw one vehicle's four camera images and a top-down map: PNG per step and an MP4",
         vision.add_render, vision.run_render),
        ("dataset", "generate the driving data set (per-vehicle HDF5 shards); rerun the same command to resume",
         data.add_dataset, data.run_dataset),
        ("dataset-stats", "label statistics, summary figure and example mosaic of a data set",
         data.add_dataset_stats, data.run_dataset_stats),
        ("train", "centralized training on all shards of a data set (the federated schemes' upper bound)",
         learning.add_train, learning.run_train),
        ("drive", "a model (or 'reference') drives an ego along a route in SUMO: metrics, map, action frames, video",
         driving.add_drive, driving.run_drive),
        ("drive-compare", "several drives of one route side by side (the paper's Fig. 5)",
         driving.add_drive_compare, driving.run_drive_compare),
        ("drive-bench", "closed-loop benchmark of a model or 'reference': CoRL2017 tasks, success, driving score",
         driving.add_drive_bench, driving.run_drive_bench),
        ("dagger", "DAgger: a model drives, the route expert labels what it sees, the model is fine-tuned on it",
         driving.add_dagger, driving.run_dagger),
        ("run", "federated training (CRCHFL, HFL or SFL) on SUMO's clock: metrics, ledger, checkpoints, summary",
         federation.add_run, federation.run_run),
        ("sweep", "a grid of runs over config settings (mobility studies): a table and plots against each parameter",
         studies.add_sweep, studies.run_sweep),
        ("mobility-study", "the built-in mobility study: speed, density, edge sites, handover policy one at a time; "
         "a table and a figure per factor", studies.add_mobility_study, studies.run_mobility_study),
        ("calibrate", "fit alpha, gamma, d of problem P from short pilot runs (docs/calibration.md)",
         planning.add_calibrate, planning.run_calibrate),
        ("plan", "solve the resource allocation (problem P) for a communication budget",
         planning.add_plan, planning.run_plan),
    ]


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

