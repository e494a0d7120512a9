"""Benchmark: our frame extraction vs plain `sumo` and vs the same loop over TraCI.

Builds a signalised grid with netgenerate and a demand that keeps at least 500
vehicles on the road (randomTrips, fixed seed), then in one run times:
  (a) the `sumo` binary alone, same options and steps (the floor),
  (b) crchfl_sumo.sim.Simulation over libsumo, reading a Frame every step,
  (c) the same Simulation class over TraCI (a socket per call batch).
Prints wall times, vehicles per step, and the ratios b/a (target <= 1.5) and
c/b (target >= 5).

    python tools/bench_sim.py [--steps 1200] [--grid 10] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from crchfl_sumo.scenario import load_scenario, sumo_binary
from crchfl_sumo.sim import Simulation


def build_scenario(folder: Path, grid: int, period_s: float, end_s: float) -> Path:
    bin_dir = Path(sumo_binary()).parent
    net = folder / "grid.net.xml"
    subprocess.run(
        [
            str(bin_dir / "netgenerate"),
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
    import sumo

    random_trips = Path(sumo.SUMO_HOME) / "tools" / "randomTrips.py"
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


def time_plain_sumo(command: list[str], steps: int, step_length_s: float) -> float:
    start = time.perf_counter()
    subprocess.run([*command, f"--end={steps * step_length_s}"], check=True, capture_output=True)
    return time.perf_counter() - start


def time_frames(scenario, steps: int, api=None) -> tuple[float, float]:
    # Start-up included, as it is in the plain sumo run.
    start = time.perf_counter()
    with Simulation(scenario, seed=1, api=api) as sim:
        counts = [len(sim.step()) for _ in range(steps)]
    elapsed = time.perf_counter() - start
    return elapsed, statistics.mean(counts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1200, help="steps of 0.25 s to time (after warm-up)")
    parser.add_argument("--grid", type=int, default=10, help="junctions per side of the grid")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each, median reported")
    args = parser.parse_args()

    import traci

    with tempfile.TemporaryDirectory() as tmp:
        cfg = build_scenario(Path(tmp), args.grid, period_s=0.4, end_s=2000)
        scenario = load_scenario(cfg)
        command = Simulation(scenario, seed=1).command()
        plain, ours, over_traci, vehicles = [], [], [], []
        for _ in range(args.repeat):
            plain.append(time_plain_sumo(command, args.steps, scenario.step_length_s))
            elapsed, mean_vehicles = time_frames(scenario, args.steps)
            ours.append(elapsed)
            vehicles.append(mean_vehicles)
            over_traci.append(time_frames(scenario, args.steps, api=traci)[0])
    a, b, c = (statistics.median(x) for x in (plain, ours, over_traci))
    print(f"scenario: {args.grid}x{args.grid} signalised grid, {args.steps} steps of 0.25 s")
    print(f"vehicles running: mean {statistics.mean(vehicles):.0f} per step")
    print(f"(a) sumo binary alone        {a:7.2f} s  ({args.steps / a:7.0f} steps/s)")
    print(f"(b) libsumo + Frame per step {b:7.2f} s  ({args.steps / b:7.0f} steps/s)")
    print(f"(c) TraCI + Frame per step   {c:7.2f} s  ({args.steps / c:7.0f} steps/s)")
    print(f"ratio b/a (ours vs plain sumo, target <= 1.5): {b / a:.2f}")
    print(f"ratio c/b (TraCI vs ours, target >= 5):        {c / b:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
