"""Benchmark: the same small sweep on the local backend and on Ray, side by side; Ray's per-task overhead.

    python tools/bench_sweep.py [--runs 4] [--samples 32] [--clock constant|sumo] [--cpus 2] [--tasks 200]

Writes a tiny random data set (5 vehicles of the paper scenario, 48 x 64
images) and sweeps ``federation.edge_interval`` (constant clock) or
``mobility.coverage_radius_m`` (SUMO clock) over ``--runs`` values, HFL, two
cloud rounds, each run in its own process. Prints the wall time of the
local sweep (``--cpus`` processes at a time), of the Ray sweep (a local Ray
runtime of ``--cpus`` CPUs; its start-up timed apart), their ratio, and the
round trip of an empty Ray task (median of ``--tasks`` one after the other)
and of a batch of them, next to an empty task in a fresh local process.
Last, one run of the sweep's first point trained in this process (local)
and with every vehicle's training and each evaluation as a Ray task.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
VEHICLES = [
    ("t01_data_0", "town01", "edge01"),
    ("t01_data_1", "town01", "edge01"),
    ("t02_data_0", "town02", "edge02"),
    ("t02_data_1", "town02", "edge02"),
    ("t02_data_2", "town02", "edge02"),
]


def noop(x=None):
    return x


def write_data(root: Path, samples: int) -> Path:
    from crchfl_sumo.data.manifest import Manifest
    from crchfl_sumo.data.shards import DatasetWriter, ShardData

    rng = np.random.default_rng(0)
    header = Manifest(scenario="paper", seed=0, sample_period_s=0.25, image_height=48, image_width=64, compression="none")
    writer = DatasetWriter(root, header)

    def data(n):
        zeros = np.zeros(n)
        return ShardData(
            rng.integers(0, 256, (n, 4, 48, 64, 3), dtype=np.uint8), rng.random((n, 3), dtype=np.float32),
            rng.integers(0, 7, n), rng.integers(0, 4, n), rng.uniform(0, 14, n).astype(np.float32),
            np.zeros((n, 2), np.float32), np.arange(n) * 0.25, zeros, zeros, zeros,
        )

    for i, (vehicle, town, edge) in enumerate(VEHICLES):
        writer.add(f"{town}-train-{i}.h5", data(samples), vehicle=vehicle, town=town, edge=edge, split="train")
    writer.add("town01-test-0.h5", data(samples), vehicle="t01_test_0", town="town01", edge="edge01", split="test")
    return root


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=4, help="runs in the sweep (default 4)")
    parser.add_argument("--samples", type=int, default=32, help="samples per vehicle (default 32)")
    parser.add_argument("--clock", choices=("constant", "sumo"), default="constant")
    parser.add_argument("--cpus", type=int, default=2, help="parallel runs on either backend (default 2)")
    parser.add_argument("--tasks", type=int, default=200, help="empty Ray tasks timed (default 200)")
    args = parser.parse_args()

    import ray
    import torch

    from crchfl_sumo.core.backend import BackendConfig, Executor
    from crchfl_sumo.core.config import from_mapping
    from crchfl_sumo.federation.run import run_federation_dir
    from crchfl_sumo.federation.run_config import RunConfig
    from crchfl_sumo.federation.run_data import read_inputs
    from crchfl_sumo.studies.sweep import parse_param, run_sweep

    torch.set_num_threads(1)  # the single run's driver: each vehicle task then uses one thread too

    tmp = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    data = write_data(tmp / "data", args.samples)
    base = {
        "dataset": str(data),
        "federation": {"scheme": "hfl", "cloud_interval": 1, "cloud_rounds": 2, "compute_s_per_sample": 1.0},
        "ledger": {"nominal_model_mb": 10.0},
        "model": {"image_height": 48, "image_width": 64},
        "train": {"device": "cpu"},
        "clock": {"kind": args.clock},
    }
    if args.clock == "constant":
        param = parse_param("federation.edge_interval=" + ",".join(str(i + 1) for i in range(args.runs)))
    else:
        base["federation"]["edge_interval"] = 2
        param = parse_param("mobility.coverage_radius_m=" + ",".join(str(150 + 50 * i) for i in range(args.runs)))
    print(f"sweep: {args.runs} runs of {param.path}, {len(VEHICLES)} vehicles x {args.samples} samples, "
          f"{args.clock} clock, {args.cpus} at a time; machine: {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.2f}")

    start = time.perf_counter()
    local_rows = run_sweep(base, [param], tmp / "local", BackendConfig(num_cpus=args.cpus))
    local_s = time.perf_counter() - start

    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(HERE), os.environ.get("PYTHONPATH")) if p)
    start = time.perf_counter()
    ray.init(num_cpus=args.cpus, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    init_s = time.perf_counter() - start
    try:
        start = time.perf_counter()
        ray_rows = run_sweep(base, [param], tmp / "ray", BackendConfig(kind="ray"))
        ray_s = time.perf_counter() - start
        single = {}
        for kind in ("local", "ray"):
            config = from_mapping(RunConfig, {**base, **{"federation": {**base["federation"], "edge_interval": 2}},
                                              "backend": {"kind": kind}})
            inputs = read_inputs(config)
            t = time.perf_counter()
            summary = run_federation_dir(config, inputs, tmp / f"single_{kind}")
            single[kind] = (time.perf_counter() - t, summary["final_accuracy"])

        from bench_sweep import noop as importable_noop  # by module name, so Ray workers import it too

        remote = ray.remote(importable_noop)
        ray.get([remote.remote() for _ in range(args.cpus)])  # workers up
        trips = []
        for _ in range(args.tasks):
            t = time.perf_counter()
            ray.get(remote.remote())
            trips.append(time.perf_counter() - t)
        t = time.perf_counter()
        ray.get([remote.remote(i) for i in range(args.tasks)])
        batch_s = (time.perf_counter() - t) / args.tasks
        with Executor(BackendConfig(kind="ray")) as executor:
            t = time.perf_counter()
            executor.map(importable_noop, [()], isolate=True)
            ray_fresh_s = time.perf_counter() - t
    finally:
        ray.shutdown()
    with Executor(BackendConfig(num_cpus=1)) as executor:
        t = time.perf_counter()
        executor.map(noop, [()], isolate=True)
        process_s = time.perf_counter() - t

    same = [r["final_accuracy"] for r in local_rows] == [r["final_accuracy"] for r in ray_rows]
    print(f"{'':34}{'local':>10}{'ray':>10}{'ray/local':>11}")
    print(f"{'sweep wall time [s]':34}{local_s:10.2f}{ray_s:10.2f}{ray_s / local_s:11.2f}")
    print(f"{'  + Ray runtime start [s]':34}{'':10}{ray_s + init_s:10.2f}{(ray_s + init_s) / local_s:11.2f}")
    print(f"{'per run [s]':34}{local_s / args.runs:10.2f}{ray_s / args.runs:10.2f}")
    print(f"same results on both: {same}")
    print(f"Ray empty task round trip: median {1e3 * statistics.median(trips):.2f} ms "
          f"(p90 {1e3 * sorted(trips)[int(0.9 * len(trips))]:.2f} ms) over {args.tasks}; "
          f"in a batch of {args.tasks}: {1e3 * batch_s:.3f} ms a task")
    print(f"empty task in a fresh process: Ray worker (max_calls=1) {ray_fresh_s:.2f} s, "
          f"local spawned process {process_s:.2f} s")
    (local_run_s, local_acc), (ray_run_s, ray_acc) = single["local"], single["ray"]
    print(f"{'one run, vehicles as tasks [s]':34}{local_run_s:10.2f}{ray_run_s:10.2f}{ray_run_s / local_run_s:11.2f}"
          f"   (same result: {local_acc == ray_acc})")
    return 0 if same and local_acc == ray_acc else 1


if __name__ == "__main__":
    sys.exit(main())
