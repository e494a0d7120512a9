"""Benchmark: automatic edge sites at city scale, hexagonal layout against k-means, on one network.

Builds an X x Y km grid network with netgenerate (500 m blocks, two lanes a direction, guessed
signals) and a few random trips, places the sites of a plain .sumocfg with each method, checks
that every road point is within the coverage radius, and runs `simulate` on it.

Prints per method:  placement METHOD: N sites in S s, farthest road point D m (radius R m)
and last:           hex/kmeans placement time = RATIO   (k-means stopped at its cap is said so)

Usage: python tools/bench_sites.py [--km 18x10] [--radius 300] [--simulate-s 30] [--kmeans]
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.studies.simulate import run_simulate_command
from crchfl_sumo.sumo.installation import sumo_binary
from crchfl_sumo.sumo.network import lane_points
from crchfl_sumo.sumo.scenario import load_scenario

BLOCK_M = 500.0


def build_network(folder: Path, x_km: float, y_km: float) -> Path:
    net = folder / "city.net.xml"
    subprocess.run([
        sumo_binary("netgenerate"), "--grid", f"--grid.x-number={int(x_km * 1000 / BLOCK_M) + 1}",
        f"--grid.y-number={int(y_km * 1000 / BLOCK_M) + 1}", f"--grid.length={BLOCK_M}", "--default.lanenumber=2",
        "--tls.guess=true", "-o", str(net),
    ], check=True, capture_output=True)
    trips = folder / "trips.rou.xml"
    # a few vehicles on the grid's outer edges' neighbours: enough for simulate to have traffic
    edges = [line.split('id="')[1].split('"')[0] for line in net.read_text().splitlines()
             if "<edge " in line and 'function="internal"' not in line][:40]
    trips.write_text("<routes>" + "".join(
        f'<trip id="t{i}" depart="{i}" from="{edges[i]}" to="{edges[-1 - i]}"/>' for i in range(10)) + "</routes>")
    cfg = folder / "city.sumocfg"
    cfg.write_text(f'<configuration><input><net-file value="{net.name}"/><route-files value="{trips.name}"/></input>'
                   '<time><step-length value="1"/></time></configuration>')
    return cfg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--km", default="18x10")
    parser.add_argument("--radius", type=float, default=300.0)
    parser.add_argument("--simulate-s", type=float, default=30.0)
    parser.add_argument("--kmeans", action="store_true", help="also time k-means (minutes, or its 64-site cap)")
    args = parser.parse_args()
    x_km, y_km = (float(v) for v in args.km.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = build_network(Path(tmp), x_km, y_km)
        points = lane_points(Path(tmp) / "city.net.xml")
        print(f"{x_km:g} x {y_km:g} km grid: {len(points)} road points")
        times = {}
        for method in ("hex", "kmeans") if args.kmeans else ("hex",):
            start = time.perf_counter()
            try:
                scenario = load_scenario(cfg, coverage_radius_m=args.radius, site_placement=method)
            except CrchflError as exc:
                times[method] = None
                print(f"placement {method}: refused after {time.perf_counter() - start:.1f} s ({exc})")
                continue
            times[method] = time.perf_counter() - start
            centres = np.array([(s.x_m, s.y_m) for s in scenario.edge_sites])
            farthest = float(cKDTree(centres).query(points)[0].max())
            print(f"placement {method}: {len(centres)} sites in {times[method]:.2f} s, farthest road point "
                  f"{farthest:.1f} m (radius {args.radius:g} m)")
        if args.simulate_s > 0:
            start = time.perf_counter()
            run_simulate_command(str(cfg), args.simulate_s, Path(tmp) / "sim", seed=0, config_path=None)
            print(f"simulate {args.simulate_s:g} s (the default [mobility] coverage radius): "
                  f"{time.perf_counter() - start:.1f} s wall, exit 0")
        if times.get("kmeans") and times.get("hex"):
            print(f"hex/kmeans placement time = {times['hex'] / times['kmeans']:.3f}")


if __name__ == "__main__":
    main()
