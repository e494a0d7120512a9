"""`crchfl-sumo mobility-study [--quick] --out DIR`: what mobility does to aggregation, one factor at a time.

A study preset (scenarios/experiments/mobility_quick.toml, mobility_full.toml)
holds a small data set to generate ([data]), a baseline run config ([run])
and the factors ([[factor]]: a name, a dotted run-config key as in
``sweep --param``, its values, optional labels). The study runs the baseline
once and, for each factor, one run per value with only that key changed
(one factor at a time around the baseline, not the grid). A value that
gives the baseline's own settings reuses the baseline run.

The runs are the sweep's (studies/sweep.py: the same run folders, backend
tasks and resume); DIR receives:

  study.json          the preset, the points and which point is each factor value
  data/               the generated data set (kept: a rerun reuses it)
  runs/NAME/          one run folder per point (``base`` is the baseline)
  results.csv, .md    one row per factor value (mobility_report.py)
  plots/FACTOR.png    the metrics against each factor's values

Rerunning the command resumes: finished runs are read, not rerun.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.backend import BackendConfig
from crchfl_sumo.core.config import from_mapping, read_toml, set_path
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.json_files import read_json
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.core.outputs import prepare_output_dir
from crchfl_sumo.core.resources import experiments_dir
from crchfl_sumo.core.result_files import BEST_MODEL_FILE, SUMMARY_FILE
from crchfl_sumo.data.settings import MAX_SAMPLE_PERIOD_S, PAPER_SAMPLE_PERIOD_S
from crchfl_sumo.federation.run_config import RunConfig, resolved_config
from crchfl_sumo.studies.mobility_study_report import BASELINE
from crchfl_sumo.studies.sweep import (
    RUNS_DIR,
    Param,
    Point,
    absolute_paths,
    check_values,
    point_name,
    point_seeds,
    run_points,
    seed_point,
    seed_runs,
    value_label,
)

log = logging.getLogger(__name__)

DATA_DIR = "data"
PRESET_KEYS = {"name", "data", "run", "factor", "seeds", "bench_episodes"}
BENCH_DIR = "bench"
# The closed loop each point's models drive: the straight and one-turn suites of both towns, one route draw.
BENCH_TOWNS = ("town01", "town02")
BENCH_TASKS = ("straight", "one_turn")
BENCH_SEED = 0
MAX_STUDY_SEEDS = 100
DATA_KEYS = {"scenario", "train_samples", "test_samples", "seed", "sample_period_s"}
FACTOR_KEYS = {"name", "key", "values", "labels"}
MAX_SAMPLES = 100_000  # per vehicle of the study's data set


@dataclass(frozen=True)
class Factor:
    """One factor of the study: its name, its key and values (a sweep Param), a label per value."""

    name: str
    param: Param
    labels: tuple[str, ...]


@dataclass(frozen=True)
class StudyData:
    """The study's data set: ``train_samples`` per data vehicle, ``test_samples`` per test vehicle of ``scenario``,
    one every ``sample_period_s`` (a multiple of the scenario's step; longer spans more of the route, turns
    included, for the same training time)."""

    scenario: str
    train_samples: int
    test_samples: int
    seed: int = 0
    sample_period_s: float = PAPER_SAMPLE_PERIOD_S

    def __post_init__(self) -> None:
        check_range(self.sample_period_s, "sample_period_s", 0, MAX_SAMPLE_PERIOD_S, "simulated seconds",
                    lo_open=True)


@dataclass(frozen=True)
class Study:
    """A study: its data set, the baseline run config, the factors; ``seeds`` runs a point (federation.seed
    = the baseline's, +1, ...), ``bench_episodes`` episodes per suite and town each of their models drives
    (0: no closed loop)."""

    name: str
    data: StudyData
    base: dict
    factors: tuple[Factor, ...]
    seeds: int = 1
    bench_episodes: int = 0
    bench_towns: tuple[str, ...] = BENCH_TOWNS  # where the models drive: built-in town names or scenario paths


@dataclass(frozen=True)
class StudyPlan:
    """The points to run (the baseline first) and, per factor, the point of each of its values."""

    points: tuple[Point, ...]
    factor_points: dict[str, tuple[str, ...]]


# ------------------------------------------------------------------ the preset


def preset_path(quick: bool) -> Path:
    return experiments_dir() / ("mobility_quick.toml" if quick else "mobility_full.toml")


def parse_study(raw: dict, where: str) -> Study:
    """A study preset's mapping -> Study; every key is checked, a bad one is named with the fix."""
    _known(raw, PRESET_KEYS, where)
    data = raw.get("data", {})
    _known(data, DATA_KEYS, f"{where} [data]")
    missing = [key for key in ("scenario", "train_samples", "test_samples") if key not in data]
    if missing:
        raise CrchflError(f"{where} [data]: {missing[0]!r} is missing (scenario, train_samples, test_samples)")
    study_data = from_mapping(StudyData, data, f"{where} [data]")
    if not (1 <= study_data.train_samples <= MAX_SAMPLES and 1 <= study_data.test_samples <= MAX_SAMPLES):
        raise CrchflError(f"{where} [data]: train_samples and test_samples must be in 1 .. {MAX_SAMPLES}")
    base = raw.get("run")
    if not isinstance(base, dict):
        raise CrchflError(f"{where}: a [run] table (the baseline run config) is missing")
    if "backend" in base or "dataset" in base:
        raise CrchflError(f"{where} [run]: leave out 'backend' (use --backend) and 'dataset' (the study makes DIR/data)")
    factors = []
    for i, table in enumerate(raw.get("factor", [])):
        label = f"{where} [[factor]] {i + 1}"
        _known(table, FACTOR_KEYS, label)
        if "key" not in table or not table.get("values"):
            raise CrchflError(f"{label}: give key = \"section.name\" and a non-empty list of values")
        key, values = str(table["key"]), tuple(table["values"])
        labels = tuple(str(v) for v in table.get("labels", [value_label(v) for v in values]))
        if len(labels) != len(values):
            raise CrchflError(f"{label} ({key}): {len(labels)} labels for {len(values)} values; give one label per value")
        factors.append(Factor(str(table.get("name", key)), Param(key, values), labels))
    if not factors:
        raise CrchflError(f"{where}: no [[factor]] tables; give at least one factor (key, values)")
    names = [f.name for f in factors]
    if len(set(names)) != len(names):
        raise CrchflError(f"{where}: factor names must be distinct, got {names}")
    seeds, episodes = raw.get("seeds", 1), raw.get("bench_episodes", 0)
    for key, value, lo, hi, what in (("seeds", seeds, 1, MAX_STUDY_SEEDS, "runs a point"),
                                     ("bench_episodes", episodes, 0, 1000, "episodes per suite and town (0: none)")):
        if isinstance(value, bool) or not isinstance(value, int):
            raise CrchflError(f"{where}: {key} = {value!r}; give a whole number of {what}")
        check_range(value, f"{where}: {key}", lo, hi, what)
    return Study(str(raw.get("name", Path(where).stem)), study_data, base, tuple(factors), int(seeds), int(episodes))


def _known(table: Any, keys: set[str], where: str) -> None:
    if not isinstance(table, dict):
        raise CrchflError(f"{where}: expected a table")
    unknown = sorted(set(table) - keys)
    if unknown:
        raise CrchflError(f"{where}: unknown key {unknown[0]!r}; the keys are {', '.join(sorted(keys))}")


# ------------------------------------------------------------------ the plan


def study_plan(base: dict, factors: tuple[Factor, ...], where: str = "study") -> StudyPlan:
    """The baseline and one point per factor value (that key alone changed); equal settings share a point.

    Every value is checked like a sweep --param first, so a bad key or value names its factor.
    """
    for factor in factors:
        check_values(base, factor.param, f"{where}: factor {factor.name!r}: {factor.param.path}")
    points: list[Point] = []
    by_settings: dict[str, str] = {}

    def add(name: str, values: dict, mapping: dict) -> str:
        settings = json.dumps(resolved_config(from_mapping(RunConfig, mapping, where=f"{where}: {name}")), sort_keys=True,
                              default=str)
        if settings not in by_settings:
            by_settings[settings] = name
            points.append(Point(name, values, mapping))
        return by_settings[settings]

    add(BASELINE, {}, base)
    factor_points = {}
    for factor in factors:
        names = []
        for value in factor.param.values:
            values = {factor.param.path: value}
            mapping = set_path(base, factor.param.keys, value, f"factor {factor.name!r}")
            names.append(add(point_name(values), values, mapping))
        factor_points[factor.name] = tuple(names)
    return StudyPlan(tuple(points), factor_points)


# Factors whose values are places of the preset's own scenario (its sites' coordinates): meaningless elsewhere.
SCENARIO_BOUND_KEYS = ("sumo.edge_sites",)


def for_scenario(study: Study, name_or_path: str) -> tuple[Study, list[str]]:
    """``study`` in another scenario (`mobility-study --scenario S`): its data set and runs there, the same
    samples per vehicle (the sample period rounded up to a multiple of its step where it is none); the models
    drive the benchmark in that scenario itself (in Town01 and Town02 where
    it has both); factors whose values are places of the preset's scenario are dropped, and named in the
    returned list. A scenario without data or test vehicles (a plain .sumocfg gets them added) is refused."""
    from crchfl_sumo.sumo.scenario import study_scenario

    scenario, name_or_path = study_scenario(name_or_path)
    if name_or_path == study.data.scenario:
        return study, []
    dropped = [f.name for f in study.factors if f.param.path in SCENARIO_BOUND_KEYS]
    towns = {t.name for t in scenario.towns}
    # the samples must fall on the scenario's steps: the preset's period, or the next multiple of a longer step
    step_s = scenario.step_length_s
    period_s = max(1, math.ceil(study.data.sample_period_s / step_s - 1e-9)) * step_s
    if not math.isclose(period_s, study.data.sample_period_s):
        log.warning("[data] sample_period_s %g s is no multiple of %s's step, %g s: sampling every %g s",
                    study.data.sample_period_s, name_or_path, step_s, period_s)
    return dataclasses.replace(
        study,
        data=dataclasses.replace(study.data, scenario=name_or_path, sample_period_s=period_s),
        base={**study.base, "scenario": name_or_path},
        factors=tuple(f for f in study.factors if f.param.path not in SCENARIO_BOUND_KEYS),
        bench_towns=BENCH_TOWNS if set(BENCH_TOWNS) <= towns else (name_or_path,),
    ), dropped


# ------------------------------------------------------------------ running


def make_data(data: StudyData, out_dir: Path) -> Path:
    """The study's data set in ``out_dir``: generated, or finished where a generation was cut off; a finished
    one, or one placed there that the study did not plan (other shard names), is used as it is."""
    from crchfl_sumo.data.generation import generate_dataset
    from crchfl_sumo.data.manifest import MANIFEST_NAME, read_manifest
    from crchfl_sumo.data.settings import DatasetConfig, TownSplit, shard_plan
    from crchfl_sumo.sumo.scenario import load_scenario

    scenario = load_scenario(data.scenario)
    sizes = DatasetConfig(
        sample_period_s=data.sample_period_s,
        towns=tuple(
            TownSplit(t.name, (data.train_samples,) * len(t.data_vehicles), (data.test_samples,) * len(t.test_vehicles))
            for t in scenario.towns
        )
    )
    if (out_dir / MANIFEST_NAME).is_file():
        present = {shard.file for shard in read_manifest(out_dir).shards}
        if not present < {shard.file for shard in shard_plan(sizes)}:  # finished, or not of this plan
            return out_dir
    generate_dataset(scenario, out_dir, seed=data.seed, sizes=sizes)  # resumes: writes only the missing shards
    return out_dir


def run_study(study: Study, out_dir: str | Path, backend: BackendConfig, where: str = "study") -> list[dict]:
    """Generate the data, run every point not finished yet, write the table and figures; returns the rows."""
    from crchfl_sumo.studies.mobility_study_report import study_rows, write_report

    out_dir = Path(out_dir)
    base = {**study.base, "dataset": str((out_dir / DATA_DIR).resolve())}
    plan = study_plan(base, study.factors, where)  # checked before anything is generated or run
    prepare_output_dir(out_dir, "mobility-study", flag="mobility-study --out", resumable=True)
    atomic_write_text(
        out_dir / "study.json",
        json.dumps(
            {
                "name": study.name,
                "data": study.data.__dict__,
                "bench_towns": list(study.bench_towns),
                "base": base,
                "factors": [{"name": f.name, "key": f.param.path, "values": list(f.param.values),
                             "labels": list(f.labels), "points": list(plan.factor_points[f.name])}
                            for f in study.factors],
                "points": [p.name for p in plan.points],
            },
            indent=2,
            default=str,
        )
        + "\n",
    )
    make_data(study.data, out_dir / DATA_DIR)
    points = [Point(p.name, p.values, absolute_paths(p.mapping)) for p in plan.points]
    runs = seed_runs(points, study.seeds, nested=True)  # runs/POINT/seed-S, one seed too
    summaries = run_points(runs, out_dir, backend)
    benches = bench_points(out_dir, [r.name for r in runs], study.bench_episodes, backend, study.bench_towns)
    seeds = {p.name: point_seeds(p, study.seeds) for p in points}
    by_point = {name: {s: summaries[seed_point(name, s)] for s in ss} for name, ss in seeds.items()}
    by_point_bench = {name: {s: benches[seed_point(name, s)] for s in ss if seed_point(name, s) in benches}
                      for name, ss in seeds.items()}
    rows = study_rows(study.factors, plan, by_point, by_point_bench)
    write_report(out_dir, study.factors, rows)
    return rows


def bench_points(out_dir: Path, names: list[str], episodes: int, backend: BackendConfig,
                 towns: tuple[str, ...] = BENCH_TOWNS) -> dict[str, dict]:
    """The closed-loop benchmark of each run's best model in ``out_dir/bench/NAME`` (finished ones are read):
    name -> its summary; none with ``episodes`` 0."""
    if not episodes:
        return {}
    from crchfl_sumo.core.backend import Executor

    paths = {name: out_dir / BENCH_DIR / name / SUMMARY_FILE for name in names}
    done = {name: read_json(path, "delete the folder to drive the benchmark again") for name, path in paths.items()
            if path.is_file()}
    todo = [name for name in names if name not in done]
    with Executor(backend) as executor:
        calls = [(str(out_dir / RUNS_DIR / n / BEST_MODEL_FILE), str(out_dir / BENCH_DIR / n), episodes, towns)
                 for n in todo]
        results = executor.map(bench_point, calls, isolate=True)
    return {**done, **dict(zip(todo, results))}


def bench_point(model: str, out: str, episodes: int, towns: tuple[str, ...] = BENCH_TOWNS) -> dict:
    """One run's best model through the study's benchmark (a backend task, in its own process)."""
    import torch

    from crchfl_sumo.driving.drive_bench import BenchConfig, run_benchmark

    torch.set_num_threads(1)  # several share the machine's cores
    return run_benchmark(model, out, episodes=episodes, seed=BENCH_SEED, towns=tuple(towns),
                         config=BenchConfig(tasks=BENCH_TASKS))


def mobility_study_command(quick: bool, out_dir: str | Path, config: str | Path | None = None, jobs: int = 0,
                           backend: str | None = None, address: str | None = None,
                           scenario: str | None = None) -> list[dict]:
    """What `crchfl-sumo mobility-study [--quick] [--config TOML] [--scenario S] --out DIR [--jobs N]
    [--backend B]` does."""
    path = Path(config) if config is not None else preset_path(quick)
    if not path.is_file():
        raise CrchflError(f"--config {path}: no such file")
    if jobs < 0:
        raise CrchflError(f"--jobs must be >= 0 (0 = all CPUs), got {jobs}")
    if address is not None and backend != "ray":
        raise CrchflError("--address joins a Ray cluster: give it with --backend ray")
    study = parse_study(read_toml(path), str(path))
    if scenario is not None:
        study, dropped = for_scenario(study, scenario)
        for name in dropped:
            log.warning("factor %r left out: its values are places of the preset's scenario, not of %s", name, scenario)
    return run_study(study, out_dir, BackendConfig(kind=backend or "local", address=address or "", num_cpus=jobs),
                     where=str(path))
