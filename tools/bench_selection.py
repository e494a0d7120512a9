"""Mobility-aware client selection against all clients, side by side: time-to-accuracy, stragglers, wasted bytes.

    nice -n 10 python tools/bench_selection.py [--data DIR] [--samples 40] [--test-samples 60]
                                               [--handover-policies new_edge,miss] [--selections all,skip_leaving]
                                               [--budget-gb 20] [--target B] [--seed 0]

1. Data: a small real data set of scenario paper_linked (its 7 data vehicles,
   two of which drive between the towns and so between the two edge
   servers), --samples training samples each, --test-samples per test
   vehicle; generated once into --data and reused.
2. Runs: HFL on SUMO's clock, the paper's accounting of a model (150 MB,
   so an upload lasts about a minute), the physical rule (a failed transfer
   is charged the bytes that crossed), --budget-gb, the same seed, one run
   per handover policy x selection. Each runs in this process, one after
   the other (libsumo allows one simulation at a time).
3. Prints per run: rounds, simulated time, stragglers, vehicle-aggregations
   skipped by the selection, wasted bytes (charged to wireless transfers
   whose payload was not used), bytes consumed, the best balanced accuracy
   of the cloud model and when (simulated s) it was first reached, and the
   simulated time to reach --target (default: the lowest best of all runs,
   so that every run reaches it).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

SCENARIO = "paper_linked"


def make_data(data_dir: Path, samples: int, test_samples: int, seed: int) -> None:
    from crchfl_sumo.data.settings import DatasetConfig, TownSplit
    from crchfl_sumo.data.generation import generate_dataset
    from crchfl_sumo.sumo.scenario import load_scenario

    scenario = load_scenario(SCENARIO)
    sizes = DatasetConfig(
        towns=tuple(
            TownSplit(t.name, (samples,) * len(t.data_vehicles), (test_samples,) * len(t.test_vehicles))
            for t in scenario.towns
        )
    )
    generate_dataset(scenario, data_dir, seed=seed, sizes=sizes)


def run_config(data_dir: Path, handover_policy: str, selection: str, budget_gb: float, seed: int):
    from crchfl_sumo.core.config import from_mapping
    from crchfl_sumo.federation.run_config import RunConfig

    mapping = {
        "scenario": SCENARIO,
        "dataset": str(data_dir),
        "federation": {"scheme": "hfl", "edge_interval": 2, "cloud_interval": 1, "seed": seed,
                       "handover_policy": handover_policy, "selection": selection},
        "ledger": {"rule": "physical", "model_size": "nominal", "budget_gb": budget_gb},
        "train": {"device": "cpu"},
        "clock": {"kind": "sumo"},
    }
    return from_mapping(RunConfig, mapping, where="bench_selection")


def cloud_lines(out_dir: Path) -> list[dict]:
    lines = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    return [m for m in lines if m["stage"] == "III"]


def score(line: dict) -> float:
    """The figure the run ranks its models by: balanced accuracy (plain accuracy where there is none)."""
    value = line.get("balanced_accuracy")
    return line["accuracy"] if value is None else value


def first_time_at(lines: list[dict], target: float) -> float | None:
    """Simulated time of the first cloud evaluation scoring at least ``target`` (None: never)."""
    return next((m["sim_time_s"] for m in lines if score(m) >= target - 1e-12), None)


def one_run(data_dir: Path, out_dir: Path, handover_policy: str, selection: str, budget_gb: float, seed: int) -> dict:
    from crchfl_sumo.federation.run import run_federation_dir
    from crchfl_sumo.federation.run_data import read_inputs

    config = run_config(data_dir, handover_policy, selection, budget_gb, seed)
    start = time.perf_counter()
    summary = run_federation_dir(config, read_inputs(config), out_dir)
    lines = cloud_lines(out_dir)
    best = max((score(m) for m in lines), default=float("nan"))
    return {
        "handover_policy": handover_policy,
        "selection": selection,
        "summary": summary,
        "lines": lines,
        "best": best,
        "best_at_s": first_time_at(lines, best),
        "wall_s": time.perf_counter() - start,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=None, help="data set folder (generated there if missing)")
    parser.add_argument("--samples", type=int, default=40)
    parser.add_argument("--test-samples", type=int, default=60)
    parser.add_argument("--handover-policies", default="new_edge,miss")
    parser.add_argument("--selections", default="all,skip_leaving")
    parser.add_argument("--budget-gb", type=float, default=20.0)
    parser.add_argument("--target", type=float, default=None, help="balanced accuracy to reach (default: lowest best)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)

    with tempfile.TemporaryDirectory(prefix="bench_selection_") as tmp:
        data_dir = args.data or Path(tmp) / "data"
        if not (data_dir / "manifest.json").exists():
            start = time.perf_counter()
            make_data(data_dir, args.samples, args.test_samples, args.seed)
            print(f"data set: {data_dir} generated in {time.perf_counter() - start:.1f} s")
        runs = []
        for policy in args.handover_policies.split(","):
            for choice in args.selections.split(","):
                out_dir = Path(tmp) / f"{policy}-{choice}"
                runs.append(one_run(data_dir, out_dir, policy, choice, args.budget_gb, args.seed))
                print(f"  ran {policy} / {choice} in {runs[-1]['wall_s']:.1f} s wall", flush=True)

    target = args.target if args.target is not None else min(r["best"] for r in runs)
    print(f"\n{SCENARIO}, HFL, 7 vehicles, {args.samples} samples each, 150 MB models (physical rule), "
          f"{args.budget_gb:g} GB, seed {args.seed}; target balanced accuracy {target:.3f}")
    header = ("handover", "selection", "rounds", "sim s", "stragglers", "skipped", "wasted MB", "consumed MB",
              "uploads failed", "best bal.acc", "at sim s", "to target s")
    rows = []
    for r in runs:
        s = r["summary"]
        reached = first_time_at(r["lines"], target)
        rows.append((
            r["handover_policy"], r["selection"], str(s["cloud_rounds"]), f"{s['sim_time_s']:.0f}",
            str(s["stragglers"]), str(s["skipped_by_selection"]), f"{s['wasted_bytes'] / 2**20:.0f}",
            f"{s['consumed_bytes'] / 2**20:.0f}", f"{s['uploads_failed']}/{s['uploads']}", f"{r['best']:.3f}",
            f"{r['best_at_s']:.0f}" if r["best_at_s"] is not None else "-",
            f"{reached:.0f}" if reached is not None else "never",
        ))
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(header)]
    print("| " + " | ".join(h.ljust(w) for h, w in zip(header, widths)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for row in rows:
        print("| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |")


if __name__ == "__main__":
    main()
