"""`crchfl-sumo report DIR`: figures, tables, report.md and summary.json from a results folder alone.

Reads only what the runs wrote (experiment.py lays the folder out):
``runs/SCHEME/seed-S/`` and ``ablation/ie-K/seed-S/`` (run.py: summary.json,
metrics.jsonl, config.json), ``centralized/seed-S/`` (local.py's
metrics.jsonl and experiment.py's summary.json), ``drives/ROUTE/LABEL/``
(drive.py: metrics.json, trajectory.csv), ``reproduce.json`` and
``timings.json``. Writes ``figures/*.png``, ``report.md`` and
``summary.json``, each atomically. Every statistic over seeds is the mean and
the sample standard deviation (ddof = 1; none for a single seed).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from crchfl_sumo.core.atomic import atomic_path, atomic_write_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.figures import pyplot, save_figure
from crchfl_sumo.core.schemes import DISPLAY_NAMES, SCHEMES

log = logging.getLogger(__name__)

GIB = 1024**3
LABEL_ORDER = (*SCHEMES, "centralized", "reference")
NAMES = {**DISPLAY_NAMES, "centralized": "Centralized", "reference": "Reference driver"}
COLORS = {"crchfl": "tab:red", "hfl": "tab:blue", "sfl": "tab:green", "centralized": "black"}
# HFL and SFL give the same model after each round when cloud_interval = 1 (FedAvg over edges, then
# over the cloud, is FedAvg over all vehicles): styles keep a line visible under another.
STYLES = {"crchfl": ("-", "o"), "hfl": ("--", "s"), "sfl": (":", "^")}
# Section IV-B of the paper: CRCHFL's Accuracy over HFL's and SFL's under 20 GB.
PAPER_GAINS_PERCENT = {"hfl": 10.33, "sfl": 12.41}
STAGES = ("I", "II", "III")
HYPER = ("pretrain_batch", "edge_interval", "cloud_interval", "cloud_rounds")
DRIVE_COLUMNS = (
    "completion", "end_reason", "duration_s", "mean_speed_mps", "collisions", "lane_departures",
    "off_road_s", "red_light_violations", "max_abs_offset_m",
)
FIGURES = {
    "fig3": "fig3_rounds.png",
    "fig4": "fig4_bytes.png",
    "fig7": "fig7_ablation.png",
}


# ------------------------------------------------------------------ statistics (pure)


def mean_std(values: Iterable[float | None]) -> dict[str, Any]:
    """Mean and sample standard deviation (ddof = 1) of the values that are not None.

    ``std`` is None with fewer than two values, ``mean`` None with none.
    """
    kept = [float(v) for v in values if v is not None]
    n = len(kept)
    mean = float(np.mean(kept)) if n else None
    std = float(np.std(kept, ddof=1)) if n >= 2 else None
    return {"mean": mean, "std": std, "n": n}


def relative_gain_percent(ours: float | None, theirs: float | None) -> float | None:
    """How much higher ``ours`` is than ``theirs``, in percent of ``theirs``: 100 (a - b) / b."""
    if ours is None or theirs is None or theirs == 0:
        return None
    return 100.0 * (ours - theirs) / theirs


def cloud_lines(metrics: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The evaluated global models: the pretrained one (stage I, round 0) and each cloud aggregation (III)."""
    return [m for m in metrics if m.get("stage") in ("I", "III") and m.get("accuracy") is not None]


def curve_by_round(runs: Sequence[Sequence[Mapping[str, Any]]], key: str) -> dict[str, np.ndarray]:
    """Mean and spread over runs of ``key`` at each cloud round (rounds some runs lack use the others)."""
    by_round: dict[int, list[float]] = {}
    for lines in runs:
        for m in cloud_lines(lines):
            if m.get(key) is not None:
                by_round.setdefault(int(m["cloud_round"]), []).append(float(m[key]))
    rounds = sorted(by_round)
    stats = [mean_std(by_round[r]) for r in rounds]
    return _curve(np.array(rounds, float), stats)


def curve_by_bytes(runs: Sequence[Sequence[Mapping[str, Any]]], key: str) -> dict[str, np.ndarray]:
    """``key`` against consumed bytes: at each cloud round, the mean over runs of both the bytes
    consumed by then and ``key`` (with the paper's accounting every seed consumes the same bytes)."""
    by_round: dict[int, list[tuple[float, float]]] = {}
    for lines in runs:
        for m in cloud_lines(lines):
            if m.get(key) is not None:
                by_round.setdefault(int(m["cloud_round"]), []).append((float(m["consumed_bytes"]), float(m[key])))
    rounds = sorted(by_round)
    x = np.array([np.mean([b for b, _ in by_round[r]]) for r in rounds], float)
    return _curve(x, [mean_std(v for _, v in by_round[r]) for r in rounds])


def _curve(x: np.ndarray, stats: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    mean = np.array([s["mean"] for s in stats], float)
    std = np.array([np.nan if s["std"] is None else s["std"] for s in stats], float)
    return {"x": x, "mean": mean, "std": std, "n": np.array([s["n"] for s in stats], int)}


# ------------------------------------------------------------------ reading the folder


def read_json(path: Path) -> Any:
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise CrchflError(f"{path}: not readable JSON ({exc}); rerun the part that writes it") from None


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def read_seed_runs(folder: Path) -> dict[int, dict[str, Any]]:
    """seed -> {"summary", "metrics", "config"} of each ``folder/seed-S`` holding a summary.json."""
    runs = {}
    for summary_path in sorted(Path(folder).glob("seed-*/summary.json")):
        run_dir = summary_path.parent
        try:
            seed = int(run_dir.name.split("-", 1)[1])
        except ValueError:
            continue
        config_path = run_dir / "config.json"
        runs[seed] = {
            "summary": read_json(summary_path),
            "metrics": read_jsonl(run_dir / "metrics.jsonl"),
            "config": read_json(config_path) if config_path.is_file() else None,
        }
    return dict(sorted(runs.items()))


def _ordered(names: Iterable[str], order: Sequence[str]) -> list[str]:
    names = list(names)
    return [n for n in order if n in names] + sorted(n for n in names if n not in order)


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
            labels = [p.name for p in route_dir.iterdir() if (p / "metrics.json").is_file()]
            if labels:
                drives[route_dir.name] = {
                    label: read_json(route_dir / label / "metrics.json") for label in _ordered(labels, LABEL_ORDER)
                }
    if not schemes and not ablation:
        raise CrchflError(
            f"{out_dir}: no finished run (runs/SCHEME/seed-S/summary.json); "
            f"run `crchfl-sumo reproduce --out {out_dir}` first"
        )
    reproduce_path = out_dir / "reproduce.json"
    timings_path = out_dir / "timings.json"
    return {
        "out_dir": out_dir,
        "schemes": schemes,
        "ablation": ablation,
        "centralized": read_seed_runs(out_dir / "centralized"),
        "drives": drives,
        "reproduce": read_json(reproduce_path) if reproduce_path.is_file() else {},
        "timings": read_json(timings_path) if timings_path.is_file() else {},
    }


# ------------------------------------------------------------------ summary (pure)


def scheme_stats(runs: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """Per-seed values and their mean/std of one scheme's (or ablation setting's) runs."""
    summaries = [r["summary"] for r in runs.values()]
    stats: dict[str, Any] = {"seeds": list(runs)}
    for key in ("cloud_rounds", "edge_aggregations", "best_accuracy", "final_accuracy", "best_loss", "final_loss",
                "consumed_bytes", "sim_time_s"):
        values = [s.get(key) for s in summaries]
        stats[key] = {**mean_std(values), "values": values}
    stats["budget_bytes"] = summaries[0].get("budget_bytes")
    stats["stop_reason"] = [s.get("stop_reason") for s in summaries]
    stats["hyper"] = summaries[0].get("hyper")
    by_stage = [s.get("bytes_by_stage") or {} for s in summaries]
    stats["bytes_by_stage"] = {stage: mean_std(b.get(stage) for b in by_stage)["mean"] for stage in STAGES}
    return stats


def centralized_stats(runs: Mapping[int, Mapping[str, Any]]) -> dict[str, Any] | None:
    if not runs:
        return None
    summaries = [r["summary"] for r in runs.values()]
    stats: dict[str, Any] = {"seeds": list(runs), "epochs": summaries[0].get("epochs")}
    for key in ("best_accuracy", "final_accuracy", "best_loss", "final_loss"):
        values = [s.get(key) for s in summaries]
        stats[key] = {**mean_std(values), "values": values}
    return stats


def gains(schemes: Mapping[str, Mapping[str, Any]], ours: str = "crchfl") -> dict[str, Any]:
    """CRCHFL's accuracy over each other scheme: relative (% of theirs) and in points, for the
    best and the final accuracy (means over seeds), next to the paper's figures."""
    out: dict[str, Any] = {"paper_percent": dict(PAPER_GAINS_PERCENT)}
    if ours not in schemes:
        return out
    for key in ("best_accuracy", "final_accuracy"):
        mine = schemes[ours][key]["mean"]
        out[key] = {}
        for other, stats in schemes.items():
            if other == ours:
                continue
            theirs = stats[key]["mean"]
            out[key][other] = {
                "relative_percent": relative_gain_percent(mine, theirs),
                "points": None if mine is None or theirs is None else 100.0 * (mine - theirs),
            }
    return out


def timing_groups(timings: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """Wall and CPU seconds per kind of part (data, centralized, runs, ablation, drives) and in total.

    The total also has ``elapsed_s``: the time during which at least one part ran (parts run side
    by side with ``--jobs``; a part recorded without its start time counts its whole wall time).
    """
    groups: dict[str, dict[str, float]] = {}
    for key, spent in list(timings.items()):
        for group in (key.split("/", 1)[0], "total"):
            sums = groups.setdefault(group, {"wall_s": 0.0, "cpu_s": 0.0})
            for unit in ("wall_s", "cpu_s"):
                sums[unit] += float(spent.get(unit, 0.0))
    total = groups.pop("total", {"wall_s": 0.0, "cpu_s": 0.0})
    total["elapsed_s"] = elapsed_s(timings.values())
    return {**groups, "total": total}


def elapsed_s(spans: Iterable[Mapping[str, float]]) -> float:
    """Length of the union of the intervals [start_unix, start_unix + wall_s]; a span without a start adds its wall."""
    spans = list(spans)
    intervals = sorted((s["start_unix"], s["start_unix"] + s["wall_s"]) for s in spans if "start_unix" in s)
    covered = sum(float(s.get("wall_s", 0.0)) for s in spans if "start_unix" not in s)
    end = -math.inf
    for start, stop in intervals:
        covered += max(0.0, stop - max(start, end))
        end = max(end, stop)
    return covered


def build_summary(results: Mapping[str, Any]) -> dict[str, Any]:
    """summary.json: per scheme cloud_rounds, accuracies and losses (mean, std), bytes, closed loop."""
    schemes = {name: scheme_stats(runs) for name, runs in results["schemes"].items()}
    for name, stats in schemes.items():
        stats["closed_loop"] = {
            route: labels[name] for route, labels in results["drives"].items() if name in labels
        }
    ablation = {}
    for setting, runs in results["ablation"].items():
        stats = scheme_stats(runs)
        budget = stats["budget_bytes"] or 0
        spent = {s: stats["bytes_by_stage"][s] or 0.0 for s in STAGES}
        stats["budget_percent"] = {
            **{s: 100.0 * spent[s] / budget if budget else None for s in STAGES},
            "unused": 100.0 * (budget - sum(spent.values())) / budget if budget else None,
        }
        ablation[setting] = stats
    reproduce = results["reproduce"]
    return {
        "mode": (reproduce.get("config") or {}).get("name"),
        "seeds": reproduce.get("seeds"),
        "schemes": schemes,
        "gains": gains(schemes),
        "centralized": centralized_stats(results["centralized"]),
        "ablation": ablation,
        "closed_loop": results["drives"],
        "running_time_s": timing_groups(results["timings"]),
    }


# ------------------------------------------------------------------ figures


def _band(
    ax,
    curve: Mapping[str, np.ndarray],
    label: str,
    color: Any,
    scale_x: float = 1.0,
    style: tuple[str, str] = ("-", "o"),
    limits: tuple[float, float] | None = None,
) -> None:
    """Mean line with markers; mean +- std shaded where there is a spread (two seeds or more),
    clipped to ``limits`` (Accuracy cannot leave [0, 1])."""
    x = curve["x"] / scale_x
    n = int(curve["n"].max()) if len(curve["n"]) else 0
    ax.plot(x, curve["mean"], linestyle=style[0], marker=style[1], markersize=4, color=color, label=f"{label} (n={n})")
    std = curve["std"]
    if np.any(np.isfinite(std)):
        spread = np.nan_to_num(std)
        low, high = curve["mean"] - spread, curve["mean"] + spread
        if limits is not None:
            low, high = np.clip(low, *limits), np.clip(high, *limits)
        ax.fill_between(x, low, high, color=color, alpha=0.2, linewidth=0)


def _upper_bound(ax, centralized: Mapping[str, Any] | None, key: str) -> None:
    if centralized and centralized[key]["mean"] is not None:
        ax.axhline(
            centralized[key]["mean"], color="black", linestyle="--", linewidth=1, label="centralized (best epoch)"
        )


def plot_metric_curves(
    groups: Mapping[str, Sequence[Sequence[Mapping[str, Any]]]],
    out_path: Path,
    against: str,
    title: str,
    centralized: Mapping[str, Any] | None = None,
    colors: Mapping[str, str] | None = None,
    names: Mapping[str, str] | None = None,
) -> Path:
    """Two panels, Accuracy and Loss, one line per group (mean over its runs, shaded spread), against
    cloud rounds (``against="rounds"``) or consumed GB (``"bytes"``)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    curve = curve_by_round if against == "rounds" else curve_by_bytes
    scale = 1.0 if against == "rounds" else GIB
    for ax, key, ylabel, bound in (
        (axes[0], "accuracy", "Accuracy (steer class, test set)", "best_accuracy"),
        (axes[1], "loss", "Loss (test set)", "best_loss"),
    ):
        limits = (0.0, 1.0) if key == "accuracy" else None
        for name, runs in groups.items():
            _band(ax, curve(runs, key), (names or NAMES).get(name, name), (colors or COLORS).get(name), scale,
                  STYLES.get(name, ("-", "o")), limits)
        _upper_bound(ax, centralized, bound)
        ax.set_xlabel("FL (cloud) rounds" if against == "rounds" else "consumed bytes [GB]")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, out_path)


def plot_ablation(
    summary_ablation: Mapping[str, Mapping[str, Any]], runs: Mapping[str, Mapping[int, Any]], out_path: Path
) -> Path:
    """Fig. 7: (a) the budget split across stages per setting, (b) Loss and (c) Accuracy against rounds."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    settings = list(summary_ablation)
    labels = [f"Interval-{s[3:]}" for s in settings]
    bottom = np.zeros(len(settings))
    for part, color in zip((*STAGES, "unused"), ("tab:orange", "tab:blue", "tab:red", "lightgrey")):
        share = np.array([summary_ablation[s]["budget_percent"][part] or 0.0 for s in settings])
        axes[0].bar(labels, share, bottom=bottom, color=color, label=f"stage {part}" if part != "unused" else "unused")
        for i, value in enumerate(share):
            if value >= 3:
                axes[0].text(i, bottom[i] + value / 2, f"{value:.1f}%", ha="center", va="center", fontsize=8)
        bottom += share
    axes[0].set_ylabel("share of the budget [%]")
    axes[0].set_title("(a) budget split across stages")
    axes[0].legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=4)
    cmap = plt.get_cmap("viridis")
    for panel, key, ylabel in ((axes[1], "loss", "Loss"), (axes[2], "accuracy", "Accuracy")):
        for i, setting in enumerate(settings):
            metrics = [r["metrics"] for r in runs[setting].values()]
            _band(panel, curve_by_round(metrics, key), labels[i], cmap(i / max(len(settings) - 1, 1)),
                  limits=(0.0, 1.0) if key == "accuracy" else None)
        panel.set_xlabel("FL (cloud) rounds")
        panel.set_ylabel(ylabel)
        panel.grid(alpha=0.3)
        panel.legend(fontsize=8)
    axes[1].set_title("(b) Loss")
    axes[2].set_title("(c) Accuracy")
    return save_figure(fig, out_path)


def plot_centralized(runs: Mapping[int, Mapping[str, Any]], out_path: Path) -> Path:
    """The centralized bound's test Accuracy and Loss per epoch (mean over seeds, shaded spread)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key in ((axes[0], "accuracy"), (axes[1], "loss")):
        by_epoch: dict[int, list[float]] = {}
        for run in runs.values():
            for m in run["metrics"]:
                by_epoch.setdefault(int(m["epoch"]), []).append(float(m[key]))
        epochs = sorted(by_epoch)
        curve = _curve(np.array(epochs, float), [mean_std(by_epoch[e]) for e in epochs])
        _band(ax, curve, "centralized", "black", limits=(0.0, 1.0) if key == "accuracy" else None)
        ax.set_xlabel("epoch")
        ax.set_ylabel(key.capitalize())
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Centralized upper bound")
    return save_figure(fig, out_path)


def drive_figure(out_dir: Path, route: str, labels: Sequence[str], figures_dir: Path) -> Path | None:
    """Fig. 5 for one route (drive_plots.compare_runs); None when a drive lacks its trajectory."""
    from crchfl_sumo.driving.plots import compare_runs

    folders = [out_dir / "drives" / route / label for label in labels]
    if not all((f / "trajectory.csv").is_file() for f in folders):
        return None
    path = figures_dir / f"fig5_drive_{route}.png"
    with atomic_path(path) as tmp:
        compare_runs(folders, [NAMES.get(label, label) for label in labels], tmp)
    return path


# ------------------------------------------------------------------ report.md


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.{digits}f}"
    return str(value)


def _seeds(stats: Mapping[str, Any]) -> str:
    """The seed count; runs still going (no stop_reason yet: a reproduction in progress) are named."""
    unfinished = sum(reason is None for reason in stats["stop_reason"])
    return f"{len(stats['seeds'])}" + (f" ({unfinished} unfinished)" if unfinished else "")


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{value:+.2f} %"


def _pm(stats: Mapping[str, Any], digits: int = 4, scale: float = 1.0) -> str:
    if stats["mean"] is None:
        return "-"
    text = f"{stats['mean'] * scale:.{digits}f}"
    return text + (f" ± {stats['std'] * scale:.{digits}f}" if stats["std"] is not None else "")


def _table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def report_markdown(summary: Mapping[str, Any], results: Mapping[str, Any], figures: Mapping[str, str]) -> str:
    """report.md: what ran, the tables, every figure, the settings, the versions and the times."""
    reproduce = results["reproduce"]
    config = reproduce.get("config") or {}
    env = reproduce.get("environment") or {}
    times = summary["running_time_s"]
    lines = [f"# CRCHFL reproduction: {summary['mode'] or 'results'}", ""]
    lines += [
        f"Results folder `{results['out_dir'].name}`, started {reproduce.get('started_utc', '-')}; "
        f"seeds {summary['seeds']}, ablation seeds {reproduce.get('ablation_seeds')}. "
        f"Running time: {times['total']['elapsed_s'] / 60:.1f} min elapsed (the parts' wall times sum to "
        f"{times['total']['wall_s'] / 60:.1f} min, CPU {times['total']['cpu_s'] / 60:.1f} min). "
        "Every ± is the sample standard deviation over seeds (none with one seed).",
        "",
        "## Experiment B: CRCHFL, HFL and SFL under one budget",
        "",
    ]
    schemes = summary["schemes"]
    rows = []
    for name, s in schemes.items():
        rows.append([
            NAMES.get(name, name), _pm(s["cloud_rounds"], 1), _pm(s["best_accuracy"]), _pm(s["final_accuracy"]),
            _pm(s["best_loss"]), _pm(s["final_loss"]), _pm(s["consumed_bytes"], 2, 1 / GIB),
            _fmt(s["budget_bytes"] / GIB if s["budget_bytes"] else None, 2), _seeds(s),
        ])
    central = summary["centralized"]
    if central:
        rows.append([
            f"Centralized ({central['epochs']} epochs)", "-", _pm(central["best_accuracy"]),
            _pm(central["final_accuracy"]), _pm(central["best_loss"]), _pm(central["final_loss"]), "-", "-",
            str(len(central["seeds"])),
        ])
    lines += _table(
        ["scheme", "cloud rounds", "best accuracy", "final accuracy", "best loss", "final loss", "consumed GB",
         "budget GB", "seeds"],
        rows,
    )
    gain = summary["gains"]
    if "best_accuracy" in gain:
        lines += ["", "Gains of CRCHFL's accuracy (means over seeds; relative: 100 (CRCHFL - other) / other):", ""]
        rows = []
        for other, paper in PAPER_GAINS_PERCENT.items():
            if other not in gain["best_accuracy"]:
                continue
            best, final = gain["best_accuracy"][other], gain["final_accuracy"][other]
            rows.append([
                f"over {NAMES[other]}", _percent(best["relative_percent"]), _fmt(best["points"], 2),
                _percent(final["relative_percent"]), _fmt(final["points"], 2), f"+{paper:.2f} %",
            ])
        lines += _table(
            ["", "best accuracy, relative", "best, points", "final accuracy, relative", "final, points", "paper"], rows
        )
        lines += [
            "",
            "The paper does not say whether its +10.33 % and +12.41 % are relative or in points; both are given here.",
        ]
    for key, caption in (
        ("fig3", "Fig. 3: Accuracy and Loss against FL rounds (round 0: CRCHFL's pretrained model)"),
        ("fig4", "Fig. 4: Accuracy and Loss against consumed bytes"),
        ("centralized", "Centralized upper bound per epoch"),
    ):
        if key in figures:
            lines += ["", f"![{caption}](figures/{figures[key]})", "", f"*{caption}* (`figures/{figures[key]}`)"]
    if summary["ablation"]:
        lines += ["", "## Experiment D: CRCHFL with edge_interval fixed", ""]
        rows = []
        for setting, s in summary["ablation"].items():
            hyper = s["hyper"] or {}
            pct = s["budget_percent"]
            rows.append([
                setting[3:], _fmt(hyper.get("pretrain_batch")), _fmt(hyper.get("cloud_interval")),
                _pm(s["cloud_rounds"], 1), *(_fmt(pct[p], 1) for p in (*STAGES, "unused")),
                _pm(s["best_accuracy"]), _pm(s["final_loss"]), _seeds(s),
            ])
        lines += _table(
            ["edge_interval", "pretrain batch", "cloud_interval", "cloud rounds", "stage I %", "stage II %",
             "stage III %", "unused %", "best accuracy", "final loss", "seeds"],
            rows,
        )
        if "fig7" in figures:
            caption = "Fig. 7: (a) budget split across stages, (b) Loss, (c) Accuracy"
            lines += ["", f"![{caption}](figures/{figures['fig7']})", "", f"*{caption}* (`figures/{figures['fig7']}`)"]
    if summary["closed_loop"]:
        lines += ["", "## Closed loop: each scheme's best model drives", ""]
        lines += [
            "The model of the seed with the highest best accuracy (its best_model.pt; centralized: the last "
            "epoch of the seed that ended best) drives each route in SUMO; the reference is the scripted driver.",
        ]
        for route, labels in summary["closed_loop"].items():
            lines += ["", f"### {route}", ""]
            rows = [
                [NAMES.get(label, label), *(_fmt(m.get(c), 3) for c in DRIVE_COLUMNS)] for label, m in labels.items()
            ]
            lines += _table(["model", *DRIVE_COLUMNS], rows)
            key = f"fig5_{route}"
            if key in figures:
                path = f"figures/{figures[key]}"
                lines += ["", f"![Fig. 5, {route}]({path})", "", f"*Fig. 5, {route}* (`{path}`)"]
    lines += ["", "## Settings", "", "Reproduction settings (reproduce.json):", "", "```json",
              json.dumps(config, indent=2), "```"]
    hyper_rows = []
    for name, s in schemes.items():
        hyper = s["hyper"] or {}
        values = (_fmt(hyper.get(k)) for k in HYPER)
        hyper_rows.append([NAMES.get(name, name), *values, ", ".join(map(str, s["seeds"]))])
    if hyper_rows:
        lines += ["", "Hyper-parameters the runs used (CRCHFL: the optimizer's plan; cloud_rounds 0 = until the "
                  "budget is spent). Each run's full settings: `runs/SCHEME/seed-S/config.json`.", ""]
        lines += _table(["scheme", *HYPER, "seeds"], hyper_rows)
    lines += ["", "## Environment and running time", ""]
    versions = env.get("versions") or {}
    lines += [
        f"Python {env.get('python', '-')}, {env.get('platform', '-')}, {env.get('cpu_count', '-')} CPUs, "
        f"{env.get('torch_threads', '-')} torch threads, CUDA {_fmt(env.get('cuda'))}.",
        "",
    ]
    lines += _table(["package", "version"], [[k, _fmt(v)] for k, v in versions.items()])
    lines += [""]
    lines += _table(
        ["part", "wall time [s]", "CPU time [s]"],
        [[k, f"{v['wall_s']:.1f}", f"{v['cpu_s']:.1f}"] for k, v in times.items()],
    )
    lines += ["", "Figures: " + ", ".join(f"`figures/{name}`" for name in figures.values()), ""]
    return "\n".join(lines)


def write_report(out_dir: str | Path) -> dict[str, Any]:
    """Figures, report.md and summary.json of a results folder, from its files alone; returns the summary."""
    out_dir = Path(out_dir)
    results = read_results(out_dir)
    summary = build_summary(results)
    figures_dir = out_dir / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    figures: dict[str, str] = {}
    groups = {name: [r["metrics"] for r in runs.values()] for name, runs in results["schemes"].items()}
    if groups:
        plot_metric_curves(groups, figures_dir / FIGURES["fig3"], "rounds",
                           "Fig. 3: CRCHFL vs HFL vs SFL against FL rounds", summary["centralized"])
        figures["fig3"] = FIGURES["fig3"]
        plot_metric_curves(groups, figures_dir / FIGURES["fig4"], "bytes",
                           "Fig. 4: CRCHFL vs HFL vs SFL against consumed bytes", summary["centralized"])
        figures["fig4"] = FIGURES["fig4"]
    if results["centralized"]:
        plot_centralized(results["centralized"], figures_dir / "centralized.png")
        figures["centralized"] = "centralized.png"
    if summary["ablation"]:
        plot_ablation(summary["ablation"], results["ablation"], figures_dir / FIGURES["fig7"])
        figures["fig7"] = FIGURES["fig7"]
    for route, labels in results["drives"].items():
        path = drive_figure(out_dir, route, list(labels), figures_dir)
        if path is not None:
            figures[f"fig5_{route}"] = path.name
    summary["figures"] = {key: f"figures/{name}" for key, name in figures.items()}
    atomic_write_text(out_dir / "report.md", report_markdown(summary, results, figures))
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    log.info("report of %s: %d figures", out_dir, len(figures))
    return summary


def report_command(out_dir: str | Path) -> dict[str, Any]:
    """What `crchfl-sumo report DIR` does: rebuild DIR's figures, report.md and summary.json."""
    return write_report(out_dir)


def format_summary(summary: Mapping[str, Any], out_dir: str | Path) -> str:
    """A few lines for the terminal: each scheme's rounds and accuracy, the gains, where the report is."""
    lines = []
    for name, s in summary["schemes"].items():
        lines.append(
            f"{NAMES.get(name, name):7s} cloud rounds {_pm(s['cloud_rounds'], 1)}, best accuracy "
            f"{_pm(s['best_accuracy'])}, final loss {_pm(s['final_loss'])} ({len(s['seeds'])} seeds)"
        )
    best = summary["gains"].get("best_accuracy", {})
    for other, paper in PAPER_GAINS_PERCENT.items():
        if other in best:
            lines.append(
                f"CRCHFL over {NAMES[other]}: {_percent(best[other]['relative_percent'])} best accuracy "
                f"(paper: +{paper:.2f} %)"
            )
    total = summary["running_time_s"]["total"]
    lines.append(f"running time {total['elapsed_s'] / 60:.1f} min -> {Path(out_dir) / 'report.md'}")
    return "\n".join(lines)
