"""Time one full CRCHFL plan (the (I_e, I_c) search included), split into compile and solve time.

Run by hand:  python tools/bench_plan.py [--repeats 5]

Side by side in one run: the shipped way (one DPP-parametrised CVXPY problem,
compiled once, re-solved per pair) against building and compiling a fresh
problem for every pair. Target: one full plan of the paper scenario under 1 s.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

from crchfl_sumo.accounting.ledger import LedgerConfig, resolve_sizes
from crchfl_sumo.accounting.schedules import Topology, cloud_round_schedule, schedule_bytes
from crchfl_sumo.planning.problem import _Relaxation, costs_for, make_plan, round_time_s
from crchfl_sumo.planning.settings import AllocationConfig


def rebuild_per_pair_s(config: AllocationConfig, ledger_config: LedgerConfig) -> tuple[float, int]:
    """Seconds to solve every pair's relaxation with a newly built (and so newly compiled) problem."""
    sizes = resolve_sizes(ledger_config)
    topology = Topology.from_counts(config.vehicles_per_edge)
    costs = costs_for(config, ledger_config.rule, topology, sizes)
    pairs = [(ie, ic) for ie in config.edge_intervals() for ic in config.cloud_intervals(ie)]
    start = time.perf_counter()
    solved = 0
    for ie, ic in pairs:
        rb = schedule_bytes(cloud_round_schedule(ledger_config.rule, "crchfl", topology, sizes, ic))
        rs = round_time_s(config, costs, ie, ic)
        if rb > sizes.budget_bytes or rs > config.training_time_budget_s:
            continue
        fresh = _Relaxation(config, costs, sizes.budget_bytes, config.training_time_budget_s)
        fresh.solve(rb, rs, config.gamma * config.local_samples * config.d / (ie * ic))
        solved += 1
    return time.perf_counter() - start, solved


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    config = AllocationConfig()
    cases = [
        ("paper rule, 20 GB", config, LedgerConfig(budget_gb=20.0)),
        ("physical rule, 20 GB", config, LedgerConfig(rule="physical", budget_gb=20.0)),
        ("paper rule, 40 GB", config, LedgerConfig(budget_gb=40.0)),
        ("paper, fix I_e = 4", dataclasses.replace(config, fix_edge_interval=4), LedgerConfig()),
    ]
    print(f"{'case':<22}{'pairs':>6}{'total ms':>10}{'compile ms':>12}{'solve ms':>10}"
          f"{'per pair ms':>13}{'rebuild ms':>12}{'rebuild/dpp':>13}  plan (x, I_e, I_c, T)")
    for name, alloc, ledger in cases:
        totals, compiles, solves, rebuilds = [], [], [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            plan = make_plan(alloc, ledger)
            totals.append(time.perf_counter() - start)
            compiles.append(plan.compile_s)
            solves.append(plan.solve_s)
            rebuild, _ = rebuild_per_pair_s(alloc, ledger)
            rebuilds.append(rebuild)
        total = statistics.median(totals)
        solve = statistics.median(solves)
        rebuild = statistics.median(rebuilds)
        print(
            f"{name:<22}{plan.pairs_searched:>6}{total * 1e3:>10.1f}{statistics.median(compiles) * 1e3:>12.1f}"
            f"{solve * 1e3:>10.1f}{solve / plan.pairs_searched * 1e3:>13.2f}{rebuild * 1e3:>12.1f}"
            f"{rebuild / (statistics.median(compiles) + solve):>13.2f}  "
            f"({plan.pretrain_batch}, {plan.edge_interval}, {plan.cloud_interval}, {plan.cloud_rounds})"
        )
    print(f"medians of {args.repeats} runs; total = whole make_plan (search, rounding, ledger replay); "
          "rebuild = a fresh problem compiled for every pair, compared with compile + solve")


if __name__ == "__main__":
    main()
