"""The subcommands whose work lives in planning/: calibrate and plan."""

from __future__ import annotations

import argparse
import json
from contextlib import nullcontext
from pathlib import Path

from crchfl_sumo.cli.arguments import output_folder, overwrite_argument
from crchfl_sumo.core.numbers import integer_arg, number_arg, seed_arg


def add_calibrate(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("calibration.toml"),
                   help="calibration file to write; it is a valid `plan --config` (default calibration.toml)")
    overwrite_argument(p, file=True)
    p.add_argument("--seed", type=seed_arg, default=0, help="seed of the pilot data, models and shuffling (default 0)")
    p.add_argument("--scenario", default="paper", help="scenario the pilot data set is generated in (default paper)")
    p.add_argument("--dataset", type=Path, default=None, help="use this data set instead of generating OUT.data/")


def run_calibrate(args) -> int:
    from crchfl_sumo.core.outputs import prepare_output_file
    from crchfl_sumo.planning.calibration import calibrate_command

    prepare_output_file(args.out, f"{args.command} --out", replace=args.overwrite)
    pilot_data = args.out.with_name(args.out.name + ".data")  # generated (and reused) beside the file
    with output_folder(args, "dataset", out=pilot_data, resumable=True) if args.dataset is None else nullcontext():
        fit = calibrate_command(args.out, args.seed, args.scenario, args.dataset)
    print(f"alpha {fit.alpha:.3f}  gamma {fit.gamma:.3f}  d {fit.d:.2f} -> {args.out}")
    return 0


def add_plan(p: argparse.ArgumentParser) -> None:
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


def run_plan(args) -> int:
    from crchfl_sumo.planning.plan_command import plan_command

    out = plan_command(args.budget_gb, args.config, args.json, args.fix_edge_interval, args.scenario, args.seed)
    print(json.dumps(out, indent=2) if args.json else out)
    return 0
