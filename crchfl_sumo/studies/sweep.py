"""`crchfl-sumo sweep CONFIG --param PATH=V1,V2 [--param ...] --out DIR`: a grid of runs, a table and plots.

A parameter is a dotted path into the run config's TOML (``sumo.scale``,
``mobility.coverage_radius_m``, ``federation.deadline_s``, ``ledger.budget_gb``
...) and a comma-separated list of values, each read as a TOML value
(``0.5``, ``inf``, ``"hfl"`` or plain ``hfl``, ``[1, 2]``, ``{name = "a", x_m = 1.0, y_m = 2.0}``;
commas inside brackets, braces or quotes do not split). The grid is every
combination of the values; every point is checked by the same validation as
a run config before anything runs, and an unknown path is an error naming
the ``--param``.

DIR receives (every file written atomically):

  sweep.json        the base config, the parameters and the points
  runs/NAME/        one run folder per point (``run``'s files); NAME is made
                    from the point's values, so a rerun finds it again
  results.csv       one row per point: its values, accuracy, rounds, handovers,
  results.md        stragglers, failed and relayed downloads, bytes per link kind, stop reason
  plots/PATH.png    each metric against each swept parameter

The runs are independent tasks on the backend (``--backend local``: one
process each, as many at a time as CPUs; ``ray``: one Ray task each, every
task in a fresh worker process, since libsumo holds one simulation per
process). Each run trains in its own process with one torch thread.

Rerunning the command resumes the sweep: a point whose run has finished is
not run again, an interrupted one continues from its checkpoint.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import itertools
import json
import logging
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.core.config import changed_keys_text, from_mapping, loads_toml, read_toml, set_path, toml_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.outputs import prepare_output_dir
from crchfl_sumo.core.result_files import CONFIG_JSON_FILE, RESULTS_CSV_FILE, RESULTS_MD_FILE, SUMMARY_FILE
from crchfl_sumo.federation.run_config import (
    RunConfig,
    load_run_config,
    resolve_config_path,
    resolved_as_today,
    resolved_config,
    with_backend,
)
from crchfl_sumo.learning.settings import DATA_DECIDED_KEYS, RESOLVED_PRECISIONS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised only on Python 3.10
    import tomli as tomllib

log = logging.getLogger(__name__)

RUNS_DIR = "runs"
BASE_POINT = "base"  # the name of the point that changes nothing (a study's baseline)
SUMMARY_COLUMNS = (
    "best_accuracy",
    "balanced_accuracy",
    "final_accuracy",
    "cloud_rounds",
    "edge_aggregations",
    "handovers",
    "stragglers",
    "downloads_failed",
    "relayed_transfers",
    "wireless_bytes",
    "wireline_bytes",
    "relay_bytes",
    "consumed_bytes",
    "sim_time_s",
    "stop_reason",
)
# The always-straight prediction on the run's test set, beside the accuracies it reads against
STRAIGHT_COLUMNS = ("always_straight_accuracy", "always_straight_balanced_accuracy")
# results.csv's and results.md's figures: the always-straight ones right after the three accuracies
TABLE_COLUMNS = (*SUMMARY_COLUMNS[:3], *STRAIGHT_COLUMNS, *SUMMARY_COLUMNS[3:])


@dataclass(frozen=True)
class Param:
    """One swept setting: its dotted path in the run config and its values."""

    path: str
    values: tuple[Any, ...]

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(self.path.split("."))


@dataclass(frozen=True)
class Point:
    """One grid point: its folder name, the value of each parameter, the run config mapping."""

    name: str
    values: dict[str, Any]
    mapping: dict


# ------------------------------------------------------------------ parsing and the grid


def parse_param(text: str) -> Param:
    """``PATH=V1,V2,...`` -> Param; values are TOML values, a word that is not one is a string."""
    path, sep, values = text.partition("=")
    path = path.strip()
    if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*", path):
        raise CrchflError(f"--param {text!r}: expected PATH=V1,V2,... with a dotted config key, e.g. sumo.scale=0.5,1,2")
    if path.split(".")[0] == "backend":
        raise CrchflError(f"--param {text!r}: [backend] says where runs go, not what they do; use --backend")
    parts = split_values(values)
    if not parts:
        raise CrchflError(f"--param {text!r}: no values after '='")
    parsed = tuple(parse_value(part, f"--param {path}") for part in parts)
    if len({json.dumps(v, sort_keys=True) for v in parsed}) != len(parsed):
        raise CrchflError(f"--param {text!r}: a value is given twice")
    return Param(path, parsed)


def split_values(text: str) -> list[str]:
    """Split on commas that are not inside brackets, braces or quotes."""
    parts, depth, quote, current = [], 0, None, []
    for char in text:
        if quote:
            quote = None if char == quote else quote
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
        elif char in "]}":
            depth -= 1
        elif char == "," and depth == 0:
            parts.append("".join(current).strip())
            current = []
            continue
        current.append(char)
    parts.append("".join(current).strip())
    return [p for p in parts if p]


def parse_value(text: str, where: str = "--param") -> Any:
    try:
        return loads_toml(f"v = {text}", where)["v"]
    except tomllib.TOMLDecodeError:
        return text  # a bare word: hfl, sumo ...


def expand_grid(base: dict, params: list[Param], where: str = "config") -> list[Point]:
    """Every combination of the parameters' values over ``base`` (the first parameter varies slowest).

    Each value is checked on its own first (so a bad path or value names its
    --param), then every point as a whole.
    """
    paths = [p.path for p in params]
    if len(set(paths)) != len(paths):
        raise CrchflError(f"--param: a path is swept twice ({', '.join(paths)}); give each once")
    for param in params:
        check_values(base, param, f"--param {param.path}")
    points = []
    for combination in itertools.product(*(p.values for p in params)):
        mapping = base
        for param, value in zip(params, combination):
            mapping = set_path(mapping, param.keys, value, f"--param {param.path}")
        values = dict(zip(paths, combination))
        name = point_name(values)
        from_mapping(RunConfig, mapping, where=f"{where} with {name}")
        points.append(Point(name, values, mapping))
    return points


def check_values(base: dict, param: Param, label: str) -> None:
    """Each of ``param``'s values set on ``base`` on its own must make a valid run config; errors name ``label``."""
    for value in param.values:
        where_value = f"{label}={value_label(value)}"
        try:
            from_mapping(RunConfig, set_path(base, param.keys, value, label), where=f"{where_value}: config")
        except CrchflError as exc:  # a settings class's own check does not know the --param: name it
            message = str(exc)
            raise CrchflError(message if message.startswith(where_value) else f"{where_value}: {message}") from None


def point_name(values: dict[str, Any]) -> str:
    """A folder name from a point's values, the same for the same values: ``path=value`` joined by ``__``.

    Values that are not short scalars (lists, tables) are named by a hash of their TOML.
    """
    parts = []
    for path, value in values.items():
        text = value_label(value)
        if isinstance(value, (list, tuple, dict)) or not re.fullmatch(r"[A-Za-z0-9.+\-_]{1,40}", text):
            text = hashlib.sha1(toml_text({"v": value}).encode()).hexdigest()[:10]
        parts.append(f"{path}={text}")
    return "__".join(parts) or BASE_POINT


def value_label(value: Any) -> str:
    """A swept value as the user writes it after --param KEY= (scalars); tables and lists as one line of JSON."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (int, float, str)):
        return str(value)
    return json.dumps(value)


# ------------------------------------------------------------------ running


def run_point(mapping: dict, out_dir: str) -> dict:
    """One grid point's run (a backend task, in its own process): its summary.

    Resumes the run in ``out_dir`` if one is there; a finished one returns its summary at once.
    """
    import torch

    from crchfl_sumo.driving.vehicle_dagger import labeller_factory
    from crchfl_sumo.federation.run import run_federation_dir
    from crchfl_sumo.federation.run_data import read_inputs

    torch.set_num_threads(1)  # several runs share the machine's cores
    config = from_mapping(RunConfig, mapping, where=f"{out_dir}/config.toml")
    return run_federation_dir(config, read_inputs(config), out_dir, resume=True, config_text=toml_text(mapping),
                              labeller_factory=labeller_factory)


def finished_summary(run_dir: Path, mapping: dict) -> dict | None:
    """The summary of a finished run of ``mapping`` in ``run_dir`` (None if there is none or it is still going).

    A finished run made with other settings (the base config changed since) is an error, never a stale row.
    """
    path = run_dir / SUMMARY_FILE
    if not path.is_file():
        return None
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
        recorded = json.loads((run_dir / CONFIG_JSON_FILE).read_text(encoding="utf-8"))["config"]
    except (OSError, KeyError, json.JSONDecodeError):
        return None  # not finished writing: the run resumes and rewrites them
    if not summary.get("stop_reason"):
        return None
    point = from_mapping(RunConfig, mapping)
    wanted = json.loads(json.dumps(resolved_config(point)))
    finished = resolved_as_today(recorded, str(run_dir / CONFIG_JSON_FILE), point.backend)  # an older version's too
    train = finished.get("train")
    if point.train.precision == "auto" and isinstance(train, dict) and train.get("precision") in RESOLVED_PRECISIONS:
        # "auto" was decided where the point ran (a Ray worker's CPU may differ from this one's): it stands
        wanted["train"]["precision"] = train["precision"]
    model = finished.get("model")
    for key in DATA_DECIDED_KEYS:  # unset in the point: the run decided it from its data
        if isinstance(model, dict) and key in model and key not in wanted["model"]:
            wanted["model"][key] = model[key]
    if finished != wanted:
        raise CrchflError(
            f"{run_dir} holds a run made with other settings than this sweep's point (its config.json differs "
            f"in {changed_keys_text(finished, wanted)}); sweep into another --out or delete that folder"
        )
    return summary


# With several seeds a point: the figures whose 95 % interval over the seeds the table gives.
INTERVAL_COLUMNS = ("balanced_accuracy", "best_accuracy")


def point_seeds(point: Point, seeds: int) -> list[int]:
    """The seeds a point runs with: its own federation.seed, +1, ... (``seeds`` of them)."""
    first = int(point.mapping.get("federation", {}).get("seed", 0))
    return list(range(first, first + seeds))


def seed_point(name: str, seed: int) -> str:
    """A point's run of one seed, as its folder under runs/ names it."""
    return f"{name}/seed-{seed}"


def seed_runs(points: list[Point], seeds: int, nested: bool | None = None) -> list[Point]:
    """Each point's run of each seed (``POINT/seed-S``, federation.seed set); ``nested`` False (the default
    for one seed): the points themselves, in their own folders."""
    if not (seeds > 1 if nested is None else nested):
        return points
    return [Point(seed_point(point.name, seed), point.values,
                  set_path(point.mapping, ("federation", "seed"), seed, "seeds"))
            for point in points for seed in point_seeds(point, seeds)]


def seed_row(point: Point, rows: list[dict]) -> dict:
    """A point's row over its seeds' rows: the mean of each figure (statistics.seed_mean), ``seeds``, and the
    95 % t interval (``KEY_ci_lo``, ``KEY_ci_hi``) of INTERVAL_COLUMNS."""
    from crchfl_sumo.studies.statistics import mean_std, seed_mean

    row: dict[str, Any] = {"point": point.name, **point.values, "seeds": len(rows)}
    for key in TABLE_COLUMNS:  # wireless and wireline bytes among them
        values = [r.get(key) for r in rows]
        row[key] = seed_mean(values)
        if key in INTERVAL_COLUMNS:
            row[f"{key}_ci_lo"], row[f"{key}_ci_hi"] = mean_std(values)["ci95"] or (None, None)
    return row


def run_sweep(base: dict, params: list[Param], out_dir: str | Path, backend: BackendConfig, where: str = "config",
              seeds: int = 1) -> list[dict]:
    """Run every point not finished yet (``seeds`` runs a point), then write the table and the plots; returns
    the rows (with several seeds: each point's means over them, with intervals)."""
    from crchfl_sumo.studies.sweep_plots import plot_sweep

    out_dir = Path(out_dir)
    base = {k: v for k, v in base.items() if k != "backend"}
    points = [
        dataclasses.replace(p, mapping=absolute_paths(p.mapping)) for p in expand_grid(base, params, where)
    ]  # every point checked before the folder is touched
    prepare_output_dir(out_dir, "sweep", flag="sweep --out", resumable=True)
    atomic_write_text(
        out_dir / "sweep.json",
        json.dumps(
            {
                "base": base,
                "params": [{"path": p.path, "values": list(p.values)} for p in params],
                "points": [{"name": p.name, "values": p.values} for p in points],
            },
            indent=2,
            default=str,
        )
        + "\n",
    )
    runs = seed_runs(points, seeds)
    summaries = run_points(runs, out_dir, backend)
    if seeds == 1:
        rows = [table_row(p, summaries[p.name]) for p in points]
    else:
        rows = [seed_row(p, [table_row(p, summaries[seed_point(p.name, s)]) for s in point_seeds(p, seeds)])
                for p in points]
    write_table(out_dir, rows, [p.path for p in params], seeds > 1)
    plot_sweep(rows, params, out_dir / "plots")
    return rows


def run_points(points: list[Point], out_dir: Path, backend: BackendConfig) -> dict[str, dict]:
    """Each point's run in ``out_dir/runs/NAME`` (finished ones are read, not rerun): name -> summary."""
    summaries = {p.name: finished_summary(out_dir / RUNS_DIR / p.name, p.mapping) for p in points}
    todo = [p for p in points if summaries[p.name] is None]
    log.info("sweep: %d points, %d finished, %d to run", len(points), len(points) - len(todo), len(todo))
    with Executor(backend) as executor:
        results = executor.map(run_point, [(p.mapping, str(out_dir / RUNS_DIR / p.name)) for p in todo], isolate=True)
    summaries.update({p.name: s for p, s in zip(todo, results)})
    return summaries


def absolute_paths(base: dict) -> dict:
    """Data set and scenario file paths made absolute: the runs may work in another directory."""
    out = dict(base)

    defaults = RunConfig()
    dataset = Path(out.get("dataset", defaults.dataset))
    out["dataset"] = str(dataset.resolve())
    scenario = out.get("scenario", defaults.scenario)
    if Path(scenario).exists():
        out["scenario"] = str(Path(scenario).resolve())
    return out


def table_row(point: Point, summary: dict) -> dict:
    """A point's values and the metrics of its run's summary."""
    links = summary.get("bytes_by_link", {})
    metrics = {
        **{k: summary.get(k) for k in SUMMARY_COLUMNS},
        **always_straight_columns(summary),
        "wireless_bytes": links.get("wireless"),
        "wireline_bytes": links.get("wireline"),
    }
    return {"point": point.name, **point.values, **metrics}


def always_straight_columns(summary: dict) -> dict:
    """STRAIGHT_COLUMNS of a run's summary: the always-straight accuracy and balanced accuracy on its test set
    (None where the run recorded no baseline)."""
    found = (summary.get("baselines") or {}).get("always_straight") or {}
    return dict(zip(STRAIGHT_COLUMNS, (found.get("accuracy"), found.get("balanced_accuracy"))))


def write_table(out_dir: Path, rows: list[dict], paths: list[str], intervals: bool = False) -> None:
    """results.csv and results.md: one row per point (``intervals``: its seeds and the intervals over them)."""
    extra = ["seeds", *(f"{k}_ci_{end}" for k in INTERVAL_COLUMNS for end in ("lo", "hi"))] if intervals else []
    columns = ["point", *paths, *extra, *TABLE_COLUMNS]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(row.get(c), csv_cell=True) for c in columns])
    atomic_write_text(out_dir / RESULTS_CSV_FILE, buffer.getvalue())
    shown = [c for c in columns if c != "point"]
    lines = ["| " + " | ".join(shown) + " |", "|" + " --- |" * len(shown)]
    lines += ["| " + " | ".join(_cell(row.get(c)) for c in shown) + " |" for row in rows]
    atomic_write_text(out_dir / RESULTS_MD_FILE, "\n".join(lines) + "\n")


def _cell(value: Any, csv_cell: bool = False) -> str:
    if value is None:
        return "" if csv_cell else "-"
    if isinstance(value, float) and not csv_cell:
        return f"{value:.4g}"
    if isinstance(value, (str, int, float)) and not isinstance(value, bool):
        return str(value)
    return value_label(value)


def sweep_command(
    config_path: str | Path,
    param_texts: list[str],
    out_dir: str | Path,
    backend: str | None = None,
    address: str | None = None,
    seeds: int = 1,
) -> list[dict]:
    """What `crchfl-sumo sweep CONFIG --param P=V1,V2 ... --out DIR [--seeds N] [--backend B] [--address A]` does."""
    if not param_texts:
        raise CrchflError("sweep: give at least one --param PATH=V1,V2,...")
    config_path = resolve_config_path(config_path)
    base = read_toml(config_path)
    config = with_backend(load_run_config(config_path), backend, address)
    params = [parse_param(text) for text in param_texts]
    return run_sweep(base, params, out_dir, config.backend, where=str(config_path), seeds=seeds)
