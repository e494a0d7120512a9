"""The subcommands whose work lives in data/: dataset and dataset-stats."""

from __future__ import annotations

import argparse
from pathlib import Path

from crchfl_sumo.cli.arguments import (
    comma_list, output_folder, overwrite_argument, scenario_argument, sumo_output_argument,
)
from crchfl_sumo.cli.progress_bars import ProgressBars
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import seed_arg


def add_dataset(p: argparse.ArgumentParser) -> None:
    scenario_argument(p)
    p.add_argument("--out", type=Path, required=True, help="data set folder (rerun the same command to resume)")
    p.add_argument("--seed", type=seed_arg, default=None, help="seed (overrides the config's; 0 .. 2**31 - 1)")
    p.add_argument("--config", type=Path, default=None,
                   help="TOML: seed, [dataset], [raster], [world], [expert] (docs/dataset.md)")
    sumo_output_argument(p, "the data set's simulation run")


def run_dataset(args) -> int:
    from crchfl_sumo.data.generation import run_dataset_command
    from crchfl_sumo.sumo.outputs import sumo_output_files

    outputs = comma_list(args.sumo_output)
    sumo_output_files(outputs, args.out)  # an unknown name is refused before --out is touched
    with output_folder(args, "dataset", resumable=True):
        with ProgressBars("sample") as bars:
            manifest = run_dataset_command(args.scenario, args.out, args.seed, args.config, bars, outputs)
    print(
        f"{manifest.scenario}: {len(manifest.shards)} shards, {manifest.samples} samples, "
        f"{manifest.png_bytes_per_sample:.0f} PNG bytes/sample -> {args.out}"
    )
    return 0


def add_dataset_stats(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="data set folder (with manifest.json)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: DIR)")
    p.add_argument("--scenario", default=None,
                   help="the scenario whose junctions the turn commands are counted at (default: the one the "
                        "manifest names; give it for a folder scenario)")
    overwrite_argument(p)


def run_dataset_stats(args) -> int:
    from crchfl_sumo.data.stats import write_dataset_stats

    if not args.dir.is_dir():
        raise CrchflError(f"{args.dir}: no data set folder there; give the folder `crchfl-sumo dataset` wrote")
    if args.scenario is not None:
        from crchfl_sumo.sumo.scenario import load_scenario

        load_scenario(args.scenario)  # an unknown one is refused before any folder is written
    beside = args.out is None or args.out.resolve() == args.dir.resolve()
    with output_folder(args, "dataset-stats", out=args.dir if args.out is None else args.out,
                       beside=("dataset",) if beside else ()):
        stats = write_dataset_stats(args.dir, args.out, args.scenario)
        files = ", ".join(f"{k}: {v}" for k, v in stats["files"].items())
    print(f"{stats['samples']} samples; steer classes (train) {stats['train']['steer_class_counts']}; {files}")
    junctions = stats["junction_commands"]
    if junctions is not None:
        missing = junctions["missing"]
        shown = ", ".join(missing[:12]) + (", ..." if len(missing) > 12 else "")
        print(f"junction turn commands (train): {len(missing)} of the {junctions['offered']} the junctions offer "
              f"have no sample" + (f": {shown}" if missing else ""))
    return 0
