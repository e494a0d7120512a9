"""The mobility study's report: one row per factor value, a table and one figure per factor, the findings.

Pure up to the writing: rows are made from the runs' summaries (summary.json) and
the benchmarks' (drive-bench summary.json), seed by seed, so the report of
hand-made summaries is the report of real runs. A row's figures are means over
the point's seeds; balanced accuracy carries its 95 % interval (Student t).
The findings compare each factor value with the baseline, paired by seed.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.figures import pyplot, save_figure
from crchfl_sumo.core.intervals import distinguishable
from crchfl_sumo.core.result_files import RESULTS_CSV_FILE, RESULTS_MD_FILE
from crchfl_sumo.studies.statistics import bench_overall, mean_std, paired_by_seed, seed_mean
from crchfl_sumo.studies.sweep import BASE_POINT as BASELINE, STRAIGHT_COLUMNS, always_straight_columns

MB = 2**20

# (row key, figure panel title, divisor): what mobility can change in a run
METRICS = (
    ("best_accuracy", "best accuracy", 1),
    ("balanced_accuracy", "best balanced accuracy", 1),
    ("cloud_rounds", "cloud rounds reached", 1),
    ("handovers", "handovers", 1),
    ("stragglers", "stragglers", 1),
    ("relay_bytes", "relayed MB", MB),
    ("wasted_bytes", "wasted MB", MB),
    ("uploads_failed", "failed uploads", 1),
)
EXTRA_COLUMNS = ("relayed_transfers", "uploads", "downloads_failed", "edge_aggregations", "sim_time_s", "stop_reason")
# results.csv's columns other tools read (docs/sweep.md): seeds, the interval, the closed loop, the cells' rate
STUDY_COLUMNS = ("seeds", "balanced_accuracy_mean", "balanced_accuracy_ci_lo", "balanced_accuracy_ci_hi",
                 "driving_score_mean", "success_rate_mean", "mean_uplink_rate_mbps")
COLUMNS = ("factor", "key", "value", "point", *STUDY_COLUMNS, *(m[0] for m in METRICS), *STRAIGHT_COLUMNS,
           *EXTRA_COLUMNS)
# The outcomes the findings test for a move beyond noise, with how they are written.
FINDINGS = (
    ("balanced_accuracy", "balanced accuracy", "{:+.3f}"),
    ("driving_score", "driving score", "{:+.3f}"),
    ("success_rate", "success", "{:+.3f}"),
    ("mean_uplink_rate_mbps", "uplink Mbit/s", "{:+.1f}"),
    ("cloud_rounds", "cloud rounds", "{:+.1f}"),
    ("stragglers", "stragglers", "{:+.1f}"),
    ("wasted_bytes", "wasted MB", "{:+.0f}"),
)


def seed_outcomes(summaries: dict[int, dict], benches: dict[int, dict]) -> dict[str, dict[int, Any]]:
    """Per outcome, per seed: the run's figures, with the benchmark's driving score and success where it drove."""
    outcomes: dict[str, dict[int, Any]] = {}
    for seed, summary in summaries.items():
        for key in (*(m[0] for m in METRICS), *EXTRA_COLUMNS, "mean_uplink_rate_mbps"):
            outcomes.setdefault(key, {})[seed] = summary.get(key)
        for key, value in always_straight_columns(summary).items():
            outcomes.setdefault(key, {})[seed] = value
        for key in ("driving_score", "success_rate") if seed in benches else ():
            outcomes.setdefault(key, {})[seed] = bench_overall(benches[seed], key)
    return outcomes


def study_rows(factors: Sequence, plan, summaries: dict[str, dict[int, dict]],
               benches: dict[str, dict[int, dict]] | None = None) -> list[dict]:
    """One row per factor value: the factor, the value's label, its point, the seeds, and each figure's mean over
    seeds (``summaries[point][seed]``: run summaries; ``benches[point][seed]``: benchmark summaries)."""
    benches = benches or {}
    rows = []
    for factor in factors:
        for label, name in zip(factor.labels, plan.factor_points[factor.name]):
            outcomes = seed_outcomes(summaries[name], benches.get(name, {}))
            accuracy = mean_std(outcomes.get("balanced_accuracy", {}).values())
            ci = accuracy["ci95"] or [None, None]
            rows.append({
                "factor": factor.name,
                "key": factor.param.path,
                "value": label,
                "point": name,
                "seeds": len(summaries[name]),
                "balanced_accuracy_mean": accuracy["mean"],
                "balanced_accuracy_ci_lo": ci[0],
                "balanced_accuracy_ci_hi": ci[1],
                **{key: seed_mean(values.values()) for key, values in outcomes.items()},
                "driving_score_mean": seed_mean(outcomes.get("driving_score", {}).values()),
                "success_rate_mean": seed_mean(outcomes.get("success_rate", {}).values()),
                "outcomes": outcomes,
            })
    return rows


def baseline_row(rows: Sequence[dict]) -> dict | None:
    """Any factor's row of the baseline run (every factor's curve passes through it); None if no row is."""
    return next((r for r in rows if r["point"] == BASELINE), None)


def findings(factors: Sequence, rows: Sequence[dict]) -> list[dict]:
    """Per factor and outcome: each value against the baseline, paired by seed (paired-t 95 % interval); the
    outcome moves where an interval excludes 0. ``moved``: the values that did, with their differences."""
    base = baseline_row(rows)
    found = []
    for factor in factors:
        for key, title, spec in FINDINGS:
            moved, compared = [], 0
            theirs = (base or {"outcomes": {}})["outcomes"].get(key, {})
            for row in (r for r in rows if r["factor"] == factor.name and r["point"] != BASELINE):
                d = paired_by_seed(theirs, row["outcomes"].get(key, {}))
                compared = max(compared, d["n"])
                if distinguishable(d["ci95"]):
                    moved.append((row["value"], d))
            found.append({"factor": factor.name, "outcome": title, "key": key, "spec": spec, "moved": moved,
                          "seeds": compared})
    return found


def findings_table(found: Sequence[dict]) -> str:
    """The findings as markdown: per factor, which outcomes moved beyond their intervals against the baseline."""
    if found and all(f["seeds"] < 2 for f in found):
        return "One seed a point: no intervals, so no findings (a study with `seeds` of 2 or more has them).\n"
    lines = ["| factor | outcome | against the baseline, paired by seed (95 %) |", "| --- | --- | --- |"]
    for f in found:
        if f["seeds"] < 2:
            verdict = "no interval: fewer than 2 seeds"
        elif not f["moved"]:
            verdict = "not distinguishable at any value"
        else:
            scale = MB if f["key"] == "wasted_bytes" else 1
            verdict = "moves: " + "; ".join(f"{value} {f['spec'].format(d['mean'] / scale)}" for value, d in f["moved"])
        lines.append(f"| {f['factor']} | {f['outcome']} | {verdict} |")
    return "\n".join(lines) + "\n"


def write_report(out_dir: Path, factors: Sequence, rows: Sequence[dict]) -> list[Path]:
    """results.csv, results.md (the table, then the findings) and plots/FACTOR.png in ``out_dir``; returns the
    figures' paths."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        writer.writerow(["" if row.get(c) is None else row[c] for c in COLUMNS])
    atomic_write_text(out_dir / RESULTS_CSV_FILE, buffer.getvalue())
    findings_text = findings_table(findings(factors, rows))
    atomic_write_text(out_dir / RESULTS_MD_FILE, markdown_table(rows) + "\n## Findings\n\n" + findings_text)
    base = baseline_row(rows)
    return [
        plot_factor(factor, [r for r in rows if r["factor"] == factor.name], base, out_dir / "plots") for factor in factors
    ]


def markdown_table(rows: Sequence[dict]) -> str:
    """The table of docs/sweep.md: bytes in MB, the baseline's rows marked with *."""
    header = ["factor", "value", "seeds", "best acc", "best bal. acc [95 %]", "driving score", "success",
              "uplink Mbit/s", "rounds", "handovers", "stragglers", "relayed MB", "wasted MB", "failed uploads",
              "sim s", "stop"]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for r in rows:
        interval = ("" if r.get("balanced_accuracy_ci_lo") is None else
                    f" [{r['balanced_accuracy_ci_lo']:.3f}, {r['balanced_accuracy_ci_hi']:.3f}]")
        cells = [
            r["factor"],
            r["value"] + (" *" if r["point"] == BASELINE else ""),
            _fmt(r.get("seeds")),
            _fmt(r["best_accuracy"], "{:.3f}"),
            _fmt(r["balanced_accuracy"], "{:.3f}") + interval,
            _fmt(r.get("driving_score_mean"), "{:.3f}"),
            _fmt(r.get("success_rate_mean"), "{:.3f}"),
            _fmt(r.get("mean_uplink_rate_mbps"), "{:.1f}"),
            _count(r["cloud_rounds"]),
            _count(r["handovers"]),
            _count(r["stragglers"]),
            _fmt(_scaled(r["relay_bytes"], MB), "{:.0f}"),
            _fmt(_scaled(r["wasted_bytes"], MB), "{:.0f}"),
            f"{_count(r['uploads_failed'])}/{_count(r['uploads'])}",
            _fmt(r["sim_time_s"], "{:.0f}"),
            _fmt(r["stop_reason"]),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    marks = "\n* the baseline run; every figure is the mean over the point's seeds\n"
    return "\n".join(lines) + "\n" + marks + straight_line(rows)


def straight_line(rows: Sequence[dict]) -> str:
    """What the accuracies read against: the always-straight prediction on the study's test set (one data set
    serves every point, so the baseline's row holds it); empty where the runs recorded none."""
    base = baseline_row(rows) or (rows[0] if rows else {})
    accuracy, balanced = (base.get(key) for key in STRAIGHT_COLUMNS)
    if accuracy is None or balanced is None:
        return ""
    return f"\nAlways straight on the study's test set: accuracy {accuracy:.3f}, balanced accuracy {balanced:.3f}.\n"


def plot_factor(factor, rows: Sequence[dict], base: dict | None, out_dir: Path) -> Path:
    """The metrics against one factor's values; the baseline's value of each metric (``base``) as a dashed line.

    The line is drawn for a factor whose values miss the baseline too (edge-site count: the baseline has the
    scenario's sites)."""
    plt = pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    xs = positions(factor.param.values)
    fig, axes = plt.subplots(2, 4, figsize=(16, 7), constrained_layout=True)
    for ax, (key, title, divisor) in zip(axes.flat, METRICS):
        points = [(x, _scaled(r[key], divisor)) for x, r in zip(xs, rows) if _is_number(r.get(key))]
        if points:
            ax.plot(*zip(*points), marker="o")
        if base is not None and _is_number(base.get(key)):
            ax.axhline(_scaled(base[key], divisor), color="grey", linestyle="--", linewidth=1, label="baseline")
        ax.set_title(title)
        ax.set_xlabel(factor.name)
        ax.set_xticks(xs, [_short(label) for label in factor.labels], rotation=20)
        ax.grid(alpha=0.3)
    fig.suptitle(f"mobility study: metrics against {factor.name} ({factor.param.path}); dashed: the baseline")
    return save_figure(fig, out_dir / f"{file_name(factor.name)}.png", dpi=90)


def positions(values: Sequence[Any]) -> list[float]:
    """x of each value: the value when all are finite numbers, else 0, 1, 2 ... in the given order."""
    if all(_is_number(v) and math.isfinite(v) for v in values):
        return [float(v) for v in values]
    return [float(i) for i in range(len(values))]


def file_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _scaled(value: Any, divisor: float) -> Any:
    return value / divisor if _is_number(value) else value


def _fmt(value: Any, spec: str = "{}") -> str:
    if value is None:
        return "-"
    return spec.format(value) if _is_number(value) else str(value)


def _count(value: Any) -> str:
    """A count, or the mean of a count over seeds: whole numbers as they are, other means to one decimal."""
    return _fmt(value, "{:.0f}" if _is_number(value) and float(value).is_integer() else "{:.1f}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _short(text: str, limit: int = 24) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."
