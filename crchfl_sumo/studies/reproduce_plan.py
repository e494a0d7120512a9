"""What a reproduction runs: its settings (a preset or a TOML), every part in order, each federated run's config.

Pure planning, no side effects; reproduce.py carries the plan out.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from crchfl_sumo.accounting.ledger import LedgerConfig, gb_label
from crchfl_sumo.core.config import deep_merge, from_mapping, read_toml
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_DRIVE_S, MAX_EPOCHS, SEED_MAX, check_range
from crchfl_sumo.core.resources import experiments_dir
from crchfl_sumo.core.schemes import CENTRALIZED, CENTRALIZED_DAGGER, REFERENCE, SCHEMES
from crchfl_sumo.data.generation import GenerateConfig
from crchfl_sumo.data.settings import TownSplit
from crchfl_sumo.driving.dagger_settings import FINE_TUNE_LEARNING_RATE, MAX_ITERATIONS, DaggerConfig
from crchfl_sumo.driving.drive import DriveConfig
from crchfl_sumo.driving.drive_bench_tasks import DEFAULT_TOWNS, TASK_NAMES, task_by_name
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.learning.settings import DEFAULT_STEER_DECODING, check_steer_decoding
from crchfl_sumo.planning.settings import MAX_INTERVAL

PRESETS = {"quick": "reproduce_quick.toml", "full": "reproduce_full.toml"}  # in resources.experiments_dir()


@dataclass(frozen=True)
class ReproduceConfig:
    """What `reproduce` runs (TOML: reproduce_quick.toml / reproduce_full.toml).

    name: a label for the report ("quick", "full", ...).
    scenario: the scenario the data set is generated in and the federation runs on.
    seeds: federated runs per scheme (seeds first_seed, first_seed + 1, ...).
    schemes: the schemes of experiment B.
    ablation_edge_intervals: experiment D: CRCHFL with edge_interval fixed to each
        of these (allocation.fix_edge_interval); empty = no ablation.
    ablation_seeds: seeds per ablation setting (the first ones of ``seeds``; at most ``seeds``).
    centralized_epochs: epochs of the centralized upper bound (0 = none); one per seed.
    dagger_iterations: DAgger iterations that refine each centralized model (`crchfl-sumo dagger`:
        the model drives routes of the benchmark's towns drawn with the DAgger seed, the route
        expert labels where it would step in, the model is fine-tuned); the refined model drives and
        is benched as ``centralized_dagger``. 0 = none.
    dagger_epochs, dagger_learning_rate: the fine-tuning of each DAgger iteration.
    dagger: the DAgger drives (DaggerConfig: tasks, episodes, route seed, labelling).
    drive_routes: named routes (scenarios/drive_routes.toml) each model drives; empty = no drives.
    drive_max_s: simulated seconds a drive may last at most.
    drive_seed: SUMO seed of the drives (the same traffic for every model).
    drive_video: also write each drive's MP4.
    drive: the drives' settings (DriveConfig: warm-up, insertion, end conditions).
    bench_episodes: episodes per task and town of the closed-loop benchmark (`drive-bench`) that
        each scheme's best model, the centralized model and the reference drive; 0 = no benchmark.
    bench_towns, bench_tasks, bench_seed: the benchmark's towns, task suites and seed.
    steer_decoding: how the drives and the benchmark turn each model's steer scores into a steer
        (learning.settings.STEER_DECODINGS; "auto": the DAC for 7 classes, the likeliest bin and its
        neighbours weighted by probability for a finer head).
    bench_all_seeds: the benchmark drives every seed's model (each scheme's best_model.pt of
        every seed, every centralized seed's last epoch), so that the report gives the spread over
        seeds; false: only the model of the seed with the highest balanced accuracy drives.
    budgets_gb: experiment E, the budget curve: balanced accuracy and driving score against the byte
        budget, at each of these budgets [GB] (each at most the runs' budget_gb; empty = no curve).
        A scheme the optimizer plans (CRCHFL) runs again at each smaller budget
        (``budget_curve/runs/SCHEME/gb-B/seed-S``); the others' schedules do not depend on the
        budget, so their smaller budgets are read from their full run (its [ledger] marks_gb).
        With a benchmark, every seed's model at every budget drives (needs bench_all_seeds).
    accuracy_targets: balanced accuracies whose bytes each scheme's runs needed (bytes-to-accuracy).
    generate: the data set (GenerateConfig: seed, [generate.dataset] sizes, camera, expert).
    run: settings laid over every built-in scheme config (scenarios/experiments/SCHEME.toml):
        a partial run config, e.g. ``[run.ledger]``, ``[run.train]``, ``[run.clock]``.
        ``scenario`` and ``dataset`` are set by reproduce, ``federation.seed`` per run.
    """

    name: str = "full"
    scenario: str = "paper"
    seeds: int = 3
    first_seed: int = 0
    schemes: tuple[str, ...] = SCHEMES
    ablation_edge_intervals: tuple[int, ...] = (2, 3, 4)
    ablation_seeds: int = 3
    centralized_epochs: int = 20
    dagger_iterations: int = 0
    dagger_epochs: int = 3
    dagger_learning_rate: float = FINE_TUNE_LEARNING_RATE
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    drive_routes: tuple[str, ...] = ("town01_right_left", "town02_south_loop")
    drive_max_s: float = 120.0
    drive_seed: int = 0
    drive_video: bool = False
    drive: DriveConfig = field(default_factory=DriveConfig)
    bench_episodes: int = 5
    bench_towns: tuple[str, ...] = DEFAULT_TOWNS
    bench_tasks: tuple[str, ...] = TASK_NAMES
    bench_seed: int = 0
    bench_all_seeds: bool = False
    steer_decoding: str = DEFAULT_STEER_DECODING
    budgets_gb: tuple[float, ...] = ()
    accuracy_targets: tuple[float, ...] = (0.5, 0.6, 0.7)
    generate: GenerateConfig = field(default_factory=GenerateConfig)
    run: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 1 <= self.seeds <= 100:
            raise CrchflError(f"reproduce.seeds: {self.seeds} must be in 1 .. 100 (runs per scheme)")
        if not 0 <= self.ablation_seeds <= 100:
            raise CrchflError(f"reproduce.ablation_seeds: {self.ablation_seeds} must be in 0 .. 100")
        last = self.first_seed + max(self.seeds, self.ablation_seeds) - 1
        if self.first_seed < 0 or last > SEED_MAX:
            raise CrchflError(
                f"reproduce.first_seed: {self.first_seed} makes seeds {self.first_seed} .. {last}; "
                f"seeds are integers in 0 .. {SEED_MAX} (2**31 - 1)"
            )
        unknown = sorted(set(self.schemes) - set(SCHEMES))
        if unknown or not self.schemes or len(set(self.schemes)) != len(self.schemes):
            raise CrchflError(
                f"reproduce.schemes: {list(self.schemes)}; list each of {', '.join(SCHEMES)} at most once"
            )
        if any(not 2 <= k <= MAX_INTERVAL for k in self.ablation_edge_intervals):
            raise CrchflError(
                f"reproduce.ablation_edge_intervals: {list(self.ablation_edge_intervals)}; each must be in "
                f"2 .. {MAX_INTERVAL} (the paper requires 0 < cloud_interval < edge_interval; each becomes "
                "allocation.fix_edge_interval)"
            )
        check_range(self.centralized_epochs, "reproduce.centralized_epochs", 0, MAX_EPOCHS,
                    "a number of epochs (0 = none)")
        check_range(self.dagger_iterations, "reproduce.dagger_iterations", 0, MAX_ITERATIONS,
                    "a number of iterations (0 = none)")
        check_range(self.dagger_epochs, "reproduce.dagger_epochs", 1, MAX_EPOCHS, "a number of epochs")
        check_range(self.dagger_learning_rate, "reproduce.dagger_learning_rate", 0, 1, "a learning rate", lo_open=True)
        if self.dagger_iterations and not self.centralized_epochs:
            raise CrchflError("reproduce.dagger_iterations: DAgger refines the centralized models; "
                              "set centralized_epochs > 0 or dagger_iterations = 0")
        if not 0 <= self.bench_episodes <= 10_000:
            raise CrchflError(
                f"reproduce.bench_episodes: {self.bench_episodes} must be in 0 .. 10000 (0 = no benchmark)"
            )
        if self.bench_episodes and (not self.bench_towns or not self.bench_tasks):
            raise CrchflError("reproduce.bench_towns / bench_tasks: name at least one of each, or set bench_episodes = 0")
        for task in self.bench_tasks:
            task_by_name(task)
        check_steer_decoding(self.steer_decoding, "reproduce.steer_decoding")
        if self.bench_seed < 0:
            raise CrchflError(f"reproduce.bench_seed: {self.bench_seed} must be >= 0")
        check_range(self.drive_max_s, "reproduce.drive_max_s", 0, MAX_DRIVE_S, "simulated seconds", lo_open=True)
        for key, instead in (("scenario", "reproduce.scenario"), ("dataset", "reproduce.generate")):
            if key in self.run:
                raise CrchflError(f"reproduce.run.{key}: set by reproduce itself; remove it (use {instead})")
        if "seed" in self.run.get("federation", {}):
            raise CrchflError("reproduce.run.federation.seed: set per run from reproduce.seeds; remove it")
        budgets = list(self.budgets_gb)
        if any(not math.isfinite(b) or b <= 0 for b in budgets) or budgets != sorted(set(budgets)):
            raise CrchflError(f"reproduce.budgets_gb: {budgets}; give positive budgets in GB, increasing, each once")
        for target in self.accuracy_targets:
            check_range(target, "reproduce.accuracy_targets", 0, 1, "a balanced accuracy", lo_open=True)
        if budgets and self.bench_episodes and not self.bench_all_seeds:
            raise CrchflError("reproduce.budgets_gb: the budget curve drives every seed's model; set "
                              "bench_all_seeds = true (or bench_episodes = 0, or budgets_gb = [])")
        for scheme in self.schemes:  # every run config must be valid before anything starts
            run_config(run_mapping(self, scheme, self.first_seed, Path("data")), f"reproduce.run ({scheme})")
            if budgets and budgets[-1] > run_budget_gb(self, scheme):
                raise CrchflError(
                    f"reproduce.budgets_gb: {budgets[-1]:g} exceeds the {scheme} runs' budget_gb = "
                    f"{run_budget_gb(self, scheme):g}; the curve's budgets lie within it"
                )
            for budget in smaller_budgets(self, scheme) if replanned(self, scheme) else ():
                run_config(run_mapping(self, scheme, self.first_seed, Path("data"), budget_gb=budget),
                           f"reproduce.budgets_gb ({scheme} at {budget:g} GB)")

    @property
    def seed_list(self) -> list[int]:
        return list(range(self.first_seed, self.first_seed + self.seeds))

    @property
    def ablation_seed_list(self) -> list[int]:
        return self.seed_list[: min(self.ablation_seeds, self.seeds)] if self.ablation_edge_intervals else []


def load_reproduce_config(preset_or_path: str | Path, seeds: int | None = None) -> ReproduceConfig:
    """A preset ("quick", "full") or a TOML file; ``seeds`` overrides the file's ``seeds``."""
    preset = PRESETS.get(str(preset_or_path))
    path = experiments_dir() / preset if preset else Path(preset_or_path)
    mapping = read_toml(path)
    if seeds is not None:
        mapping = {**mapping, "seeds": int(seeds)}
    return from_mapping(ReproduceConfig, mapping, where=str(path))


def _scheme_mapping(config: ReproduceConfig, scheme: str) -> dict[str, Any]:
    """The built-in scheme config with the overrides laid over it."""
    return deep_merge(read_toml(experiments_dir() / f"{scheme}.toml"), config.run)


def for_scenario(config: ReproduceConfig, name_or_path: str) -> ReproduceConfig:
    """``config`` run in another scenario (`reproduce --scenario S`).

    Where the scenario has the preset's towns, only the scenario changes. Otherwise (a user's
    network, a plain .sumocfg with the vehicles it gets added): the preset's training and test samples,
    in total, are shared evenly among the scenario's data and test vehicles; the named drive routes,
    which run in the built-in towns, are dropped; and the benchmark drives in the scenario itself.
    """
    from crchfl_sumo.sumo.scenario import study_scenario

    scenario, name_or_path = study_scenario(name_or_path)
    sizes = config.generate.dataset
    names = {town.name for town in scenario.towns}
    if {split.town for split in sizes.towns} <= names:
        return dataclasses.replace(config, scenario=name_or_path)
    data = sum(len(town.data_vehicles) for town in scenario.towns)
    tests = sum(len(town.test_vehicles) for town in scenario.towns)
    train_total = sum(n for split in sizes.towns for n in split.train_samples)
    test_total = sum(n for split in sizes.towns for n in split.test_samples)
    towns = tuple(
        TownSplit(town.name, (max(1, train_total // data),) * len(town.data_vehicles),
                  (max(1, test_total // tests),) * len(town.test_vehicles))
        for town in scenario.towns if town.data_vehicles and town.test_vehicles
    )
    generate = dataclasses.replace(config.generate, dataset=dataclasses.replace(sizes, towns=towns))
    return dataclasses.replace(config, scenario=name_or_path, generate=generate, drive_routes=(),
                               bench_towns=(name_or_path,))


def run_budget_gb(config: ReproduceConfig, scheme: str) -> float:
    """The budget of the scheme's runs of experiment B."""
    return float(_scheme_mapping(config, scheme).get("ledger", {}).get("budget_gb", LedgerConfig.budget_gb))


def replanned(config: ReproduceConfig, scheme: str) -> bool:
    """Does the optimizer plan the scheme's runs for their budget (CRCHFL: federation.use_plan)?"""
    return bool(_scheme_mapping(config, scheme).get("federation", {}).get("use_plan", False))


def smaller_budgets(config: ReproduceConfig, scheme: str) -> list[float]:
    """The curve's budgets below the scheme's run budget: a run of their own each (``replanned``), or marks."""
    return [b for b in config.budgets_gb if b < run_budget_gb(config, scheme)]


def run_mapping(
    config: ReproduceConfig, scheme: str, seed: int, data_dir: Path, fix_edge_interval: int | None = None,
    budget_gb: float | None = None,
) -> dict[str, Any]:
    """The run config of one federated run: the built-in scheme config, the overrides, data, seed; a
    run of the budget curve at ``budget_gb``; or experiment B's run, which keeps the best model within each
    of the curve's smaller budgets where the optimizer does not plan the scheme."""
    mapping = deep_merge(
        _scheme_mapping(config, scheme),
        {"scenario": config.scenario, "dataset": str(data_dir), "federation": {"seed": int(seed)}},
    )
    if fix_edge_interval is not None:
        mapping = deep_merge(mapping, {"allocation": {"fix_edge_interval": int(fix_edge_interval)}})
    if budget_gb is not None:
        mapping = deep_merge(mapping, {"ledger": {"budget_gb": float(budget_gb)}})
    elif fix_edge_interval is None and not replanned(config, scheme) and smaller_budgets(config, scheme):
        mapping = deep_merge(mapping, {"ledger": {"marks_gb": smaller_budgets(config, scheme)}})
    return mapping


def run_config(mapping: Mapping[str, Any], where: str) -> RunConfig:
    return from_mapping(RunConfig, mapping, where=where)


@dataclass(frozen=True)
class ReproductionPart:
    """One unit of work: its key in timings.json (also its folder, relative to the results folder)."""

    key: str
    kind: str  # "dataset", "centralized", "federated", "ablation", "dagger", "drive", "bench"
    scheme: str = ""
    seed: int | None = None  # None for the data set, the reference, and a benchmark of the best seed only
    edge_interval: int | None = None
    route: str = ""
    budget_gb: float | None = None  # a point of the budget curve below the runs' budget


def plan_parts(config: ReproduceConfig) -> list[ReproductionPart]:
    """Every part in the order they run: data, upper bound, experiment B, experiment D.

    Drives come after (``drive_parts``): which seed's model drives is known only then.
    """
    parts = [ReproductionPart("data", "dataset")]
    if config.centralized_epochs:
        parts += [ReproductionPart(f"{CENTRALIZED}/seed-{s}", "centralized", CENTRALIZED, s) for s in config.seed_list]
    for seed in config.seed_list:  # seed by seed, so that a partial result already compares the schemes
        parts += [ReproductionPart(f"runs/{scheme}/seed-{seed}", "federated", scheme, seed) for scheme in config.schemes]
    for seed in config.seed_list:
        parts += [
            ReproductionPart(budget_key("runs", scheme, budget, seed), "federated", scheme, seed, budget_gb=budget)
            for scheme in config.schemes if replanned(config, scheme)
            for budget in smaller_budgets(config, scheme)
        ]
    for seed in config.ablation_seed_list:
        parts += [
            ReproductionPart(f"ablation/ie-{k}/seed-{seed}", "ablation", "crchfl", seed, edge_interval=k)
            for k in config.ablation_edge_intervals
        ]
    return parts


BUDGET_CURVE_DIR = "budget_curve"


def budget_key(kind: str, scheme: str, budget_gb: float, seed: int) -> str:
    """The folder of a budget-curve part: ``budget_curve/KIND/SCHEME/gb-B/seed-S`` (KIND: runs, drive_bench)."""
    return f"{BUDGET_CURVE_DIR}/{kind}/{scheme}/gb-{gb_label(budget_gb)}/seed-{seed}"


def dagger_parts(config: ReproduceConfig) -> list[ReproductionPart]:
    """DAgger on each centralized model: after the training parts, before the drives."""
    if not config.dagger_iterations:
        return []
    return [
        ReproductionPart(f"{CENTRALIZED_DAGGER}/seed-{s}", "dagger", CENTRALIZED_DAGGER, s) for s in config.seed_list
    ]


def drive_labels(config: ReproduceConfig) -> list[str]:
    centralized = [CENTRALIZED] if config.centralized_epochs else []
    return [*config.schemes, *centralized, *([CENTRALIZED_DAGGER] if config.dagger_iterations else []), REFERENCE]


def drive_parts(config: ReproduceConfig) -> list[ReproductionPart]:
    """The closed-loop parts: every model drives each named route, then the benchmark's suites."""
    drives = [
        ReproductionPart(f"drives/{route}/{label}", "drive", label, route=route)
        for route in config.drive_routes
        for label in drive_labels(config)
    ]
    return drives + bench_parts(config)


def bench_parts(config: ReproduceConfig) -> list[ReproductionPart]:
    """The benchmark's parts: per model label one, or with ``bench_all_seeds`` one per seed (``drive_bench/LABEL/seed-S``)."""
    if not config.bench_episodes:
        return []
    parts = []
    for label in drive_labels(config):
        if config.bench_all_seeds and label != REFERENCE:
            parts += [ReproductionPart(f"drive_bench/{label}/seed-{s}", "bench", label, s) for s in config.seed_list]
        else:
            parts.append(ReproductionPart(f"drive_bench/{label}", "bench", label))
    for scheme in config.schemes:  # the budget curve: every seed's model at each smaller budget
        parts += [
            ReproductionPart(budget_key("drive_bench", scheme, budget, s), "bench", scheme, s, budget_gb=budget)
            for budget in smaller_budgets(config, scheme) for s in config.seed_list
        ]
    return parts


def describe(config: ReproduceConfig) -> str:
    """One paragraph of what a reproduction runs (for logs and the CLI's start line)."""
    sizes = [n for town in config.generate.dataset.towns for n in town.train_samples]
    return (
        f"{config.name}: {sum(sizes)} training samples over {len(sizes)} vehicles, schemes "
        f"{', '.join(config.schemes)} x seeds {config.seed_list}, ablation edge_interval "
        f"{list(config.ablation_edge_intervals)} x seeds {config.ablation_seed_list}, centralized "
        f"{config.centralized_epochs} epochs"
        + (f" + {config.dagger_iterations} DAgger iteration(s)" if config.dagger_iterations else "")
        + (f", budget curve {list(config.budgets_gb)} GB" if config.budgets_gb else "")
        + f", drives {list(config.drive_routes)}, drive-bench "
        f"{config.bench_episodes} episodes per task in {', '.join(config.bench_towns)}"
    )
