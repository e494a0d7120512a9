"""Benchmark: our frame extraction and the `simulate` command's step vs plain `sumo`, and vs TraCI.

Builds a signalised grid with netgenerate and a demand that keeps at least 500
vehicles on the road (randomTrips, fixed seed), then in one run times:
  (a) the `sumo` binary alone, same options and steps (the floor),
  (b) crchfl_sumo.sumo.simulation.Simulation over libsumo, reading a Frame every step,
  (s) what `crchfl-sumo simulate` computes per step (studies.simulate.simulate):
      a Frame of every vehicle, association and rates to the edge sites placed
      automatically at the default 300 m coverage, the trace's columns kept,
  (c) the same Simulation class over TraCI (a socket per call batch).
Prints wall and CPU times (CPU time is the steadier figure on a shared
machine), vehicles per step, the ratios b/a and c/b (target >= 5), and
`simulate/sumo = X.XX`: s/a in CPU time, the median of the ratios of runs
taken in turn (target <= 1.5). (b) is run four ways: every vehicle in the
frame with the signal ahead read for all of them, or for five watched
vehicles; and frames that hold only five focus vehicles, alone (as the
federation's SUMO clock reads its federated vehicles) or with every vehicle
within 100 m of one (as data generation reads the sampled vehicles and what
their cameras may draw). (sf) is the frames alone as simulate reads them (no
lanes, signals ahead or signal states); s - sf is the link model's share.
`--runs a,s` times only those.

    python tools/bench_sim.py [--steps 1200] [--grid 10] [--repeat 3] [--runs a,b,b5,f5,n5,sf,s,c]
"""

from __future__ import annotations

import argparse
import math
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from crchfl_sumo.studies.simulate import SimulateConfig, simulate
from crchfl_sumo.sumo.installation import sumo_binary, sumo_tool_script
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation


def build_scenario(folder: Path, grid: int, period_s: float, end_s: float) -> Path:
    net = folder / "grid.net.xml"
    subprocess.run(
        [
            sumo_binary("netgenerate"),
            "--grid",
            f"--grid.number={grid}",
            "--grid.length=150",
            "--default-junction-type=traffic_light",
            "-o",
            str(net),
        ],
        check=True,
        capture_output=True,
    )
    random_trips = sumo_tool_script("randomTrips.py")
    subprocess.run(
        [
            sys.executable,
            str(random_trips),
            "-n",
            str(net),
            "-o",
            str(folder / "trips.xml"),
            "-r",
            str(folder / "routes.rou.xml"),
            "-e",
            str(end_s),
            "-p",
            str(period_s),
            "--min-distance=800",
            "--seed=42",
            "--validate",
        ],
        check=True,
        capture_output=True,
    )
    cfg = folder / "bench.sumocfg"
    cfg.write_text(
        """<configuration>
  <input><net-file value="grid.net.xml"/><route-files value="routes.rou.xml"/></input>
  <time><step-length value="0.25"/></time>
</configuration>
"""
    )
    return cfg


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def time_plain_sumo(command: list[str], steps: int, step_length_s: float) -> tuple[float, float]:
    """(wall s, CPU s) of the sumo binary alone."""
    wall, cpu = time.perf_counter(), _children_cpu_s()
    subprocess.run([*command, f"--end={steps * step_length_s}"], check=True, capture_output=True)
    return time.perf_counter() - wall, _children_cpu_s() - cpu


def time_frames(scenario, steps: int, **options) -> tuple[float, float, float]:
    """(wall s, CPU s of this process and its children, mean vehicles per frame) of a Frame per step."""
    # Start-up included, as it is in the plain sumo run.
    wall, cpu = time.perf_counter(), time.process_time() + _children_cpu_s()
    with Simulation(scenario, seed=1, **options) as sim:
        counts = [len(sim.step()) for _ in range(steps)]
    return time.perf_counter() - wall, time.process_time() + _children_cpu_s() - cpu, statistics.mean(counts)


def time_simulate(scenario, steps: int) -> tuple[float, float, float]:
    """(wall s, CPU s, mean vehicles per step) of the simulate command's run: frames, association, rates, trace."""
    wall, cpu = time.perf_counter(), time.process_time()
    trace = simulate(scenario, steps * scenario.step_length_s, SimulateConfig(seed=1))
    return time.perf_counter() - wall, time.process_time() - cpu, len(trace.t_s) / steps


LABELS = {
    "a": "(a) sumo binary alone",
    "b": "(b) libsumo, Frame, signal ahead for all",
    "b5": "(b5) libsumo, Frame, signal ahead for 5",
    "f5": "(f5) libsumo, Frame of 5 focus vehicles",
    "n5": "(n5) libsumo, Frame of 5 + 100 m, signal 5",
    "sf": "(sf) libsumo, Frame as simulate reads it",
    "s": "(s) simulate: Frame + association + rates",
    "c": "(c) TraCI, Frame, signal ahead for all",
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1200, help="steps of 0.25 s to time")
    parser.add_argument("--grid", type=int, default=10, help="junctions per side of the grid")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each, median reported")
    parser.add_argument("--runs", default=",".join(LABELS), help="which of " + ",".join(LABELS) + " to time")
    args = parser.parse_args()
    chosen = [k for k in LABELS if k in args.runs.split(",")]

    import traci

    runs: dict[str, list[tuple[float, float]]] = {k: [] for k in chosen}
    vehicles: dict[str, list[float]] = {k: [] for k in chosen}
    with tempfile.TemporaryDirectory() as tmp:
        cfg = build_scenario(Path(tmp), args.grid, period_s=0.25, end_s=2000)
        scenario = load_scenario(cfg)
        # simulate's scenario: edge sites placed as the command places them
        linked = load_scenario(cfg, None, SimulateConfig().mobility.coverage_radius_m)
        command = Simulation(scenario, seed=1).command()
        watch5 = {str(i) for i in range(5)}  # the first five vehicles, as a data run watches its own
        timers = {
            "a": lambda: (*time_plain_sumo(command, args.steps, scenario.step_length_s), math.nan),
            "b": lambda: time_frames(scenario, args.steps),
            "b5": lambda: time_frames(scenario, args.steps, watch=watch5),
            "f5": lambda: time_frames(scenario, args.steps, watch=(), focus=watch5),
            "n5": lambda: time_frames(scenario, args.steps, watch=watch5, focus=watch5, around_m=100.0),
            "sf": lambda: time_frames(scenario, args.steps, watch=(), signals=False),
            "s": lambda: time_simulate(linked, args.steps),
            "c": lambda: time_frames(scenario, args.steps, api=traci),
        }
        for _ in range(args.repeat):
            for key in chosen:
                if key == "c" and runs["c"]:  # TraCI is an order of magnitude slower: one run of it is enough
                    continue
                wall, cpu, mean_vehicles = timers[key]()
                runs[key].append((wall, cpu))
                vehicles[key].append(mean_vehicles)
    med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in runs.items()}
    print(f"scenario: {args.grid}x{args.grid} signalised grid, {args.steps} steps of 0.25 s, "
          f"median of {args.repeat} (TraCI: one run); simulate: {len(linked.edge_sites)} edge sites")
    for key in ("b", "n5", "s"):
        if key in chosen:
            print(f"vehicles per step in {LABELS[key].split()[0]}: mean {statistics.mean(vehicles[key]):.0f}")
    print(f"{'':44s} {'wall s':>8s} {'CPU s':>8s}")
    for key in chosen:
        print(f"{LABELS[key]:44s} {med[key][0]:8.2f} {med[key][1]:8.2f}")
    for name, num, den in (
        ("b/a  (ours vs plain sumo)", "b", "a"),
        ("b5/a (ours, 5 watched, vs plain sumo)", "b5", "a"),
        ("f5/a (ours, 5 focus: FL clock, target <= 1.5)", "f5", "a"),
        ("n5/a (ours, 5 + 100 m: data gen., target <= 1.5)", "n5", "a"),
        ("sf/a (simulate's frames vs plain sumo)", "sf", "a"),
        ("c/b  (TraCI vs ours, target >= 5)", "c", "b"),
    ):
        if num in med and den in med:
            print(f"ratio {name:42s} wall {med[num][0] / med[den][0]:5.2f}   CPU {med[num][1] / med[den][1]:5.2f}")
    if "s" in runs and "a" in runs:
        # runs taken in turn, so each ratio compares two runs under the same load
        paired = [s_cpu / a_cpu for (_, s_cpu), (_, a_cpu) in zip(runs["s"], runs["a"])]
        fastest = min(c for _, c in runs["s"]) / min(c for _, c in runs["a"])
        print(f"simulate/sumo = {statistics.median(paired):.2f}")
        print(f"  (CPU time, median of {len(paired)} paired runs: {', '.join(f'{r:.2f}' for r in paired)}; "
              f"fastest s / fastest a: {fastest:.2f}; target <= 1.5)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
