"""Benchmark one federation with 200 clients (scenario scale200): where the time and the memory go.

    nice -n 10 python tools/bench_scale.py [--samples 8] [--test-samples 50] [--scheme hfl]
                                           [--rounds 3] [--cloud-interval 2] [--out DIR] [--profile N]
                                           [--download-handover relay|restart|drop]
                                           [--scenario scale200|DIR] [--backend local|ray] [--data DIR]

A larger federation: ``python tools/build_nets.py --scale-clients 1000 --out DIR``
builds DIR/scale1000 (20 copies of Town01, 1,000 data vehicles, 40 edge
sites); pass ``--scenario DIR/scale1000``. ``--backend ray`` trains the
clients as tasks of a local Ray runtime (RayTrainer).

1. Data: generates a data set for all 200 data vehicles of scale200 (the
   clients): --samples training samples each, --test-samples per test
   vehicle (4), 64 x 128 images. It runs in a child process, so that its peak
   memory (every SUMO frame is kept) is measured apart from the federation's.
   Prints the wall time per generation stage.
2. Federation: one run (--scheme hfl, or crchfl with stage I pretraining on
   --pretrain-batch uploaded samples) on SUMO's clock with all 200 clients,
   compact model, charged at its real size (physical rule, 1 TB budget: the
   run stops at --rounds cloud rounds, not at the budget), --cloud-interval
   edge aggregations of one local epoch per cloud round. The wall time is split at the library's public seams: SUMO's
   step (a Frame), the link models, the rest of the clock (per-vehicle link
   series), local training, FedAvg, evaluation, the time the loop waits for
   the previous step's save (checkpoint and output files, written on a
   background thread beside the next step; their own writing time is printed
   apart and is not part of the split), and the loop itself (transfers over
   the links, ledger, bookkeeping).
3. Prints per-client figures (time per client per round, bytes per client),
   rounds reached, handovers, stragglers, the wall time of every step (a
   cost that grows with the round shows there) and peak memory
   (ru_maxrss of each process), and the machine's memory in use above its
   level at the start, sampled every 0.5 s (MemTotal - MemAvailable: every
   process, Ray's workers and object store included; other work on the
   machine moves it too). The federation process's resident memory is split
   into its own (RssAnon) and the shared pages it maps (RssShmem: Ray's
   object store, which the machine's Shmem counts once), sampled too.

--data DIR federates on a data set generated before (OUT/data of an earlier
run with --out OUT) and skips step 1.

--profile N also prints the N functions with the most own time in the
federation (cProfile; it slows the run down).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import cProfile
import functools
import io
import json
import multiprocessing
import pstats
import resource
import tempfile
import threading
import time
from pathlib import Path

import torch

SCENARIO = "scale200"  # the default; --scenario names another


def kib_fields(path: str) -> dict[str, float]:
    """The ``Name: N kB`` lines of a /proc file, in MiB."""
    fields = {}
    for line in Path(path).read_text().splitlines():
        name, _, value = line.partition(":")
        if value.strip().endswith("kB"):
            fields[name] = float(value.split()[0]) / 1024
    return fields


def memory_now() -> dict[str, float]:
    """What is in use now [MiB]: on the machine (MemTotal - MemAvailable) and its shared memory
    (Shmem: Ray's object store lives there), and this process's resident memory split into its own
    (RssAnon) and the shared pages it has mapped (RssShmem: object-store pages it wrote or read)."""
    machine, own = kib_fields("/proc/meminfo"), kib_fields("/proc/self/status")
    return {
        "machine": machine["MemTotal"] - machine["MemAvailable"],
        "machine shared": machine["Shmem"],
        "process anon": own["RssAnon"],
        "process shared": own["RssShmem"],
    }


class MachineMemory:
    """Peaks of ``memory_now``'s figures, sampled; ``above_start_mib``: the machine's above the level at the start."""

    def __init__(self, period_s: float = 0.5) -> None:
        self.period_s = period_s
        self.start = memory_now()
        self.peak = dict(self.start)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def sample(self) -> dict[str, float]:
        now = memory_now()
        self.peak = {k: max(v, now[k]) for k, v in self.peak.items()}
        return now

    def _sample(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()

    def __enter__(self) -> "MachineMemory":
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()

    @property
    def start_mib(self) -> float:
        return self.start["machine"]

    @property
    def above_start_mib(self) -> float:
        return self.peak["machine"] - self.start["machine"]


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far [MiB] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# ------------------------------------------------------------------ data (child process)


def dataset_sizes(scenario: str, samples: int, test_samples: int):
    from crchfl_sumo.data.settings import DatasetConfig, TownSplit
    from crchfl_sumo.sumo.scenario import load_scenario

    towns = load_scenario(scenario).towns
    return DatasetConfig(
        towns=tuple(
            TownSplit(t.name, (samples,) * len(t.data_vehicles), (test_samples,) * len(t.test_vehicles)) for t in towns
        )
    )


def generate(scenario: str, data_dir: str, samples: int, test_samples: int, seed: int, metres_per_pixel: float) -> dict:
    """Child process: generate the data set; its wall time per stage and peak memory."""
    torch.set_num_threads(1)
    from crchfl_sumo.data.generation import generate_dataset
    from crchfl_sumo.sumo.scenario import load_scenario
    from crchfl_sumo.vision.world import WorldConfig

    stages: dict[str, float] = {}
    start = time.perf_counter()
    manifest = generate_dataset(
        load_scenario(scenario), data_dir, seed=seed, sizes=dataset_sizes(scenario, samples, test_samples),
        timings_s=stages, world=WorldConfig(metres_per_pixel=metres_per_pixel),
    )
    return {
        "total_s": time.perf_counter() - start,
        "stages_s": stages,
        "samples": manifest.samples,
        "train_shards": len(manifest.select("train")),
        "test_shards": len(manifest.select("test")),
        "peak_rss_mib": peak_rss_mib(),
    }


# ------------------------------------------------------------------ timing seams


class Stopwatch:
    """Wall seconds and calls per named part; ``wrap`` times a function under a name."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = collections.defaultdict(float)
        self.calls: dict[str, int] = collections.defaultdict(int)

    @contextlib.contextmanager
    def part(self, name: str, count: bool = True):
        """Time the block under ``name``; ``count``: it is a call of its own (not a piece of one)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - start
            self.calls[name] += count

    def wrap(self, name: str, function, count: bool = True):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            with self.part(name, count):
                return function(*args, **kwargs)

        return timed


class TimedTrainer:
    """The run's trainer with its training and evaluation timed."""

    def __init__(self, inner, watch: Stopwatch) -> None:
        self.inner = inner
        self.watch = watch
        self.initial_state = inner.initial_state
        self.evaluate = watch.wrap("evaluation", inner.evaluate)

    def train(self, *args):
        """The inner trainer's models as it yields them; the waits for them are the training's time
        (the loop folds each into its FedAvg between two waits)."""
        with self.watch.part("local training"):
            models = iter(self.inner.train(*args))
        end = object()  # a vehicle the loop does not need is None: not the end
        while True:
            with self.watch.part("local training", count=False):
                model = next(models, end)
            if model is end:
                return
            yield model


def timed_running_average(watch: Stopwatch):
    """services.RunningAverage with its folds timed as FedAvg (a result counts as one average)."""
    from crchfl_sumo.learning.aggregate import RunningAverage

    class Timed(RunningAverage):
        add = watch.wrap("FedAvg", RunningAverage.add, count=False)
        result = watch.wrap("FedAvg", RunningAverage.result)

    return Timed


class TimedClock:
    """A clock (context manager) whose link series are timed; everything else is the clock's own."""

    def __init__(self, inner, watch: Stopwatch) -> None:
        self.inner = inner
        self.watch = watch

    def __enter__(self):
        with self.watch.part("SUMO start"):
            self.inner.__enter__()
        for name in ("series", "handovers", "collected"):  # every way the run asks the clock for time
            if hasattr(self.inner, name):
                setattr(self.inner, name, self.watch.wrap("clock (all)", getattr(self.inner, name)))
        return self.inner

    def __exit__(self, *exc_info):
        return self.inner.__exit__(*exc_info)


@contextlib.contextmanager
def patched(owner, name: str, replacement):
    """``owner.name`` replaced for the duration (the benchmark's timing seams)."""
    original = getattr(owner, name)
    setattr(owner, name, replacement)
    try:
        yield original
    finally:
        setattr(owner, name, original)


# ------------------------------------------------------------------ federation


def run_config(args: argparse.Namespace, data_dir: Path):
    from crchfl_sumo.core.config import from_mapping
    from crchfl_sumo.federation.run_config import RunConfig

    federation = {"scheme": args.scheme, "edge_interval": 1, "cloud_interval": args.cloud_interval,
                  "cloud_rounds": args.rounds, "seed": args.seed, "download_handover": args.download_handover}
    if args.scheme == "crchfl":  # fixed hyper-parameters: the optimizer would spend the whole 1 TB budget
        federation["pretrain_batch"] = args.pretrain_batch
    mapping = {
        "scenario": args.scenario,
        "dataset": str(data_dir),
        "federation": federation,
        "ledger": {"rule": "physical", "model_size": "real", "sample_size": "measured", "budget_gb": 1024.0},
        "model": {"size": "compact"},
        "clock": {"kind": "sumo"},
    }
    return from_mapping(RunConfig, mapping, where="bench_scale")


def federate(args: argparse.Namespace, data_dir: Path, out_dir: Path) -> dict:
    from crchfl_sumo.federation import scheme_steps, services
    from crchfl_sumo.federation import run as run_module
    from crchfl_sumo.federation import run_data
    from crchfl_sumo.learning.trainers import TorchTrainer
    from crchfl_sumo.links.mobility import LinkModel
    from crchfl_sumo.sumo.simulation import Simulation

    watch = Stopwatch()
    config = run_config(args, data_dir)
    with watch.part("load data set"):
        inputs = run_data.read_inputs(config)
    rss_inputs = peak_rss_mib()
    stack = contextlib.ExitStack()
    if args.backend == "ray":
        from crchfl_sumo.core.backend import BackendConfig, Executor
        from crchfl_sumo.learning.trainers import RayTrainer

        executor = stack.enter_context(Executor(BackendConfig(kind="ray")))
        inner = RayTrainer(config.model, config.train, inputs.test, config.federation.seed, executor)
    else:
        inner = TorchTrainer(config.model, config.train, inputs.test, config.federation.seed)
    trainer = TimedTrainer(inner, watch)
    clocks = []

    def clock_factory():
        clocks.append(TimedClock(run_data.make_clock(config, inputs), watch))
        return clocks[-1]

    step_ends = [time.perf_counter()]
    step_parts = [dict(watch.seconds)]  # the stopwatch after every step
    step_rss = []
    step_memory = []  # memory_now() after every step

    def progress(info: dict) -> None:
        step_ends.append(time.perf_counter())
        step_parts.append(dict(watch.seconds))
        step_rss.append(peak_rss_mib())
        step_memory.append(memory_now())

    profiler = cProfile.Profile() if args.profile else None
    with stack:
        stack.enter_context(patched(Simulation, "step", watch.wrap("clock: SUMO step", Simulation.step)))
        stack.enter_context(patched(LinkModel, "step", watch.wrap("clock: link models", LinkModel.step)))
        # the cloud's FedAvg of the edge models (a step's), and the FedAvg folded in as the models come (the services')
        stack.enter_context(patched(scheme_steps, "fedavg", watch.wrap("FedAvg", scheme_steps.fedavg)))
        stack.enter_context(patched(services, "RunningAverage", timed_running_average(watch)))
        for name in ("append_logs", "_save_state", "_write_outputs"):  # run.py's per-step files
            if hasattr(run_module, name):
                timed = watch.wrap("checkpoint + outputs", getattr(run_module, name))
                stack.enter_context(patched(run_module, name, timed))
        saver = getattr(run_module, "BackgroundSaver", None)
        if saver is not None:  # the files are written beside the next step: what the loop waits for is apart
            for name in ("submit", "__exit__"):
                stack.enter_context(patched(saver, name, watch.wrap("save: waited", getattr(saver, name))))
        start = time.perf_counter()
        if profiler is not None:
            profiler.enable()
        summary = run_module.run_federation_dir(
            config, inputs, out_dir, trainer=trainer, clock_factory=clock_factory, progress=progress
        )
        if profiler is not None:
            profiler.disable()
        total_s = time.perf_counter() - start
    clock = clocks[-1].inner
    return {
        "config": config,
        "inputs": inputs,
        "summary": summary,
        "total_s": total_s,
        "watch": watch,
        "step_s": [b - a for a, b in zip(step_ends, step_ends[1:])],
        "step_parts": [{k: b.get(k, 0.0) - a.get(k, 0.0) for k in b} for a, b in zip(step_parts, step_parts[1:])],
        "step_rss_mib": step_rss,
        "step_memory": step_memory,
        "link_handovers": link_handovers(clock, inputs.vehicles),
        "clock_steps": int(round((clock.t_s - clock.start_s) / clock.step_s)) + 1,
        "rss_inputs_mib": rss_inputs,
        "profile": profiler,
        "background_saves": saver is not None,
    }


def link_handovers(clock, vehicles) -> tuple[int, int]:
    """Site-to-site changes of the clients' serving edge site over the simulated span the run used,
    and how many of them went back to the site served before within 5 s (mobility.ping_pongs)."""
    from crchfl_sumo.links.mobility import ping_pongs
    from crchfl_sumo.links.snapshots import Handover

    events = []
    for v in vehicles:
        link = clock.series(v, "edge", clock.start_s, clock.t_s)
        events += [Handover(float(t), v, int(a), int(b))
                   for t, a, b in zip(link.t_s[1:], link.site[:-1], link.site[1:]) if a != b and a >= 0 and b >= 0]
    return len(events), ping_pongs(events)


def ledger_figures(out_dir: Path, vehicles) -> dict:
    """Bytes per client and upload times from ledger.jsonl; membership changes between aggregations."""
    lines = (out_dir / "ledger.jsonl").read_text(encoding="utf-8").splitlines()
    records = [json.loads(line) for line in lines[1:]]
    clients = set(vehicles)
    wireless = [r for r in records if r["link"] == "wireless"]
    up = [r for r in wireless if r["sender"] in clients]
    down = [r for r in wireless if r["receiver"] in clients]
    edge_of: dict[str, list[str]] = collections.defaultdict(list)
    for r in up:
        edge_of[r["sender"]].append(r["receiver"])
    moves = sum(sum(1 for a, b in zip(edges, edges[1:]) if a != b) for edges in edge_of.values())
    return {
        "up_bytes": sum(r["size_bytes"] for r in up),
        "down_bytes": sum(r["size_bytes"] for r in down),
        "wireline_bytes": sum(r["size_bytes"] for r in records if r["link"] == "wireline"),
        "uploads": len(up),
        "downloads": len(down),
        "upload_s": [r["end_s"] - r["start_s"] for r in up],
        "download_s": [r["end_s"] - r["start_s"] for r in down],
        "edge_moves": moves,
    }


# ------------------------------------------------------------------ report


def report(args: argparse.Namespace, data: dict | None, fed: dict, out_dir: Path) -> None:
    inputs = fed["inputs"]
    clients = len(inputs.vehicles)
    print(f"scenario {args.scenario}, backend {args.backend}: {clients} clients over {len(inputs.edges)} edge sites; torch threads "
          f"{torch.get_num_threads()}")

    if data is None:
        print(f"\n1. data set: {args.data} (given, not generated)")
    else:
        report_data(args, data)
    report_federation(args, fed, out_dir)


def report_data(args: argparse.Namespace, data: dict) -> None:
    print(f"\n1. data set: {data['samples']} samples ({data['train_shards']} train shards x {args.samples}, "
          f"{data['test_shards']} test shards x {args.test_samples}), 64 x 128, in {data['total_s']:.1f} s")
    for stage in ("simulate", "world", "label", "render", "write"):
        seconds = data["stages_s"].get(stage, 0.0)
        print(f"   {stage:9s} {seconds:7.1f} s  {100 * seconds / data['total_s']:5.1f} %")
    other = data["total_s"] - sum(data["stages_s"].values())
    print(f"   {'other':9s} {other:7.1f} s  {100 * other / data['total_s']:5.1f} %  (scenario load, plan, manifest)")
    print(f"   peak memory of the generating process: {data['peak_rss_mib']:.0f} MiB")


def report_federation(args: argparse.Namespace, fed: dict, out_dir: Path) -> None:
    config, inputs, summary, watch = fed["config"], fed["inputs"], fed["summary"], fed["watch"]
    clients = len(inputs.vehicles)
    train_samples = sum(len(inputs.samples[v]) for v in inputs.vehicles)

    rounds, aggregations = summary["cloud_rounds"], summary["edge_aggregations"]
    hyper = summary["hyper"]
    total = fed["total_s"]
    print(f"\n2. federation: {config.federation.scheme}, edge_interval {hyper['edge_interval']}, cloud_interval "
          f"{hyper['cloud_interval']}, pretrain_batch {hyper['pretrain_batch']}; {train_samples} training samples, "
          f"{len(inputs.test)} test samples")
    print(f"   reached {rounds} cloud rounds, {aggregations} edge aggregations, {len(fed['step_s'])} steps "
          f"(stop: {summary['stop_reason']}), {summary['sim_time_s']:.1f} simulated s "
          f"({fed['clock_steps']} SUMO steps)")
    print(f"   wall {total:.1f} s (data set load {watch.seconds['load data set']:.1f} s before it):")
    s = watch.seconds
    clock_rest = s["clock (all)"] - s["clock: SUMO step"] - s["clock: link models"]
    parts = [
        ("SUMO start", s["SUMO start"], "libsumo load of the network and routes"),
        ("clock: SUMO step", s["clock: SUMO step"], f"{watch.calls['clock: SUMO step']} steps -> Frames"),
        ("clock: link models", s["clock: link models"], f"association, handover, rates of {clients} clients"),
        ("clock: series", clock_rest, f"{watch.calls['clock (all)']} link-series requests, per-vehicle appends"),
        ("local training", s["local training"], f"{watch.calls['local training']} calls x {clients} clients"
         + (" (and stage I's pretraining)" if hyper["pretrain_batch"] else "")),
        ("FedAvg", s["FedAvg"], f"{watch.calls['FedAvg']} averages"),
        ("evaluation", s["evaluation"], f"{watch.calls['evaluation']} test-set evaluations"),
    ]
    background = fed["background_saves"]
    saving = ("save: waited", s["save: waited"], "the loop waiting for the previous step's files") if background else (
        "checkpoint + outputs", s["checkpoint + outputs"], "checkpoint.pt, ledger, metrics, models, summary per step")
    parts.append(saving)
    loop = total - sum(seconds for _, seconds, _ in parts)
    parts.append(("loop (transfers, ledger)", loop, "the rest: transfers over the series, ledger, bookkeeping"))
    for name, seconds, note in parts:
        print(f"   {name:26s} {seconds:7.2f} s  {100 * seconds / total:5.1f} %  {note}")
    if background:
        print(f"   (written beside the loop: checkpoint + outputs {s['checkpoint + outputs']:.2f} s, not in the split)")
    print("   per step [s]:  step   wall  training  clock  FedAvg+eval  save waited [ms]  written [ms]  loop  peak MiB"
          "  after it: anon MiB  shared MiB  machine shared MiB")
    rows = zip(fed["step_s"], fed["step_parts"], fed["step_rss_mib"], fed["step_memory"])
    waited = saving[0]
    for k, (wall, part, rss, now) in enumerate(rows, start=1):
        known = ("local training", "clock (all)", "FedAvg", "evaluation", waited)
        print(f"                 {k:4d} {wall:6.2f} {part.get('local training', 0):9.2f} "
              f"{part.get('clock (all)', 0):6.2f} "
              f"{part.get('FedAvg', 0) + part.get('evaluation', 0):12.2f} {1e3 * part.get(waited, 0):16.1f} "
              f"{1e3 * part.get('checkpoint + outputs', 0):13.1f} "
              f"{wall - sum(part.get(x, 0) for x in known):5.2f} {rss:9.0f} {now['process anon']:19.0f} "
              f"{now['process shared']:11.0f} {now['machine shared']:19.0f}")

    ledger = ledger_figures(out_dir, inputs.vehicles)
    per_round = max(rounds, 1)
    mib = 1024 * 1024
    print("\n3. per client")
    print(f"   local training {1e3 * s['local training'] / (clients * max(aggregations, 1)):.1f} ms per client per "
          f"edge aggregation ({train_samples // clients} samples, {hyper['edge_interval']} epoch); "
          f"{1e3 * s['local training'] / (clients * per_round):.1f} ms per client per cloud round")
    print(f"   SUMO clock {1e3 * s['clock (all)'] / (clients * per_round):.1f} ms per client per cloud round; "
          f"whole federation {1e3 * total / (clients * per_round):.1f} ms per client per cloud round")
    print(f"   model {summary['model_bytes'] / mib:.2f} MiB (real size, compact); per client per cloud round: "
          f"up {ledger['up_bytes'] / clients / per_round / mib:.2f} MiB, down "
          f"{ledger['down_bytes'] / clients / per_round / mib:.2f} MiB wireless "
          f"({ledger['uploads']} uploads, {ledger['downloads']} downloads in all); wireline "
          f"{ledger['wireline_bytes'] / mib:.1f} MiB in all")
    if ledger["upload_s"]:
        up_s, down_s = sorted(ledger["upload_s"]), sorted(ledger["download_s"])
        print(f"   simulated transfer time: upload median {up_s[len(up_s) // 2]:.2f} s (max {up_s[-1]:.2f} s), "
              f"download median {down_s[len(down_s) // 2]:.2f} s (max {down_s[-1]:.2f} s)")
    stragglers = [json.loads(line) for line in (out_dir / "stragglers.jsonl").read_text().splitlines()]
    reasons = collections.Counter(x["reason"] for x in stragglers)
    handovers, back = fed["link_handovers"]
    print(f"   handovers: {handovers} site-to-site changes of the clients' serving site over the run's "
          f"{summary['sim_time_s']:.0f} simulated s (one per client every "
          f"{clients * summary['sim_time_s'] / max(handovers, 1):.0f} s; {back} back to the previous site within 5 s); "
          f"{ledger['edge_moves']} changes of edge membership between aggregations (new_edge policy)")
    print(f"   stragglers: {len(stragglers)} {dict(reasons)}")
    print(f"   failed downloads: {summary['downloads_failed']}/{summary['downloads']}; failed uploads: "
          f"{summary['uploads_failed']}/{summary['uploads']}; relayed downloads: {summary['relayed_transfers']} "
          f"({summary['relay_bytes'] / mib:.1f} MiB over the wireline, "
          f"federation.download_handover = {config.federation.download_handover!r})")

    checkpoint = out_dir / "checkpoint.pt"
    print("\n4. memory")
    print(f"   peak of the federation process: {peak_rss_mib():.0f} MiB (after loading the data set: "
          f"{fed['rss_inputs_mib']:.0f} MiB)")
    machine = fed["machine"]
    print(f"   the machine during the federation: peak {machine.above_start_mib:.0f} MiB in use above the "
          f"{machine.start_mib:.0f} MiB at its start (every process; {clients} clients: "
          f"{machine.above_start_mib / clients:.1f} MiB a client)")
    print(f"   sampled peaks: federation process {machine.peak['process anon']:.0f} MiB its own (RssAnon) + "
          f"{machine.peak['process shared']:.0f} MiB shared pages mapped (RssShmem); the machine's shared memory "
          f"(Ray's object store) {machine.peak['machine shared'] - machine.start['machine shared']:.0f} MiB above "
          f"its start")
    images = sum(x.images.nelement() * x.images.element_size() for x in inputs.samples.values())
    print(f"   training images in memory {images / mib:.1f} MiB; checkpoint.pt {checkpoint.stat().st_size / mib:.1f} "
          f"MiB; ledger.jsonl {(out_dir / 'ledger.jsonl').stat().st_size / 1024:.0f} KiB")

    if fed["profile"] is not None:
        text = io.StringIO()
        pstats.Stats(fed["profile"], stream=text).sort_stats("tottime").print_stats(args.profile)
        print("\n5. profile (own time)\n" + text.getvalue())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=8, help="training samples per client (default 8)")
    parser.add_argument("--test-samples", type=int, default=50, help="samples per test vehicle (default 50)")
    parser.add_argument("--scheme", choices=("hfl", "crchfl"), default="hfl")
    parser.add_argument("--rounds", type=int, default=3, help="cloud rounds (default 3)")
    parser.add_argument("--cloud-interval", type=int, default=2, help="edge aggregations per cloud round (default 2)")
    parser.add_argument("--pretrain-batch", type=int, default=200, help="crchfl: samples uploaded for pretraining")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--download-handover", choices=("relay", "restart", "drop"), default="relay",
                        help="what a download does when its vehicle changes edge (default relay)")
    parser.add_argument("--out", type=Path, help="keep the data set and the run here (default: a temp folder)")
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="print the N costliest functions")
    parser.add_argument("--scenario", default=SCENARIO, help="a built-in name or a scenario folder (default scale200)")
    parser.add_argument("--backend", choices=("local", "ray"), default="local", help="where the clients train")
    parser.add_argument("--metres-per-pixel", type=float, default=0.1,
                        help="the ground texture's resolution (default 0.1; scale1000's 20 towns need 0.15)")
    parser.add_argument("--data", type=Path,
                        help="federate on this data set (OUT/data of an earlier run of this script) instead of "
                             "generating one")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.out or Path(tmp)
        data_dir, out_dir = args.data or root / "data", root / "run"
        data = None
        if args.data is None:
            with multiprocessing.get_context("spawn").Pool(1) as pool:
                data = pool.apply(generate, (args.scenario, str(data_dir), args.samples, args.test_samples, args.seed,
                                                args.metres_per_pixel))
        with MachineMemory() as machine:
            fed = federate(args, data_dir, out_dir)
        fed["machine"] = machine
        report(args, data, fed, out_dir)


if __name__ == "__main__":
    main()
