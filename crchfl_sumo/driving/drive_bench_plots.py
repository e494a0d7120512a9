"""The benchmark's figure: one map a town and task, each episode's planned route and the path driven."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from crchfl_sumo.core.figures import pyplot, save_figure
from crchfl_sumo.sumo.maps import draw_network

SUCCESS_COLOR = "tab:green"
FAILURE_COLOR = "tab:red"
ROUTE_COLOR = "tab:blue"


def plot_benchmark(
    records: Sequence[Mapping], net_paths: Mapping[str, Path], tasks: Sequence[str], out_path: Path, title: str = ""
) -> Path:
    """Rows: towns, columns: tasks. Planned routes wide and pale, paths driven green (success) or red,
    a circle at each start and a cross where each drive ended."""
    plt = pyplot()
    towns = list(net_paths)
    fig, axes = plt.subplots(len(towns), len(tasks), figsize=(4.2 * len(tasks), 4.0 * len(towns)), squeeze=False)
    for row, town in enumerate(towns):
        for col, task in enumerate(tasks):
            ax = axes[row][col]
            draw_network(ax, net_paths[town], color="0.8", linewidth=0.8)
            episodes = [r for r in records if r["town"] == town and r["task"] == task]
            for r in episodes:
                route = np.asarray(r["route_xy"])
                path = np.asarray(r["path_xy"])
                color = SUCCESS_COLOR if r["success"] else FAILURE_COLOR
                ax.plot(route[:, 0], route[:, 1], color=ROUTE_COLOR, alpha=0.25, linewidth=4, zorder=2)
                ax.plot(path[:, 0], path[:, 1], color=color, linewidth=1.3, zorder=3)
                ax.plot(*path[0], "o", color=color, markersize=4, zorder=4)
                ax.plot(*path[-1], "x", color=color, markersize=6, zorder=4)
            successes = sum(bool(r["success"]) for r in episodes)
            ax.set_title(f"{town} {task}: {successes}/{len(episodes)} succeeded", fontsize=9)
            ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title)
    return save_figure(fig, out_path)
