"""Benchmark: drive-bench's route drawing on a large network (bounded searches from sampled starts).

Builds an N x N grid network with netgenerate (200 m blocks, one lane a direction: about
4 N (N - 1) edges), then times `drive_bench_tasks.draw_episodes` for the four suites. Prints

    route drawing: E edges, C candidates, S s (straight K, one_turn K, navigation K)

Usage: python tools/bench_routes.py [--grid 36] [--episodes 10]
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from collections import Counter
from pathlib import Path

from crchfl_sumo.driving.drive_bench_tasks import TASKS, candidate_routes, draw_episodes
from crchfl_sumo.sumo.route import read_net
from crchfl_sumo.sumo.installation import sumo_binary
from crchfl_sumo.sumo.scenario import load_scenario


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grid", type=int, default=36)
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        net = Path(tmp) / "grid.net.xml"
        subprocess.run([sumo_binary("netgenerate"), "--grid", f"--grid.number={args.grid}", "--grid.length=200",
                        "--no-turnarounds", "-o", str(net)], check=True, capture_output=True)
        cfg = Path(tmp) / "grid.sumocfg"
        cfg.write_text(f'<configuration><input><net-file value="{net.name}"/></input></configuration>')
        scenario = load_scenario(cfg, coverage_radius_m=300.0)
        edges = len(read_net(net).getEdges(withInternal=False))
        start = time.perf_counter()
        episodes = draw_episodes(scenario, TASKS, args.episodes, seed=0)  # the candidates, then the draws
        elapsed = time.perf_counter() - start
        candidates = candidate_routes(scenario)
        per_task = Counter(e.task for e in episodes)
        turns = Counter("straight" if c.turns == 0 else "one_turn" if c.turns == 1 else "navigation" for c in candidates)
        print(f"route drawing: {edges} edges, {len(candidates)} candidates, {elapsed:.1f} s "
              f"(straight {turns['straight']}, one_turn {turns['one_turn']}, navigation {turns['navigation']}); "
              f"episodes per task {dict(per_task)}")


if __name__ == "__main__":
    main()
