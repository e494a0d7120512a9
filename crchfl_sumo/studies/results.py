"""Reading a reproduction's results folder: each run's summary, metrics and ledger, the centralized runs, the drives, the timings.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable, Sequence

from crchfl_sumo.core import json_files
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.result_files import (
    CONFIG_JSON_FILE,
    DRIVE_METRICS_FILE,
    EPISODES_FILE,
    METRICS_LOG_FILE,
    SUMMARY_FILE,
    TIMINGS_FILE,
)
from crchfl_sumo.core.schemes import MODEL_LABELS, SCHEMES
from crchfl_sumo.studies.reproduce_plan import BUDGET_CURVE_DIR


def read_json(path: Path) -> Any:
    return json_files.read_json(path, "rerun the part that writes it")


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def seed_folders(folder: Path) -> dict[int, Path]:
    """seed -> ``folder/seed-S`` for each such folder holding a summary.json, by seed."""
    found = {}
    for summary_path in Path(folder).glob("seed-*/summary.json"):
        try:
            found[int(summary_path.parent.name.split("-", 1)[1])] = summary_path.parent
        except ValueError:
            continue
    return dict(sorted(found.items()))


def read_seed_runs(folder: Path) -> dict[int, dict[str, Any]]:
    """seed -> {"summary", "metrics", "config"} of each ``folder/seed-S`` holding a summary.json."""
    runs = {}
    for seed, run_dir in seed_folders(folder).items():
        config_path = run_dir / CONFIG_JSON_FILE
        runs[seed] = {
            "summary": read_json(run_dir / SUMMARY_FILE),
            "metrics": read_jsonl(run_dir / METRICS_LOG_FILE),
            "config": read_json(config_path) if config_path.is_file() else None,
        }
    return runs


def _ordered(names: Iterable[str], order: Sequence[str]) -> list[str]:
    names = list(names)
    return [n for n in order if n in names] + sorted(n for n in names if n not in order)


def read_benchmarks(bench_dir: Path) -> dict[str, dict[str, Any]]:
    """label -> the drive-bench summary.json of ``bench_dir/LABEL``, or {"seeds": {seed: summary}, "episodes":
    {seed: episode records}} where the benchmark drove every seed's model (``bench_dir/LABEL/seed-S/``; a seed
    without episodes.json has no records)."""
    bench: dict[str, dict[str, Any]] = {}
    if not bench_dir.is_dir():
        return bench
    for folder in bench_dir.iterdir():
        if (folder / SUMMARY_FILE).is_file():
            bench[folder.name] = read_json(folder / SUMMARY_FILE)
        elif folder.is_dir():
            found = seed_folders(folder)
            if found:
                bench[folder.name] = {
                    "seeds": {seed: read_json(path / SUMMARY_FILE) for seed, path in found.items()},
                    "episodes": {seed: read_json(path / EPISODES_FILE) for seed, path in found.items()
                                 if (path / EPISODES_FILE).is_file()},
                }
    return {label: bench[label] for label in _ordered(bench, MODEL_LABELS)}


def read_budget_curve(folder: Path) -> dict[str, Any]:
    """The budget curve's parts (studies/reproduce_plan.budget_key): ``{"runs": {SCHEME: {"B": {seed: summary}}},
    "bench": {SCHEME: {"B": {seed: drive-bench summary}}}}``, B as the folder names it (gb-B)."""
    found: dict[str, Any] = {"runs": {}, "bench": {}}
    for kind, key in (("runs", "runs"), ("drive_bench", "bench")):
        for scheme_dir in sorted(p for p in (folder / kind).glob("*") if p.is_dir()):
            for budget_dir in sorted(p for p in scheme_dir.glob("gb-*") if p.is_dir()):
                seeds = {seed: read_json(path / SUMMARY_FILE) for seed, path in seed_folders(budget_dir).items()}
                if seeds:
                    found[key].setdefault(scheme_dir.name, {})[budget_dir.name[3:]] = seeds
    return found


def read_results(out_dir: str | Path) -> dict[str, Any]:
    """Everything the report shows, read from the results folder."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise CrchflError(f"{out_dir}: no such results folder; give the --out folder of `crchfl-sumo reproduce`")
    runs_dir, ablation_dir, drives_dir = out_dir / "runs", out_dir / "ablation", out_dir / "drives"
    schemes = {}
    if runs_dir.is_dir():
        for name in _ordered([p.name for p in runs_dir.iterdir() if p.is_dir()], SCHEMES):
            found = read_seed_runs(runs_dir / name)
            if found:
                schemes[name] = found
    ablation = {}
    if ablation_dir.is_dir():
        settings = [p for p in ablation_dir.iterdir() if p.is_dir() and p.name.startswith("ie-")]
        for path in sorted(settings, key=lambda p: int(p.name[3:]) if p.name[3:].isdigit() else 0):
            found = read_seed_runs(path)
            if found:
                ablation[path.name] = found
    drives: dict[str, dict[str, dict[str, Any]]] = {}
    if drives_dir.is_dir():
        for route_dir in sorted(p for p in drives_dir.iterdir() if p.is_dir()):
            labels = [p.name for p in route_dir.iterdir() if (p / DRIVE_METRICS_FILE).is_file()]
            if labels:
                drives[route_dir.name] = {
                    label: read_json(route_dir / label / DRIVE_METRICS_FILE) for label in _ordered(labels, MODEL_LABELS)
                }
    bench = read_benchmarks(out_dir / "drive_bench")
    if not schemes and not ablation:
        raise CrchflError(
            f"{out_dir}: no finished run (runs/SCHEME/seed-S/summary.json); "
            f"run `crchfl-sumo reproduce --out {out_dir}` first"
        )
    reproduce_path = out_dir / "reproduce.json"
    timings_path = out_dir / TIMINGS_FILE
    return {
        "out_dir": out_dir,
        "schemes": schemes,
        "ablation": ablation,
        "centralized": read_seed_runs(out_dir / "centralized"),
        "drives": drives,
        "drive_bench": bench,
        "budget_curve": read_budget_curve(out_dir / BUDGET_CURVE_DIR),
        "reproduce": read_json(reproduce_path) if reproduce_path.is_file() else {},
        "timings": read_json(timings_path) if timings_path.is_file() else {},
    }
