"""Benchmark: training many vehicle models vs one sequential loop vs one centralized model.

In one run, on the same synthetic samples (vehicle sizes in the proportions of
the paper's data set, FACTS.md), measures one epoch of training throughput of
  (a) train_vehicles, our multi-vehicle trainer, with each multi_vehicle method
      ("sequential", which "auto" picks on a CPU, and "vmap", on a GPU:
      functional_call + vmap over stacked parameters),
  (b) the plain sequential per-vehicle loop (a fresh model and optimizers per
      vehicle, written out here without train_vehicles),
  (c) one centralized model on all samples,
and prints samples/s, the ratios a/c and a/b for each method, and the achieved
GFLOP/s against a large float32 matmul measured in the same run.

Then the speed levers of one centralized training epoch, each against the
plain float32 eager path in the same run, interleaved: the product's default
path (``default/fp32 = X.XX``, TrainConfig's default precision), the bf16
precision (``train.precision = "bf16"``: the forward pass under bfloat16
autocast), channels_last weights, torch.compile (inductor) and torch.compile
with bf16. Compilation happens in the warm-up run, which is not timed; its
seconds are printed apart.

Then, in fresh processes, one centralized training at a time (``--busy-s``
seconds each, best epoch kept, the default precision): one thread on the
otherwise idle machine (solo1); the product's defaults beside one busy process,
which leaves one of the two cores free (busy: the threads the affinity mask
gives, pinned one to a CPU while they train, ``crchfl_sumo.core.cpus
.pinned_threads``, and the wait policy ``choose_wait_policy`` picks as every
command starts); beside the same process, threads left unpinned with sleeping
waits (unpinned, the product before the pinning) and unpinned with OpenMP's
spinning wait (before: the product before either). It prints
``busy/solo1 = X.XX``, ``unpinned/solo1 = X.XX`` and ``before/solo1 = X.XX``.

Usage: python tools/bench_train.py [--scale 0.05] [--height 64] [--width 128] [--repeats 5] [--busy-s 25]
       [--busy-only | --levers-only]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.model import DrivingModel, build_model, longitudinal_target
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.devices import resolve_device, resolved_multi_vehicle
from crchfl_sumo.learning.training import Learner, branch_losses, train_vehicles

PAPER_VEHICLE_SAMPLES = (2928, 2928, 2586, 2587, 1555)


def synthetic_samples(num_samples: int, height: int, width: int, rng: np.random.Generator) -> Samples:
    actions = rng.random((num_samples, 3), dtype=np.float32)
    return Samples.from_numpy(
        rng.integers(0, 256, size=(num_samples, 4, height, width, 3), dtype=np.uint8),
        actions,
        rng.integers(0, 7, size=num_samples),
        rng.integers(0, 4, size=num_samples),
        rng.uniform(0, 14, size=num_samples),
        rng.uniform(0, 14, size=num_samples),
    )


def train_flops_per_sample(model_config: ModelConfig, batch_size: int) -> float:
    """FLOPs of one forward + backward pass, per sample, counted by torch's flop counter."""
    model = DrivingModel(model_config)
    batch = synthetic_samples(batch_size, model_config.image_height, model_config.image_width, np.random.default_rng(0))
    with FlopCounterMode(display=False) as counter:
        longitudinal, steer_logits = model(batch.images, batch.command, batch.speed_mps)
        target = longitudinal_target(model_config, batch)
        loss_tb, loss_steer = branch_losses(longitudinal, steer_logits, target, batch.steer_class)
        (loss_tb + loss_steer).backward()
    return counter.get_total_flops() / batch_size


def matmul_gflops(device: torch.device, size: int = 2048, trials: int = 5, repeats: int = 3) -> float:
    """Best float32 GFLOP/s of a size^3 matmul on ``device`` over a few short trials."""
    a, b = torch.randn(size, size, device=device), torch.randn(size, size, device=device)
    a @ b
    best = 0.0
    for _ in range(trials):
        seconds = timed(lambda: [a @ b for _ in range(repeats)])
        best = max(best, 2 * size**3 * repeats / seconds / 1e9)
    return best


def timed(function) -> float:
    """Wall seconds of ``function()``, queued GPU work included (CUDA runs asynchronously)."""
    synchronize = torch.cuda.synchronize if torch.cuda.is_initialized() else (lambda: None)
    synchronize()
    start = time.perf_counter()
    function()
    synchronize()
    return time.perf_counter() - start


def best_seconds(runs: dict, repeats: int, warmup_s: dict[str, float] | None = None) -> dict[str, float]:
    """Best wall seconds of each run: one warm-up each (its seconds go into ``warmup_s``), then
    ``repeats`` interleaved rounds, each starting with the next run (the first run of a round is
    the slower one), so load changes and that penalty hit all runs alike."""
    for name, function in runs.items():
        seconds = timed(function)
        if warmup_s is not None:
            warmup_s[name] = seconds
    best_s = {name: float("inf") for name in runs}
    names = list(runs)
    for r in range(repeats):
        for name in names[r % len(names):] + names[: r % len(names)]:
            best_s[name] = min(best_s[name], timed(runs[name]))
    return best_s


# One centralized training in a fresh process: the wait policy is chosen as a command would, before torch loads.
EPOCH_RATE_CHILD = """
import sys, time
from crchfl_sumo.core import cpus
if sys.argv[1] == "product":
    cpus.choose_wait_policy()
else:
    cpus.can_pin_threads = lambda: False  # the threads as the kernel places them
import numpy as np, torch
sys.path.insert(0, {tools!r})
from bench_train import synthetic_samples
from crchfl_sumo.learning.model import build_model
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.training import Learner
config = ModelConfig("compact", {height}, {width})
samples = synthetic_samples(320, {height}, {width}, np.random.default_rng(0))
learner = Learner(build_model(config, seed=0), TrainConfig())
learner.train_epoch(samples, torch.Generator().manual_seed(0))
best_s, end = float("inf"), time.perf_counter() + {seconds}
while time.perf_counter() < end:
    start = time.perf_counter()
    learner.train_epoch(samples, torch.Generator().manual_seed(1))
    best_s = min(best_s, time.perf_counter() - start)
print(len(samples) / best_s, torch.get_num_threads())
"""


def epoch_rate(mode: str, environ: dict[str, str], args) -> tuple[float, int]:
    """(samples/s, torch threads) of a fresh process's centralized training; mode "product" pins the threads
    and picks the wait policy, "plain" does neither (the policy is then ``environ``'s)."""
    code = EPOCH_RATE_CHILD.format(tools=os.path.dirname(os.path.abspath(__file__)), height=args.height,
                                   width=args.width, seconds=args.busy_s)
    out = subprocess.run([sys.executable, "-c", code, mode], env=environ, check=True, capture_output=True, text=True)
    rate, threads = out.stdout.split()
    return float(rate), int(threads)


def busy_against_solo(args) -> None:
    """The busy/solo1 lines: training beside one busy process against one thread alone."""
    plain = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
    solo1, _ = epoch_rate("plain", {**plain, "OMP_NUM_THREADS": "1"}, args)
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(1.0)  # the spinner is on its core before the product looks at the load
        busy, threads = epoch_rate("product", plain, args)
        unpinned, _ = epoch_rate("plain", {**plain, "OMP_WAIT_POLICY": "PASSIVE"}, args)
        before, _ = epoch_rate("plain", plain, args)
    finally:
        spinner.kill()
        spinner.wait()
    print(f"centralized training, {args.busy_s:g} s each, best epoch of 320 samples; one busy process beside:")
    print(f"solo1 {solo1:.1f} samples/s (1 thread, idle machine); busy {busy:.1f} ({threads} threads, "
          f"product defaults); unpinned {unpinned:.1f} (sleeping wait); before {before:.1f} (spinning wait)")
    print(f"busy/solo1 = {busy / solo1:.2f}")
    print(f"unpinned/solo1 = {unpinned / solo1:.2f}")
    print(f"before/solo1 = {before / solo1:.2f}")


def lever_rates(
    samples: Samples, model_config: ModelConfig, device: torch.device, repeats: int
) -> tuple[dict[str, float], dict[str, float]]:
    """(samples/s of one centralized epoch per speed lever, best of ``repeats`` interleaved runs;
    seconds of each lever's warm-up epoch, compilation included)."""

    def epoch(config: TrainConfig, channels_last: bool = False, compile: bool = False):
        def run() -> None:
            model = build_model(model_config, seed=0).to(device)
            if channels_last:
                model = model.to(memory_format=torch.channels_last)
            if compile:
                # A fresh model each run reuses the code compiled in the warm-up (parameters are graph inputs).
                model = torch.compile(model)
            Learner(model, config).train_epoch(samples, torch.Generator().manual_seed(1))

        return run

    fp32, bf16 = TrainConfig(device=device.type, precision="fp32"), TrainConfig(device=device.type, precision="bf16")
    levers = {
        "fp32": epoch(fp32),
        "default": epoch(TrainConfig(device=device.type, precision=TrainConfig.precision)),
        "bf16": epoch(bf16),
        "channels_last": epoch(fp32, channels_last=True),
        "compile": epoch(fp32, compile=True),
        "bf16+compile": epoch(bf16, compile=True),
    }
    warmup_s: dict[str, float] = {}
    best_s = best_seconds(levers, repeats, warmup_s)
    return {name: len(samples) / seconds for name, seconds in best_s.items()}, warmup_s


def print_levers(samples: Samples, model_config: ModelConfig, device: torch.device, repeats: int) -> None:
    rate, warmup_s = lever_rates(samples, model_config, device, repeats)
    print(f"centralized training, one epoch of {len(samples)} samples, best of {repeats} interleaved runs:")
    for name, samples_per_s in rate.items():
        print(f"{name:20s} {samples_per_s:8.1f} samples/s   (warm-up epoch {warmup_s[name]:.1f} s)")
    for name in rate:
        if name != "fp32":
            print(f"{name}/fp32 = {rate[name] / rate['fp32']:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=0.05, help="fraction of the paper's per-vehicle sample counts")
    parser.add_argument("--height", type=int, default=ModelConfig.image_height)
    parser.add_argument("--width", type=int, default=ModelConfig.image_width)
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats of each method (best is kept)")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--arch", default=ModelConfig.arch, choices=("cil", "paper"))
    parser.add_argument("--busy-s", type=float, default=25.0, help="seconds of each busy/solo1 training (0: skip)")
    parser.add_argument("--busy-only", action="store_true", help="measure only busy/solo1")
    parser.add_argument("--levers-only", action="store_true", help="measure only the speed levers (default/fp32)")
    args = parser.parse_args()
    if args.busy_only:
        busy_against_solo(args)
        return

    rng = np.random.default_rng(0)
    counts = [max(1, round(n * args.scale)) for n in PAPER_VEHICLE_SAMPLES]
    vehicles = [synthetic_samples(n, args.height, args.width, rng) for n in counts]
    everything = Samples.concat(vehicles)
    total = len(everything)
    model_config = ModelConfig("compact", args.height, args.width, arch=args.arch)
    state = build_model(model_config, seed=0).state_dict()
    states = [state] * len(vehicles)
    configs = {m: TrainConfig(device=args.device, multi_vehicle=m) for m in ("vmap", "sequential")}

    device = resolve_device(args.device)
    if args.levers_only:
        print_levers(everything.to(device), model_config, device, args.repeats)
        return
    vehicles_on_device = [s.to(device) for s in vehicles]
    everything_on_device = everything.to(device)

    def run_multi(method: str) -> None:
        train_vehicles(states, vehicles_on_device, 1, model_config, configs[method], seed=1)

    def run_plain_loop() -> None:
        for v, samples in enumerate(vehicles_on_device):
            model = DrivingModel(model_config)
            model.load_state_dict(state)
            trainer = Learner(model.to(device), configs["sequential"])
            trainer.train_epoch(samples, torch.Generator().manual_seed(v))
            trainer.state()

    def run_central() -> None:
        trainer = Learner(build_model(model_config, seed=0).to(device), configs["sequential"])
        trainer.train_epoch(everything_on_device, torch.Generator().manual_seed(1))

    runs = {
        "a sequential": lambda: run_multi("sequential"),
        "a vmap": lambda: run_multi("vmap"),
        "b plain loop": run_plain_loop,
        "c centralized": run_central,
    }
    best_s = best_seconds(runs, args.repeats)

    flops = train_flops_per_sample(model_config, TrainConfig().batch_size)
    peak = matmul_gflops(device)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}")
    print(f"vehicles {counts} = {total} samples, image {args.height}x{args.width}, batch 32, 1 epoch, best of {args.repeats}")
    print(f"train FLOPs per sample {flops / 1e9:.3f} GFLOP; float32 matmul 2048^3: {peak:.1f} GFLOP/s")
    rate = {name: total / seconds for name, seconds in best_s.items()}
    for name, samples_per_s in rate.items():
        gflops = samples_per_s * flops / 1e9
        print(f"{name:15s} {samples_per_s:8.1f} samples/s  {gflops:6.1f} GFLOP/s  ({100 * gflops / peak:4.1f}% of matmul)")
    b, c = rate["b plain loop"], rate["c centralized"]
    for method in ("sequential", "vmap"):
        a = rate[f"a {method}"]
        print(f"a={method:10s}  a/c = {a / c:.3f}   a/b = {a / b:.3f}")
    default = resolved_multi_vehicle(TrainConfig(), model_config, device.type)
    print(f"b/c = {b / c:.3f}; train_vehicles default method here: {default}")
    print_levers(everything_on_device, model_config, device, args.repeats)
    if args.busy_s > 0:
        busy_against_solo(args)


if __name__ == "__main__":
    main()
