"""A sweep's figures: every metric against each swept parameter, one PNG per parameter.

For a parameter P, each panel is one metric; each line joins the points
that share the values of the other parameters (the legend names them).
Numeric values sit on a numeric axis, any other values (names, lists of
sites) at evenly spaced positions labelled with the value.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

from crchfl_sumo.core.figures import pyplot, save_figure

# (row key, panel title)
PANELS = (
    ("best_accuracy", "best accuracy"),
    ("final_accuracy", "final accuracy"),
    ("cloud_rounds", "cloud rounds reached"),
    ("handovers", "handovers"),
    ("stragglers", "stragglers"),
    ("wireless_bytes", "wireless bytes"),
    ("wireline_bytes", "wireline bytes"),
)


def plot_sweep(rows: Sequence[dict], params: Sequence, out_dir: Path) -> list[Path]:
    """One figure per parameter with two or more values in ``out_dir`` (``PATH.png``); returns their paths.

    A parameter given a single value is a fixed setting: it gets no figure and does not split the lines.
    """
    plt = pyplot()

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    swept = [p for p in params if len(p.values) > 1]
    for param in swept:
        others = [p.path for p in swept if p.path != param.path]
        xs = axis_positions(param.values)
        fig, axes = plt.subplots(2, 4, figsize=(16, 7), constrained_layout=True)
        for ax, (key, title) in zip(axes.flat, PANELS):
            for label, group in series(rows, param.path, others):
                points = [(xs[_key(r[param.path])], r[key]) for r in group if _is_number(r.get(key))]
                if points:
                    x, y = zip(*sorted(points))
                    ax.plot(x, y, marker="o", label=label or None)
            ax.set_title(title)
            ax.set_xlabel(param.path)
            ax.grid(alpha=0.3)
            if not all(_is_number(v) for v in param.values) or len(param.values) <= 8:
                ax.set_xticks(list(xs.values()), [_short(v) for v in param.values], rotation=20)
        legend_ax = axes.flat[len(PANELS)]
        legend_ax.axis("off")
        handles, labels = axes.flat[0].get_legend_handles_labels()
        if labels:
            legend_ax.legend(handles, labels, loc="center", title=", ".join(others), fontsize="small")
        fig.suptitle(f"sweep: metrics against {param.path}")
        path = out_dir / f"{param.path}.png"
        paths.append(save_figure(fig, path, dpi=90))
    return paths


def axis_positions(values: Sequence[Any]) -> dict[str, float]:
    """x position of each value: the value itself when all are numbers, else 0, 1, 2 ... in the given order."""
    if all(_is_number(v) for v in values) and all(math.isfinite(float(v)) for v in values):
        return {_key(v): float(v) for v in values}
    return {_key(v): float(i) for i, v in enumerate(values)}


def series(rows: Sequence[dict], path: str, others: Sequence[str]) -> list[tuple[str, list[dict]]]:
    """Rows grouped by the values of the other parameters, in first-seen order, with a legend label."""
    groups: dict[str, list[dict]] = {}
    for row in rows:
        label = ", ".join(f"{o}={_short(row[o])}" for o in others)
        groups.setdefault(label, []).append(row)
    return list(groups.items())


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _key(value: Any) -> str:
    return repr(value)


def _short(value: Any, limit: int = 24) -> str:
    text = str(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
