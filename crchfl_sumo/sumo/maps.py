"""Drawing a SUMO network with matplotlib: the base layer of every map plot."""

from __future__ import annotations

from pathlib import Path

from crchfl_sumo.core.atomic import atomic_path
from crchfl_sumo.sumo.scenario import lane_polylines


def draw_network(ax, net_path: Path, color: str = "0.75", linewidth: float = 1.0) -> None:
    """Draw the network's lanes on ``ax`` in metres, equal aspect."""
    from matplotlib.collections import LineCollection

    ax.add_collection(LineCollection(lane_polylines(Path(net_path)), colors=color, linewidths=linewidth, zorder=1))
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def save_figure(fig, path: Path) -> None:
    """Save a figure atomically (temporary file, then rename) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
