"""The report's figures (the paper's Fig. 3, 4, 5 and 7 and the centralized curve), drawn from results and statistics.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from crchfl_sumo.accounting.ledger import GIB
from crchfl_sumo.accounting.schedules import STAGES
from crchfl_sumo.core.atomic import atomic_path
from crchfl_sumo.core.figures import pyplot, save_figure
from crchfl_sumo.core.schemes import CENTRALIZED, CENTRALIZED_DAGGER, DISPLAY_NAMES, REFERENCE
from crchfl_sumo.studies.statistics import _curve, curve_by_bytes, curve_by_round, mean_std

NAMES = {
    **DISPLAY_NAMES, CENTRALIZED: "Centralized", CENTRALIZED_DAGGER: "Centralized + DAgger",
    REFERENCE: "Reference driver",
}


COLORS = {"crchfl": "tab:red", "hfl": "tab:blue", "sfl": "tab:green", "centralized": "black"}


# HFL and SFL give the same model after each round when cloud_interval = 1 (FedAvg over edges, then
# over the cloud, is FedAvg over all vehicles): styles keep a line visible under another.
STYLES = {"crchfl": ("-", "o"), "hfl": ("--", "s"), "sfl": (":", "^")}


FIGURES = {
    "fig3": "fig3_rounds.png",
    "fig4": "fig4_bytes.png",
    "fig7": "fig7_ablation.png",
    "budget": "budget_curve.png",
}


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


def plot_budget_curve(curve: Mapping[str, Mapping[str, Any]], path: Path) -> None:
    """Experiment E: balanced accuracy (left) and driving score (right) against the budget, per scheme,
    the mean over seeds with its 95 % interval as error bars."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    budgets = sorted({float(label) for points in curve.values() for label in points})
    for ax, key, scale, title in ((axes[0], "balanced_accuracy", 1.0, "Balanced accuracy"),
                                  (axes[1], "driving_score", 100.0, "Driving score")):
        for scheme, points in curve.items():
            known = {float(label): p[key] for label, p in points.items() if p[key]["mean"] is not None}
            if not known:
                continue
            x = list(known)
            mean = np.array([s["mean"] for s in known.values()]) * scale
            ci = [s["ci95"] or [s["mean"]] * 2 for s in known.values()]
            ci = np.clip(np.array(ci).T * scale, 0.0, scale)  # neither score leaves [0, scale]
            error = np.abs(ci - mean)
            style = STYLES.get(scheme, ("-", "o"))
            ax.errorbar(x, mean, yerr=error, linestyle=style[0], marker=style[1], capsize=3,
                        color=COLORS.get(scheme), label=NAMES.get(scheme, scheme))
        ax.set_xscale("log", base=2)
        ax.set_xticks(budgets, [f"{b:g}" for b in budgets])
        ax.minorticks_off()
        ax.set_xlabel("budget (GB)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    save_figure(fig, path)
