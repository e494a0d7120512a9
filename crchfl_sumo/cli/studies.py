"""The subcommands whose work lives in studies/: reproduce, report, simulate, sweep and mobility-study."""

from __future__ import annotations

import argparse
from pathlib import Path

from crchfl_sumo.cli.arguments import (
    backend_arguments, comma_list, output_folder, overwrite_argument, scenario_names, sumo_output_argument,
)
from crchfl_sumo.cli.progress_bars import ProgressBars
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_JOBS, MAX_SIMULATED_S, integer_arg, number_arg, seed_arg
from crchfl_sumo.core.result_files import RESULTS_MD_FILE


def add_reproduce(p: argparse.ArgumentParser) -> None:
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
    backend_arguments(p, "where the parts run: processes of this machine (local, --jobs at a time) or Ray tasks "
                          "of one CPU each (every node must see --out at the same path)")


def run_reproduce(args) -> int:
    from crchfl_sumo.studies.report import format_summary
    from crchfl_sumo.studies.reproduce import reproduce_command

    with ProgressBars("part") as bars:
        out, summary = reproduce_command(args.quick, args.out, args.seeds, args.resume, args.config, bars, args.jobs,
                                         args.backend, args.address, args.scenario)
    print(format_summary(summary, out))
    return 0


def add_report(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="results folder of `crchfl-sumo reproduce`")


def run_report(args) -> int:
    from crchfl_sumo.core.outputs import check_writable
    from crchfl_sumo.studies.report import format_summary, report_command

    check_writable(args.dir, f"report {args.dir}")  # the figures and report.md are rewritten there
    print(format_summary(report_command(args.dir), args.dir))
    return 0


def add_simulate(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", default=None,
                   help=f"built-in scenario name ({scenario_names()}), a folder laid out as one or a .sumocfg path; "
                   "or none, with --net")
    p.add_argument("--net", type=Path, default=None,
                   help="a bare SUMO network (.net.xml or .net.xml.gz) instead of a scenario: OUT/NAME.sumocfg is "
                   "written for it")
    p.add_argument("--routes", default="", help="with --net: route files, separated by commas")
    p.add_argument("--duration-s", type=number_arg(0, MAX_SIMULATED_S, "simulated seconds", lo_open=True),
                   default=None,
                   help="simulated seconds (default: the .sumocfg's <end> less <begin>; without an end 300)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    overwrite_argument(p)
    p.add_argument("--seed", type=seed_arg, default=None, help="seed (overrides the config's; 0 .. 2**31 - 1)")
    p.add_argument("--config", type=Path, default=None,
                   help="TOML with seed, [[edge_sites]], [channel], [mobility] (docs/links.md)")
    sumo_output_argument(p, "the simulation")


def run_simulate(args) -> int:
    from crchfl_sumo.studies.simulate import run_simulate_command
    from crchfl_sumo.sumo.outputs import sumo_output_files

    outputs, routes = comma_list(args.sumo_output), tuple(Path(r) for r in comma_list(args.routes))
    sumo_output_files(outputs, args.out)  # an unknown name is refused before --out is touched
    if (args.scenario is None) == (args.net is None):
        raise CrchflError("simulate: give a SCENARIO or --net NET.net.xml (with --routes R1,R2), not both or neither")
    if routes and args.net is None:
        raise CrchflError("simulate --routes: route files go with --net; a scenario names its own")
    with output_folder(args, "simulate"):
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


def add_sweep(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="base run config TOML, or a built-in: crchfl, hfl, sfl")
    p.add_argument("--param", action="append", default=[], metavar="PATH=V1,V2,...",
                   help="a dotted config key and its values, e.g. sumo.scale=0.5,1,2 (repeat for a grid)")
    p.add_argument("--out", type=Path, required=True, help="sweep folder (rerun the same command to resume)")
    p.add_argument("--seeds", type=integer_arg(1, 100, "a number of seeds a point"), default=1,
                   help="runs a point, federation.seed the config's +0, +1, ...: the table gives each point's "
                   "means with their 95 %% intervals (default 1: one run a point)")
    backend_arguments(p)


def run_sweep(args) -> int:
    from crchfl_sumo.studies.sweep import sweep_command

    # checks --out after --param
    rows = sweep_command(args.config, args.param, args.out, args.backend, args.address, args.seeds)
    print((args.out / RESULTS_MD_FILE).read_text(encoding="utf-8"), end="")
    print(f"{len(rows)} runs -> {args.out}")
    return 0


def add_mobility_study(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true",
                   help="the quick preset: within 15 minutes on 2 cores (docs/sweep.md)")
    p.add_argument("--config", type=Path, default=None, help="a study preset TOML instead of the built-in one")
    p.add_argument("--scenario", default=None,
                   help="run the study in this scenario (a built-in name, a folder or a .sumocfg; a plain .sumocfg "
                   "gets its data vehicles added): the same samples per vehicle, the benchmark driven there, the "
                   "factors that place the preset scenario's sites left out")
    p.add_argument("--out", type=Path, required=True, help="study folder (rerun the same command to resume)")
    p.add_argument("--jobs", type=integer_arg(0, MAX_JOBS, "a number of processes (0: all CPUs)"), default=0,
                   help="runs at a time, each in its own process (default 0: all CPUs)")
    backend_arguments(p)


def run_mobility_study(args) -> int:
    from crchfl_sumo.studies.mobility_study import mobility_study_command

    rows = mobility_study_command(args.quick, args.out, args.config, args.jobs, args.backend, args.address,
                                  args.scenario)
    print((args.out / RESULTS_MD_FILE).read_text(encoding="utf-8"), end="")
    seeds = max((r["seeds"] for r in rows), default=0)
    print(f"{len({r['point'] for r in rows})} points x {seeds} seed(s) -> {args.out}")
    return 0
