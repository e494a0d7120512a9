"""Mobility-aware client selection (``federation.selection``): which members of an edge train in an aggregation.

``all`` (the paper): every member trains and uploads. ``skip_leaving``: a
vehicle sits the aggregation out when the time it is predicted to stay in
the cell its upload needs (links/residence.py, from its pose on the clock
when it would start training) is shorter than what it needs: its local
training (the loop's own compute model) plus the upload of one model at the
rate its link gave it over the last ``RATE_WINDOW_S`` (what a vehicle can
know; the clock's future is not looked at). A skipped vehicle trains
nothing, sends nothing, is no straggler, and still receives the edge's model.

The cell the upload needs: under the ``wait`` and ``miss`` handover policies
the vehicle's own edge (time on another site does not carry the upload, so
a vehicle already elsewhere has none left); under ``new_edge`` and
``forward`` whichever site serves it when it would start.
"""

from __future__ import annotations

import math
from typing import Mapping

from crchfl_sumo.links.clock import Clock
from crchfl_sumo.links.residence import Coverage, residence_time_s
from crchfl_sumo.planning.timing import time_mean_rate_bps

RATE_WINDOW_S = 10.0  # long enough to average out fast fading, short enough to follow the vehicle's cell


def needed_s(train_s: float, model_bytes: int, rate_bps: float) -> float:
    """Local training plus one model upload at ``rate_bps`` (inf at no rate)."""
    return train_s + (8.0 * model_bytes / rate_bps if rate_bps > 0.0 else math.inf)


def leaving(residence_s: float, needed_s: float) -> bool:
    """The vehicle leaves its cell before its training and upload end."""
    return residence_s < needed_s


def chosen(needed: Mapping[str, float], residence: Mapping[str, float]) -> tuple[str, ...]:
    """The vehicles (in ``needed``'s order) that stay long enough to train and upload."""
    return tuple(v for v in needed if not leaving(residence[v], needed[v]))


def residence_on_clock(
    clock: Clock, vehicle: str, t_s: float, coverage: Coverage | None, own_site: int | None
) -> float:
    """``vehicle``'s predicted time left at ``t_s`` in its serving cell (``own_site``: only that one counts).

    0 where no site serves it (or another than ``own_site``); inf where the
    clock has no pose (no mobility) or there is no coverage to leave.
    """
    site = int(clock.series(vehicle, "edge", t_s, t_s).site[0])  # the sample at or before t_s
    if site < 0 or (own_site is not None and site != own_site):
        return 0.0
    pose = clock.pose(vehicle, t_s)
    if pose is None or coverage is None:
        return math.inf
    return residence_time_s(pose, site, coverage)


def recent_rate_bps(clock: Clock, vehicle: str, t_s: float) -> float:
    """Time-mean edge rate of ``vehicle`` over the ``RATE_WINDOW_S`` before ``t_s`` (from the clock's start)."""
    from_s = max(clock.start_s, t_s - RATE_WINDOW_S)
    series = clock.series(vehicle, "edge", from_s, t_s)
    if not t_s > from_s:
        return float(series.rate_bps[0])
    return time_mean_rate_bps(series, from_s, t_s)
