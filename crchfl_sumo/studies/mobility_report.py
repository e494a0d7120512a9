"""The mobility study's report: one row per factor value, a table and one figure per factor.

Pure up to the writing: rows are made from the runs' summaries (summary.json),
so the report of hand-made summaries is the report of real runs.
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
COLUMNS = ("factor", "key", "value", "point", *(m[0] for m in METRICS), *EXTRA_COLUMNS)


def study_rows(factors: Sequence, plan, summaries: dict[str, dict]) -> list[dict]:
    """One row per factor value: the factor, the value's label, its run's point and metrics."""
    rows = []
    for factor in factors:
        for label, name in zip(factor.labels, plan.factor_points[factor.name]):
            summary = summaries[name]
            rows.append({
                "factor": factor.name,
                "key": factor.param.path,
                "value": label,
                "point": name,
                **{key: summary.get(key) for key, _, _ in METRICS},
                **{key: summary.get(key) for key in EXTRA_COLUMNS},
            })
    return rows


def write_report(out_dir: Path, factors: Sequence, rows: Sequence[dict]) -> list[Path]:
    """results.csv, results.md and plots/FACTOR.png in ``out_dir``; returns the figures' paths."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        writer.writerow(["" if row.get(c) is None else row[c] for c in COLUMNS])
    atomic_write_text(out_dir / "results.csv", buffer.getvalue())
    atomic_write_text(out_dir / "results.md", markdown_table(rows))
    base = next((r for r in rows if r["point"] == "base"), None)  # any factor's row of the baseline run
    return [
        plot_factor(factor, [r for r in rows if r["factor"] == factor.name], base, out_dir / "plots") for factor in factors
    ]


def markdown_table(rows: Sequence[dict]) -> str:
    """The table of docs/sweep.md: bytes in MB, the baseline's rows marked with *."""
    header = ["factor", "value", "best acc", "best bal. acc", "rounds", "handovers", "stragglers", "relayed MB",
              "wasted MB", "failed uploads", "sim s", "stop"]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for r in rows:
        cells = [
            r["factor"],
            r["value"] + (" *" if r["point"] == "base" else ""),
            _fmt(r["best_accuracy"], "{:.3f}"),
            _fmt(r["balanced_accuracy"], "{:.3f}"),
            _fmt(r["cloud_rounds"]),
            _fmt(r["handovers"]),
            _fmt(r["stragglers"]),
            _fmt(_scaled(r["relay_bytes"], MB), "{:.0f}"),
            _fmt(_scaled(r["wasted_bytes"], MB), "{:.0f}"),
            f"{_fmt(r['uploads_failed'])}/{_fmt(r['uploads'])}",
            _fmt(r["sim_time_s"], "{:.0f}"),
            _fmt(r["stop_reason"]),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n* the baseline run\n"


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


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _short(text: str, limit: int = 24) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."
