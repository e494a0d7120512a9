"""Benchmark: what traffic density does to the federated vehicles' uplink rate when the traffic loads the cells.

Runs the federation's SUMO clock (links/clock.py) over a scenario's data vehicles at each demand
scale, with and without background load, and prints the mean edge rate of the vehicles while
covered, side by side:

    scale S: mean uplink A Mbit/s without load, B Mbit/s with share X
    density 2 / density 0.5 (loaded) = R

Usage: python tools/bench_cell_load.py [--scenario paper_linked] [--seconds 300] [--share 0.25]
       [--scales 0.5,1,2]
"""

from __future__ import annotations

import argparse

import numpy as np

from crchfl_sumo.links.clock import SumoClock
from crchfl_sumo.links.mobility import MobilityConfig
from crchfl_sumo.sumo.scenario import SumoConfig, configured_scenario


def mean_rate_mbps(scenario, seconds: float, mobility: MobilityConfig) -> float:
    vehicles = [v for town in scenario.towns for v in town.data_vehicles]
    with SumoClock(scenario, vehicles, seed=0, mobility=mobility) as clock:
        rates = []
        for vehicle in vehicles:
            series = clock.series(vehicle, "edge", clock.start_s, clock.start_s + seconds)
            covered = series.rate_bps[series.rate_bps > 0]
            rates.append(covered)
    return float(np.mean(np.concatenate(rates))) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="paper_linked")
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--share", type=float, default=0.25)
    parser.add_argument("--scales", default="0.5,1,2")
    args = parser.parse_args()
    loaded = {}
    for scale in (float(s) for s in args.scales.split(",")):
        base = MobilityConfig()
        scenario = configured_scenario(args.scenario, SumoConfig(scale=scale), base.coverage_radius_m)
        plain = mean_rate_mbps(scenario, args.seconds, base)
        loaded[scale] = mean_rate_mbps(scenario, args.seconds, MobilityConfig(background_active_share=args.share))
        print(f"scale {scale:g}: mean uplink {plain:.1f} Mbit/s without load, {loaded[scale]:.1f} Mbit/s "
              f"with share {args.share:g}")
    if 0.5 in loaded and 2.0 in loaded:
        print(f"density 2 / density 0.5 (loaded) = {loaded[2.0] / loaded[0.5]:.3f}")


if __name__ == "__main__":
    main()
