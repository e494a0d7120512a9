"""Benchmark a run's per-step save against the length of the run: append-only logs against rewriting them.

    nice -n 10 python tools/bench_saves.py [--clients 200] [--repeat 5]

For a state holding N ledger records (N = 2,400, 16,600 and 80,000: about
3, 40 and 100 rounds of 200 clients), one step's save is timed two ways,
side by side in one process, in a temporary folder:

* append: what a run does (federation/logs.py, federation/run.py): append the
  step's new records and lines to the logs, then write the checkpoint of the
  state less its history;
* rewrite: what it did before: rewrite ledger.jsonl, metrics.jsonl and
  stragglers.jsonl whole, and put every record in the checkpoint.

The models are tiny here (one shared 16-element tensor), so the figures are
the cost of the history alone; a real run adds the write of its model state,
the same at every step.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from crchfl_sumo.accounting.ledger import Ledger, Record
from crchfl_sumo.accounting.schedules import ByteSizes
from crchfl_sumo.core.atomic import atomic_path, atomic_write_text
from crchfl_sumo.federation.logs import append_logs, start_logs
from crchfl_sumo.federation.state import FederationState

SIZES = ByteSizes(model_bytes=2_000_000, sample_bytes=1_000, budget_bytes=2**60)


def history(records: int, clients: int) -> tuple[list[Record], list[dict]]:
    """``records`` wireless/wireline records and one metric line per 2 x ``clients`` records."""
    out = []
    for i in range(records):
        out.append(Record("wireless", "uplink" if i % 2 else "downlink", "II", f"v{i % clients}", "e0", "model",
                          SIZES.model_bytes, 1 + i // (2 * clients), 10.0 * i, 10.0 * i + 7.25))
    lines = [{"step": k + 1, "stage": "II", "loss": 0.5, "accuracy": 0.5, "sim_time_s": 10.0 * k}
             for k in range(max(1, records // (2 * clients)))]
    return out, lines


def state_of(records: list[Record], lines: list[dict], clients: int) -> FederationState:
    model = {"w": torch.zeros(16)}
    vehicles = [f"v{i}" for i in range(clients)]
    return FederationState(
        vehicle_models={v: model for v in vehicles}, edge_models={"e0": model}, edge_weights={"e0": 1.0},
        cloud_model=model, member={v: "e0" for v in vehicles}, ready_s={v: 0.0 for v in vehicles},
        open_s={"e0": 0.0}, records=records, metrics=lines, stragglers=[],
    )


def save_appending(out: Path, state: FederationState, marks) -> float:
    start = time.perf_counter()
    marks = append_logs(out, state, marks)
    with atomic_path(out / "checkpoint.pt") as tmp:
        torch.save({"state": state.to_payload(), "logs": marks}, tmp)
    return time.perf_counter() - start


def save_rewriting(out: Path, state: FederationState) -> float:
    start = time.perf_counter()
    atomic_write_text(out / "metrics.jsonl", "".join(json.dumps(m) + "\n" for m in state.metrics))
    atomic_write_text(out / "stragglers.jsonl", "".join(json.dumps(s) + "\n" for s in state.stragglers))
    Ledger(SIZES, state.records).save(out / "ledger.jsonl")
    payload = {**state.to_payload(), "records": [r.to_dict() for r in state.records], "metrics": state.metrics,
               "stragglers": state.stragglers}
    with atomic_path(out / "checkpoint.pt") as tmp:
        torch.save({"state": payload}, tmp)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=5, help="steps timed per size (the median is printed)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    per_step = 2 * args.clients  # an edge aggregation: one upload and one download per client
    print(f"one step adds {per_step} records; median of {args.repeat} steps [ms]")
    print(f"{'records':>8} {'append':>8} {'rewrite':>8} {'rewrite / append':>17}")
    for n in (2_400, 16_600, 80_000):
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp)
            records, lines = history(n + per_step * args.repeat, args.clients)
            appending, rewriting = [], []
            for k in range(args.repeat):
                done = n + per_step * k  # the logs hold the history up to the step before
                before = state_of(records[:done], lines[: done // per_step], args.clients)
                marks = start_logs(out, SIZES)
                marks = append_logs(out, before, marks)
                state = state_of(records[: done + per_step], lines[: done // per_step + 1], args.clients)
                appending.append(save_appending(out, state, marks))
                rewriting.append(save_rewriting(out, state))
            a, r = sorted(appending)[len(appending) // 2], sorted(rewriting)[len(rewriting) // 2]
            print(f"{n:8d} {1e3 * a:8.1f} {1e3 * r:8.1f} {r / a:17.1f}")


if __name__ == "__main__":
    main()
