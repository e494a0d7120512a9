"""Drawing a SUMO network with matplotlib: the base layer of every map plot."""

from __future__ import annotations

from pathlib import Path

from crchfl_sumo.sumo.network import lane_polylines


def draw_network(ax, net_path: Path, color: str = "0.75", linewidth: float = 1.0) -> None:
    """Draw the network's lanes on ``ax`` in metres, equal aspect."""
    from matplotlib.collections import LineCollection

    ax.add_collection(LineCollection(lane_polylines(Path(net_path)), colors=color, linewidths=linewidth, zorder=1))
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
