"""Benchmark the data set pipeline: generation speed and the storage codecs, side by side.

    python tools/bench_dataset.py [--scenario paper] [--samples 300] [--paper-size] [--out DIR]
                                  [--repeats 1] [--no-codecs]

1. Generates a data set (the paper's split with ``--paper-size``, else every
   vehicle ``--samples`` samples) twice, alternating ``--repeats`` times:
   rendering each sample in its own call (one by one), and rendering a frame's
   samples in one call (batched, the default). Times every stage and prints
   ``batched/one-by-one = X.XX``, the end-to-end speed ratio.
2. Rewrites the same samples with each HDF5 image filter (none, lzf, gzip)
   and measures bytes per sample, write time, full load (fast path) with and
   without checksum verification, and random per-sample reads (ShardDataset).
3. Prints the PNG bytes per sample against the paper's nominal 1800 KB.

OpenCV and numpy run with the product's settings (core.cpus.settle_native_libraries).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from crchfl_sumo.core.cpus import settle_native_libraries
from crchfl_sumo.data.dataset import ShardDataset, load_samples
from crchfl_sumo.data.settings import PAPER_TOWNS, DatasetConfig, TownSplit
from crchfl_sumo.data.generation import generate_dataset
from crchfl_sumo.data.manifest import NOMINAL_SAMPLE_BYTES, read_manifest
from crchfl_sumo.data.shards import DatasetWriter, read_shard
from crchfl_sumo.sumo.scenario import load_scenario


def sizes_for(args: argparse.Namespace) -> DatasetConfig:
    if args.paper_size:
        return DatasetConfig()
    towns = tuple(
        TownSplit(t.town, tuple(args.samples for _ in t.train_samples), tuple(args.samples for _ in t.test_samples))
        for t in PAPER_TOWNS
    )
    return DatasetConfig(towns=towns)


def timed_generation(args: argparse.Namespace, out: Path, vehicles_per_call: int | None) -> float:
    """Generate the data set into ``out`` (a fresh folder); print the stages; the end-to-end seconds."""
    shutil.rmtree(out, ignore_errors=True)
    scenario = load_scenario(args.scenario)
    stages: dict[str, float] = {}
    start = time.perf_counter()
    manifest = generate_dataset(
        scenario, out, seed=args.seed, sizes=sizes_for(args), timings_s=stages, vehicles_per_call=vehicles_per_call
    )
    total = time.perf_counter() - start
    n = manifest.samples
    mode = "one by one" if vehicles_per_call == 1 else "batched (a frame's samples in one call)"
    print(f"generation, rendering {mode}: {n} samples in {total:.1f} s ({n / total:.0f} samples/s end to end)")
    for stage in ("simulate", "world", "label", "render", "write"):
        seconds = stages.get(stage, 0.0)
        print(f"  {stage:9s} {seconds:6.1f} s  {100 * seconds / total:5.1f} %  ({n / max(seconds, 1e-9):8.0f} samples/s)")
    other = total - sum(stages.values())
    print(f"  {'other':9s} {other:6.1f} s  {100 * other / total:5.1f} %  (scenario load, planning, manifest)")
    print(f"  image size {manifest.image_height}x{manifest.image_width}, 4 cameras")
    return total


def generation_ratio(args: argparse.Namespace, out: Path) -> None:
    """Batched against one-by-one rendering, end to end, alternating ``--repeats`` times (best of each)."""
    best = {1: float("inf"), None: float("inf")}
    for _ in range(args.repeats):
        for vehicles_per_call in best:
            best[vehicles_per_call] = min(best[vehicles_per_call], timed_generation(args, out, vehicles_per_call))
    print(f"batched/one-by-one = {best[1] / best[None]:.2f}  (end-to-end speed, best of {args.repeats} each)")


def best_of(repeats: int, work) -> float:
    """Shortest wall time of ``repeats`` runs (the first may pay for a cold page cache)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        work()
        times.append(time.perf_counter() - t0)
    return min(times)


def codec_table(source: Path, work: Path, reads: int) -> None:
    manifest = read_manifest(source)
    shards = [(entry, read_shard(source, entry)) for entry in manifest.shards]
    n = manifest.samples
    raw = n * 4 * manifest.image_height * manifest.image_width * 3
    print(f"\nstorage ({n} samples, raw images {raw / n / 1024:.1f} KiB/sample):")
    print(f"{'codec':6} {'KiB/sample':>10} {'ratio':>6} {'write+sha+png s':>15} {'load s':>7} {'load+sha s':>10} "
          f"{'random read ms':>14}")
    rng = np.random.default_rng(0)
    for codec in ("none", "lzf", "gzip"):
        root = work / codec
        shutil.rmtree(root, ignore_errors=True)
        t0 = time.perf_counter()
        writer = DatasetWriter(root, dataclasses.replace(manifest, compression=codec, shards=()))
        for entry, data in shards:
            writer.add(entry.file, data, vehicle=entry.vehicle, town=entry.town, edge=entry.edge, split=entry.split)
        write_s = time.perf_counter() - t0
        size = sum(e.size_bytes for e in writer.manifest.shards)
        load_s = best_of(2, lambda: load_samples(root, verify=False))
        verify_s = best_of(2, lambda: load_samples(root, verify=True))
        dataset = ShardDataset(root, verify=False)
        indices = rng.integers(0, len(dataset), reads)
        t0 = time.perf_counter()
        for i in indices:
            dataset[int(i)]
        random_ms = (time.perf_counter() - t0) / reads * 1e3
        dataset.close()
        print(f"{codec:6} {size / n / 1024:10.1f} {raw / size:6.1f} {write_s:15.2f} {load_s:7.2f} {verify_s:10.2f} "
              f"{random_ms:14.3f}")
        shutil.rmtree(root)
    png = manifest.png_bytes_per_sample
    print(f"\nbytes per sample: nominal {NOMINAL_SAMPLE_BYTES} (1800 KiB), measured PNG {png:.0f} "
          f"({png / 1024:.1f} KiB, OpenCV PNG level 3); nominal / measured = {NOMINAL_SAMPLE_BYTES / png:.0f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--samples", type=int, default=300, help="samples per vehicle (without --paper-size)")
    parser.add_argument("--paper-size", action="store_true", help="the paper's split (14,665 samples)")
    parser.add_argument("--reads", type=int, default=2000, help="random per-sample reads per codec")
    parser.add_argument("--out", type=Path, help="keep the generated data set here (default: a temp folder)")
    parser.add_argument("--repeats", type=int, default=1, help="alternating generations of each rendering mode")
    parser.add_argument("--no-codecs", action="store_true", help="skip the storage comparison")
    args = parser.parse_args()
    settle_native_libraries()  # as every command does: OpenCV on one thread, no numpy hugepages
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "dataset"
        generation_ratio(args, out)
        if not args.no_codecs:
            codec_table(out, Path(tmp) / "codecs", args.reads)


if __name__ == "__main__":
    main()
