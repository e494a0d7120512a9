"""`crchfl-sumo report DIR`: figures, tables, report.md and summary.json from a results folder alone.

Reads only what the runs wrote (studies/reproduce.py lays the folder out):
``runs/SCHEME/seed-S/`` and ``ablation/ie-K/seed-S/`` (federation/run.py: summary.json,
metrics.jsonl, config.json), ``centralized/seed-S/`` (learning/centralized.py's
metrics.jsonl and studies/reproduce.py's summary.json), ``drives/ROUTE/LABEL/``
(driving/drive.py: metrics.json, trajectory.csv), ``reproduce.json`` and
``timings.json``. Writes ``figures/*.png``, ``report.md`` (its sections: studies/report_sections.py) and
``summary.json``, each atomically. Every statistic over seeds is the mean and
the sample standard deviation (ddof = 1; none for a single seed).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

from crchfl_sumo.core.atomic import atomic_write_text, remove_stale_temporaries
from crchfl_sumo.core.json_files import write_json
from crchfl_sumo.core.result_files import SUMMARY_FILE
from crchfl_sumo.studies.report_figures import (
    FIGURES,
    NAMES,
    drive_figure,
    plot_ablation,
    plot_budget_curve,
    plot_centralized,
    plot_metric_curves,
)
from crchfl_sumo.studies.report_sections import _difference_words, _fmt, _percent, _pm, lead_sentence, report_markdown
from crchfl_sumo.studies.results import read_results
from crchfl_sumo.studies.statistics import PAPER_GAINS_PERCENT, bench_overall, build_summary

log = logging.getLogger(__name__)


def write_report(out_dir: str | Path) -> dict[str, Any]:
    """Figures, report.md and summary.json of a results folder, from its files alone; returns the summary."""
    out_dir = Path(out_dir)
    results = read_results(out_dir)
    summary = build_summary(results)
    figures_dir = out_dir / "figures"
    figures_dir.mkdir(parents=True, exist_ok=True)
    for folder in (out_dir, figures_dir):  # what a report (or reproduce) killed while writing left
        remove_stale_temporaries(folder)
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
    if summary.get("budget_curve"):
        plot_budget_curve(summary["budget_curve"], figures_dir / FIGURES["budget"])
        figures["budget"] = FIGURES["budget"]
    for route, labels in results["drives"].items():
        path = drive_figure(out_dir, route, list(labels), figures_dir)
        if path is not None:
            figures[f"fig5_{route}"] = path.name
    summary["figures"] = {key: f"figures/{name}" for key, name in figures.items()}
    atomic_write_text(out_dir / "report.md", report_markdown(summary, results, figures))
    write_json(out_dir / SUMMARY_FILE, summary)
    log.info("report of %s: %d figures", out_dir, len(figures))
    return summary


def report_command(out_dir: str | Path) -> dict[str, Any]:
    """What `crchfl-sumo report DIR` does: rebuild DIR's figures, report.md and summary.json."""
    return write_report(out_dir)


def format_summary(summary: Mapping[str, Any], out_dir: str | Path) -> str:
    """A few lines for the terminal: each scheme's rounds, balanced accuracy (beside accuracy and the
    always-straight baseline), the paired differences, the gains, where the report is."""
    lines = []
    bench = summary.get("drive_bench") or {}
    for name, s in summary["schemes"].items():
        driven = ""
        if name in bench:  # the closed loop over all its episodes (every seed's, where every seed drove)
            score, success = (bench_overall({"results": bench[name]}, key) for key in ("driving_score", "success_rate"))
            if score is not None:
                driven = f", driving score {100 * score:.1f}, success {100 * success:.0f} %"
        lines.append(
            f"{NAMES.get(name, name):7s} cloud rounds {_pm(s['cloud_rounds'], 1)}, balanced accuracy "
            f"{_pm(s['balanced_accuracy'])}, best accuracy {_pm(s['best_accuracy'])}{driven} ({len(s['seeds'])} seeds)"
        )
    straight = (summary.get("baselines") or {}).get("always_straight") or {}
    if straight:
        lines.append(f"always straight: balanced accuracy {_fmt(straight.get('balanced_accuracy'))}, "
                     f"accuracy {_fmt(straight.get('accuracy'))}")
    for pair, keys in (summary.get("differences") or {}).items():
        other = NAMES.get(pair.split("-", 1)[1], pair)
        d = keys.get("balanced_accuracy") or {}
        if d.get("n", 0) >= 2:
            lines.append(f"CRCHFL minus {other}, balanced accuracy: {_difference_words(d)}")
        d = (keys.get("by_episode") or {}).get("success_rate") or {}
        if d.get("n", 0) >= 2:
            lines.append(f"CRCHFL minus {other}, closed-loop success by episode: {_difference_words(d)}")
    if summary.get("budget_curve"):
        lines.append(lead_sentence(summary.get("budget_differences") or {}))
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
