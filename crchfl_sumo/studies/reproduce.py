"""`crchfl-sumo reproduce [--quick] [--out DIR] [--seeds N] [--resume] [--jobs N]`: the paper's experiments B and D.

One results folder holds every part (each written by its owning module):

  reproduce.json              the resolved settings, seeds and package versions
  timings.json                wall and CPU seconds of every finished part (also: which parts are finished)
  data/                       the data set, generated once and shared by every run
  configs/NAME.toml           the run config each federated run was started with
  centralized/seed-S/         the centralized upper bound (learning.centralized.train_centralized)
  runs/SCHEME/seed-S/         experiment B: CRCHFL, HFL and SFL under one budget (federation/run.py's folder)
  ablation/ie-K/seed-S/       experiment D: CRCHFL with edge_interval fixed to K
  drives/ROUTE/LABEL/         closed loop: each scheme's best model, the centralized
                              model and the scripted reference drive ROUTE (driving/drive.py)
  figures/, report.md, summary.json   written by studies/report.py from the folders above alone

Resumable: a part recorded in timings.json is not redone; an unfinished
federated run continues from its checkpoint; an unfinished centralized run
or drive starts over. ``--jobs N`` runs N independent parts at a time in
worker processes; only this process writes timings.json.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any, Mapping

from crchfl_sumo.core.atomic import atomic_write_text, remove_stale_temporaries
from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.core.config import changed_keys_text, to_mapping, toml_text
from crchfl_sumo.core.cpus import WAIT_POLICY, available_cpus, threads_per_part
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.json_files import read_json, write_json
from crchfl_sumo.core.outputs import prepare_output_dir
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.core.result_files import BEST_MODEL_FILE, MODEL_FILE, SUMMARY_FILE, TIMINGS_FILE
from crchfl_sumo.studies.reproduce_plan import (
    CENTRALIZED,
    CENTRALIZED_DAGGER,
    REFERENCE,
    ReproduceConfig,
    ReproductionPart,
    budget_key,
    dagger_parts,
    drive_parts,
    for_scenario,
    load_reproduce_config,
    plan_parts,
    replanned,
    run_config,
    run_mapping,
)

log = logging.getLogger(__name__)


# ------------------------------------------------------------------ run configs (pure)


# ------------------------------------------------------------------ the parts


def best_seed(summaries: Mapping[int, Mapping[str, Any]], key: str = "balanced_accuracy") -> int:
    """The seed whose run reached the highest ``key`` (ties: the smallest seed; None counts lowest)."""
    if not summaries:
        raise CrchflError("no finished run to pick a model from; run the federated parts first")
    return max(sorted(summaries), key=lambda s: -math.inf if summaries[s].get(key) is None else summaries[s][key])


# ------------------------------------------------------------------ orchestration


def reproduce(
    config: ReproduceConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: Progress | None = None,
    jobs: int = 1,
    backend: BackendConfig | None = None,
) -> dict[str, Any]:
    """Run (or finish) every part of ``config`` into ``out_dir``, then write the report; returns summary.json.

    ``jobs`` > 1 runs that many parts at a time, each in its own process
    (libsumo holds one simulation per process) with ``available CPUs // jobs``
    torch threads: first the data set, then the centralized, experiment B
    and experiment D parts, then the drives. The results are those of
    ``jobs`` = 1 (each part is seeded on its own), except that training
    drifts a little when the thread count differs (float sums in another order).

    ``backend`` of kind "ray" runs every part as a Ray task (one CPU, one torch thread each;
    ``jobs`` is ignored) on a local Ray runtime or the cluster at ``backend.address``; every
    node must see ``out_dir`` at the same path (a shared file system). The folders, resume and
    results are the local backend's with one thread per part.
    """
    if jobs < 1:
        raise CrchflError(f"--jobs: {jobs} must be >= 1 (parts run at a time)")
    on_ray = backend is not None and backend.kind == "ray"
    out_dir = Path(out_dir).resolve()
    _start(config, out_dir, resume)
    parts = plan_parts(config)
    total = len(parts) + len(dagger_parts(config)) + len(drive_parts(config))
    done = 0  # parts finished, for progress

    def run_stage(stage: list[ReproductionPart]) -> None:
        nonlocal done
        todo = [part for part in stage if not _finished(part, out_dir)]

        def finished(i: int, elapsed: dict[str, float]) -> None:
            nonlocal done
            _record(out_dir, todo[i], elapsed)
            done += 1
            report(progress, "part", done, total, part=todo[i].key)

        done += len(stage) - len(todo)
        if on_ray and todo:
            report(progress, "part", done, total, part=f"{len(todo)} parts as Ray tasks")
            with Executor(backend) as executor:
                executor.map(_timed_part, [(config, out_dir, p, RAY_PART) for p in todo], isolate=True,
                             on_result=finished)
            return
        if jobs == 1 or len(todo) < 2:
            for part in todo:
                report(progress, "part", done, total, part=part.key)
                _record(out_dir, part, _timed_part(config, out_dir, part, 1))
                done += 1
            return
        report(progress, "part", done, total, part=f"{len(todo)} parts, {jobs} at a time")
        with Executor(BackendConfig(num_cpus=jobs)) as executor:  # a killed part is retried (resumed) twice
            executor.map(_timed_part, [(config, out_dir, p, jobs) for p in todo], isolate=True, on_result=finished)

    run_stage(parts[:1])  # the data set, read by every other part
    run_stage(parts[1:])
    run_stage(dagger_parts(config))  # refines the centralized models just trained
    run_stage(drive_parts(config))  # which seed's model drives is known only now
    report(progress, "part", total, total, part="report")
    from crchfl_sumo.studies.report import write_report

    return write_report(out_dir)


def reproduce_command(
    quick: bool = False,
    out_dir: str | Path | None = None,
    seeds: int | None = None,
    resume: bool = False,
    config_path: str | Path | None = None,
    progress: Progress | None = None,
    jobs: int = 1,
    backend: str | None = None,
    address: str | None = None,
    scenario: str | None = None,
) -> tuple[Path, dict[str, Any]]:
    """What `crchfl-sumo reproduce [--quick] [--out DIR] [--seeds N] [--resume] [--config TOML] [--jobs N]
    [--backend local|ray] [--address A]` does.

    ``config_path`` replaces the preset; ``scenario`` runs it in another scenario (reproduce_plan.for_scenario);
    DIR defaults to results/NAME (NAME: the config's name).
    Returns the results folder and its summary.json.
    """
    if address is not None and backend != "ray":
        raise CrchflError("--address joins a Ray cluster: give it with --backend ray")
    chosen = BackendConfig(kind=backend or "local", address=address or "")
    preset = "quick" if quick else "full"
    config = load_reproduce_config(config_path if config_path is not None else preset, seeds)
    if scenario is not None:
        config = for_scenario(config, scenario)
    out_dir = Path(out_dir) if out_dir is not None else Path("results") / config.name
    prepare_output_dir(out_dir, "reproduce", flag="reproduce --out", resumable=True)
    return out_dir, reproduce(config, out_dir, resume, progress, jobs, chosen)


def _start(config: ReproduceConfig, out_dir: Path, resume: bool) -> None:
    """Write reproduce.json, or check that a resumed folder was started with the same settings."""
    path = out_dir / "reproduce.json"
    settings = json.loads(json.dumps(to_mapping(config)))  # tuples as JSON reads them back
    if path.exists():
        if not resume:
            raise CrchflError(
                f"{out_dir} already holds a reproduction; pass --resume to finish it or choose another --out"
            )
        earlier = json.loads(path.read_text(encoding="utf-8"))
        if earlier.get("config") != settings:
            moved = changed_keys_text(earlier.get("config") or {}, settings)
            raise CrchflError(
                f"{path}: started with other settings (its 'config' differs in {moved}: a default may have "
                "changed since); resume with the same preset, --seeds and --config, or choose another --out"
            )
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    record = {
        "config": settings,
        "seeds": config.seed_list,
        "ablation_seeds": config.ablation_seed_list,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "environment": environment(),
    }
    write_json(path, record)


def environment() -> dict[str, Any]:
    """Package versions and the machine: what the report states next to the running times."""
    import os
    import platform
    from importlib import metadata

    import torch

    from crchfl_sumo.learning.devices import native_bfloat16

    versions = {}
    packages = ("crchfl-sumo", "torch", "numpy", "matplotlib", "cvxpy", "eclipse-sumo", "libsumo", "h5py",
                "opencv-python-headless")
    for name in packages:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "available_cpus": available_cpus(),
        "torch_threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get(WAIT_POLICY, "default"),
        "cuda": torch.cuda.is_available(),
        "bfloat16_cpu": native_bfloat16("cpu"),  # where train.precision "auto" trains in bfloat16
        "versions": versions,
    }


def read_timings(out_dir: Path) -> dict[str, dict[str, float]]:
    path = Path(out_dir) / TIMINGS_FILE
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def _finished(part: ReproductionPart, out_dir: Path) -> bool:
    """Finished: timings.json records the part and its folder exists."""
    if part.key in read_timings(out_dir) and (out_dir / part.key).exists():
        log.info("%s: finished earlier, kept", part.key)
        return True
    return False


# The ``jobs`` a part runs with as a Ray task (recorded in timings.json as such).
RAY_PART = 0


def _timed_part(config: ReproduceConfig, out_dir: Path, part: ReproductionPart, jobs: int) -> dict[str, float]:
    """Run one part (in this process, as a worker process of ``jobs`` > 1, or as a Ray task: ``jobs``
    RAY_PART); its wall and CPU seconds."""
    if jobs > 1 or jobs == RAY_PART:
        import torch

        # the parts share the cores; a Ray task holds one CPU
        torch.set_num_threads(1 if jobs == RAY_PART else threads_per_part(jobs))
    log.info("%s: starting", part.key)
    if (out_dir / part.key).is_dir():  # a part killed earlier starts again (or resumes) without its temporaries
        remove_stale_temporaries(out_dir / part.key, recursive=True)
    start_unix, start_s, start_cpu_s = time.time(), time.perf_counter(), time.process_time()
    if part.kind == "dataset":
        _make_dataset(config, out_dir / part.key)
    elif part.kind == "centralized":
        _centralized(config, out_dir, part.seed, out_dir / part.key)
    elif part.kind == "dagger":
        _dagger(config, out_dir, part)
    elif part.kind == "drive":
        _drive_part(config, out_dir, part)
    elif part.kind == "bench":
        _bench_part(config, out_dir, part)
    else:
        _federated(config, out_dir, part)
    # CPU time beside wall time: on a shared machine it is disturbed less by other jobs; the start
    # time lets the report tell the elapsed time from the sum of parts that ran side by side
    return {
        "wall_s": round(time.perf_counter() - start_s, 3),
        "cpu_s": round(time.process_time() - start_cpu_s, 3),
        "start_unix": round(start_unix, 3),
        "jobs": jobs,
    }


def _record(out_dir: Path, part: ReproductionPart, elapsed: dict[str, float]) -> None:
    """Mark ``part`` finished in timings.json (only the main process writes it)."""
    timings = read_timings(out_dir)
    timings[part.key] = elapsed
    write_json(out_dir / TIMINGS_FILE, timings)
    log.info("%s: done in %.1f s (CPU %.1f s)", part.key, elapsed["wall_s"], elapsed["cpu_s"])


def _make_dataset(config: ReproduceConfig, data_dir: Path) -> None:
    from crchfl_sumo.data.generation import generate_dataset
    from crchfl_sumo.sumo.scenario import load_scenario

    gen = config.generate
    generate_dataset(
        load_scenario(config.scenario), data_dir, gen.seed, gen.dataset, gen.raster, gen.world, gen.expert, command=gen.command
    )


def _centralized(config: ReproduceConfig, out_dir: Path, seed: int, folder: Path) -> None:
    """The upper bound: one model trained on every vehicle's data; summary.json beside learning/centralized.py's files."""
    from crchfl_sumo.data.dataset import load_samples
    from crchfl_sumo.data.manifest import read_manifest
    from crchfl_sumo.learning.centralized import train_centralized

    run = run_config(run_mapping(config, config.schemes[0], seed, out_dir / "data"), "reproduce.run")
    train = load_samples(out_dir / "data", "train")
    test = load_samples(out_dir / "data", "test")
    manifest = read_manifest(out_dir / "data")
    manifest.check_model(run.model, str(out_dir / "data"))
    records = train_centralized(
        train, test, config.centralized_epochs, folder, run.model, run.train, seed,
        drive_settings=manifest.drive_settings(str(out_dir / "data" / "manifest.json")),
        resume=True,  # a part killed after some epochs continues from its checkpoint
    )
    # the best epoch as the federation ranks its models: balanced accuracy, then accuracy, then loss
    best = max(records, key=lambda r: (r["balanced_accuracy"], r["accuracy"], -r["loss"]))
    summary = {
        "scheme": CENTRALIZED,
        "seed": seed,
        "epochs": len(records),
        "train_samples": len(train),
        "test_samples": len(test),
        "best_accuracy": best["accuracy"],
        "best_loss": best["loss"],
        "best_epoch": best["epoch"],
        "final_accuracy": records[-1]["accuracy"],
        "final_loss": records[-1]["loss"],
        "balanced_accuracy": best["balanced_accuracy"],
        "final_balanced_accuracy": records[-1]["balanced_accuracy"],
        "best_steer_error": best["steer_error"],
        "best_throttle_error": best["throttle_error"],
        "best_brake_error": best["brake_error"],
        "best_recall": best["recall"],
        "best_confusion": best["confusion"],
        "baselines": {"always_straight": best["always_straight"]},
    }
    write_json(folder / SUMMARY_FILE, summary)


def _dagger(config: ReproduceConfig, out_dir: Path, part: ReproductionPart) -> None:
    """DAgger on one seed's centralized model, driving in the benchmark's towns (its own route seed)."""
    from crchfl_sumo.data.dataset import load_samples
    from crchfl_sumo.driving.dagger import dagger_iterations

    train, test = load_samples(out_dir / "data", "train"), load_samples(out_dir / "data", "test")
    dagger_iterations(
        model_for(out_dir, CENTRALIZED, part.seed), train, test, out_dir / part.key, config.bench_towns,
        config.dagger, config.dagger_iterations, config.dagger_epochs, part.seed,
        learning_rate=config.dagger_learning_rate,
    )


def _federated(config: ReproduceConfig, out_dir: Path, part: ReproductionPart) -> None:
    """One federated run through run.run_command; an unfinished one resumes from its checkpoint."""
    from crchfl_sumo.driving.vehicle_dagger import labeller_factory
    from crchfl_sumo.federation.run import run_command

    mapping = run_mapping(config, part.scheme, part.seed, out_dir / "data", part.edge_interval, part.budget_gb)
    name = part.key.replace("/", "_")
    config_path = out_dir / "configs" / f"{name}.toml"
    atomic_write_text(config_path, toml_text(mapping))
    run_command(config_path, out_dir / part.key, resume=True, labeller_factory=labeller_factory)


def _drive_part(config: ReproduceConfig, out_dir: Path, part: ReproductionPart) -> None:
    from crchfl_sumo.driving.route_drive import drive_route

    model = None if part.scheme == REFERENCE else model_for(out_dir, part.scheme)
    drive_route(
        model, None, part.route, out_dir / part.key, seed=config.drive_seed, max_s=config.drive_max_s,
        config=config.drive, video=config.drive_video, steer_decoding=config.steer_decoding,
    )


def _bench_part(config: ReproduceConfig, out_dir: Path, part: ReproductionPart) -> None:
    """The closed-loop benchmark for one model (its own process already: the episodes run one by one)."""
    from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark

    if part.scheme == REFERENCE:
        model = None
    elif part.budget_gb is not None:
        model = budget_model_for(config, out_dir, part.scheme, part.budget_gb, part.seed)
    else:
        model = model_for(out_dir, part.scheme, part.seed)
    run_benchmark(
        model, out_dir / part.key, episodes=config.bench_episodes, jobs=1, seed=config.bench_seed,
        towns=config.bench_towns, config=BenchConfig(tasks=config.bench_tasks, steer_decoding=config.steer_decoding),
    )


def model_for(out_dir: Path, label: str, seed: int | None = None) -> Path:
    """The model that drives for ``label``: the run_model_file of the scheme's best seed (or of ``seed``);
    for the centralized bound, the last epoch's checkpoint of the seed that ended best (or of ``seed``);
    for the centralized bound refined by DAgger, its last iteration's, chosen the same way."""
    from crchfl_sumo.federation.run import run_model_file

    centralized = label in (CENTRALIZED, CENTRALIZED_DAGGER)
    folder = Path(out_dir) / (label if centralized else f"runs/{label}")
    if seed is not None:
        summary_path = folder / f"seed-{seed}" / SUMMARY_FILE
        summary = read_json(summary_path) if not centralized and summary_path.exists() else {}
        return folder / f"seed-{seed}" / (MODEL_FILE if centralized else run_model_file(summary))
    summaries = {}
    for path in sorted(folder.glob(f"seed-*/{SUMMARY_FILE}")):
        summaries[int(path.parent.name.split("-", 1)[1])] = read_json(path)
    if label == CENTRALIZED_DAGGER:  # the last iteration's model of the seed that ended best
        last = {seed: summary["iterations"][-1] for seed, summary in summaries.items()}
        return folder / f"seed-{best_seed(last)}" / MODEL_FILE
    if label == CENTRALIZED:
        return folder / f"seed-{best_seed(summaries, 'final_balanced_accuracy')}" / MODEL_FILE
    seed = best_seed(summaries)
    return folder / f"seed-{seed}" / run_model_file(summaries[seed])


def budget_model_for(config: ReproduceConfig, out_dir: Path, scheme: str, budget_gb: float, seed: int) -> Path:
    """The model of a scheme and seed at a budget of the curve below the runs' own: the best model of its run
    at that budget (a scheme the optimizer plans), else the best within that budget of experiment B's run."""
    from crchfl_sumo.federation.run import mark_model_file

    if replanned(config, scheme):
        return Path(out_dir) / budget_key("runs", scheme, budget_gb, seed) / BEST_MODEL_FILE
    return Path(out_dir) / "runs" / scheme / f"seed-{seed}" / mark_model_file(budget_gb)
