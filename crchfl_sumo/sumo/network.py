"""A SUMO network file read: its bounds and its lanes' centre lines."""

from __future__ import annotations

import functools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crchfl_sumo.core.errors import CrchflError


@dataclass(frozen=True)
class Bounds:
    xmin_m: float
    ymin_m: float
    xmax_m: float
    ymax_m: float

    def contains(self, x_m: float, y_m: float, margin_m: float = 0.0) -> bool:
        return (
            self.xmin_m - margin_m <= x_m <= self.xmax_m + margin_m
            and self.ymin_m - margin_m <= y_m <= self.ymax_m + margin_m
        )



def read_net_bounds(net_path: Path) -> Bounds:
    """The network's convBoundary, read without parsing the whole file (plain or gzipped, as sumo reads it)."""
    import sumolib

    if not net_path.is_file():
        raise CrchflError(f"{net_path}: network file not found; check <net-file> in the configuration")
    try:
        with sumolib.openz(str(net_path), "rb") as source:
            for location in sumolib.xml.parse(source, "location"):  # the first one: the rest is not read
                bounds = location.getAttributeSecure("convBoundary", "")
                xmin, ymin, xmax, ymax = (float(v) for v in bounds.split(","))
                return Bounds(xmin, ymin, xmax, ymax)
    except (ET.ParseError, ValueError, OSError, EOFError) as exc:
        raise CrchflError(f"{net_path}: malformed SUMO network ({exc}); rebuild it with netconvert") from None
    raise CrchflError(f"{net_path}: no <location> element: not a SUMO network; rebuild it with netconvert")


@functools.lru_cache(maxsize=4)
def lane_polylines(net_path: Path) -> tuple[np.ndarray, ...]:
    """Every non-internal lane's centre line as an [N, 2] array (the network is read once)."""
    import sumolib

    try:
        net = sumolib.net.readNet(str(net_path))
    except Exception as exc:  # sumolib raises assorted errors on bad input
        raise CrchflError(f"{net_path}: could not read the network ({exc}); rebuild it with netconvert") from None
    return tuple(
        np.asarray(lane.getShape(), dtype=np.float64) for edge in net.getEdges() for lane in edge.getLanes()
    )


def lane_points(net_path: Path, spacing_m: float = 10.0) -> np.ndarray:
    """Points every ``spacing_m`` along every non-internal lane of the network, [P, 2]."""
    points = []
    for shape in lane_polylines(Path(net_path)):
        for a, b in zip(shape[:-1], shape[1:]):
            n = max(1, int(math.ceil(np.hypot(*(b - a)) / spacing_m)))
            t = np.arange(n)[:, None] / n
            points.append(a + t * (b - a))
        points.append(shape[-1:])
    return np.concatenate(points) if points else np.zeros((0, 2))
