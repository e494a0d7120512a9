"""Benchmark: our frame extraction vs plain `sumo` and vs the same loop over TraCI.

Builds a signalised grid with netgenerate and a demand that keeps at least 500
vehicles on the road (randomTrips, fixed seed), then in one run times:
  (a) the `sumo` binary alone, same options and steps (the floor),
  (b) crchfl_sumo.sumo.simulation.Simulation over libsumo, reading a Frame every step,
  (c) the same Simulation class over TraCI (a socket per call batch).
Prints wall and CPU times (CPU time is the steadier figure on a shared
machine), vehicles per step, and the ratios b/a (target <= 1.5) and c/b
(target >= 5). (b) is run four ways: every vehicle in the frame with the signal
ahead read for all of them, or for five watched vehicles; and frames that hold
only five focus vehicles, alone (as the federation's SUMO clock reads its
federated vehicles) or with every vehicle within 100 m of one (as data
generation reads the sampled vehicles and what their cameras may draw).

    python tools/bench_sim.py [--steps 1200] [--grid 10] [--repeat 3]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from crchfl_sumo.sumo.scenario import load_scenario, sumo_binary, sumo_tool_script
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


def time_frames(scenario, steps: int, api=None, watch=None, focus=None, around_m=0.0) -> tuple[float, float, float]:
    """(wall s, CPU s of this process and its children, mean vehicles per frame) of a Frame per step."""
    # Start-up included, as it is in the plain sumo run.
    wall, cpu = time.perf_counter(), time.process_time() + _children_cpu_s()
    with Simulation(scenario, seed=1, api=api, watch=watch, focus=focus, around_m=around_m) as sim:
        counts = [len(sim.step()) for _ in range(steps)]
    return time.perf_counter() - wall, time.process_time() + _children_cpu_s() - cpu, statistics.mean(counts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1200, help="steps of 0.25 s to time")
    parser.add_argument("--grid", type=int, default=10, help="junctions per side of the grid")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each, median reported")
    args = parser.parse_args()

    import traci

    runs: dict[str, list[tuple[float, float]]] = {k: [] for k in ("a", "b", "b5", "f5", "n5", "c")}
    vehicles, near = [], []
    with tempfile.TemporaryDirectory() as tmp:
        cfg = build_scenario(Path(tmp), args.grid, period_s=0.25, end_s=2000)
        scenario = load_scenario(cfg)
        command = Simulation(scenario, seed=1).command()
        watch5 = {str(i) for i in range(5)}  # the first five vehicles, as a data run watches its own
        for _ in range(args.repeat):
            runs["a"].append(time_plain_sumo(command, args.steps, scenario.step_length_s))
            wall, cpu, mean_vehicles = time_frames(scenario, args.steps)
            runs["b"].append((wall, cpu))
            vehicles.append(mean_vehicles)
            runs["b5"].append(time_frames(scenario, args.steps, watch=watch5)[:2])
            runs["f5"].append(time_frames(scenario, args.steps, watch=(), focus=watch5)[:2])
            wall, cpu, mean_near = time_frames(scenario, args.steps, watch=watch5, focus=watch5, around_m=100.0)
            runs["n5"].append((wall, cpu))
            near.append(mean_near)
            if not runs["c"]:  # TraCI is an order of magnitude slower: one run of it is enough
                runs["c"].append(time_frames(scenario, args.steps, api=traci)[:2])
    med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in runs.items()}
    labels = {
        "a": "(a) sumo binary alone",
        "b": "(b) libsumo, Frame, signal ahead for all",
        "b5": "(b5) libsumo, Frame, signal ahead for 5",
        "f5": "(f5) libsumo, Frame of 5 focus vehicles",
        "n5": "(n5) libsumo, Frame of 5 + 100 m, signal 5",
        "c": "(c) TraCI, Frame, signal ahead for all",
    }
    print(f"scenario: {args.grid}x{args.grid} signalised grid, {args.steps} steps of 0.25 s, "
          f"median of {args.repeat} (TraCI: one run)")
    print(f"vehicles running: mean {statistics.mean(vehicles):.0f} per step; "
          f"in the 5 + 100 m frames: mean {statistics.mean(near):.0f}")
    print(f"{'':44s} {'wall s':>8s} {'CPU s':>8s}")
    for key, label in labels.items():
        print(f"{label:44s} {med[key][0]:8.2f} {med[key][1]:8.2f}")
    for name, num, den, target in (
        ("b/a  (ours vs plain sumo, target <= 1.5)", "b", "a", None),
        ("b5/a (ours, 5 watched, vs plain sumo)", "b5", "a", None),
        ("f5/a (ours, 5 focus: FL clock, target <= 1.5)", "f5", "a", None),
        ("n5/a (ours, 5 + 100 m: data gen., target <= 1.5)", "n5", "a", None),
        ("c/b  (TraCI vs ours, target >= 5)", "c", "b", None),
    ):
        print(f"ratio {name:42s} wall {med[num][0] / med[den][0]:5.2f}   CPU {med[num][1] / med[den][1]:5.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
