"""How long a vehicle will stay in its cell: straight-line extrapolation of its track to the cell's border.

The model (pure; docs/beyond_paper.md, "Mobility-aware client selection"):
the vehicle keeps its speed and heading, ``p(t) = p0 + speed t (cos h, sin h)``;
its serving site ``s`` stops serving it at the first of

* leaving the site's range: ``|p(t) - s| = coverage_radius_m`` (the larger
  root: association drops a vehicle out of range at once), and
* another site ``j`` becoming the nearer one: ``p(t)`` crosses the
  perpendicular bisector of ``s`` and ``j``, plus ``time_to_trigger_s``
  (the A3 event must hold that long). A point on the bisector inside
  ``s``'s range is inside ``j``'s too, so ``j`` can take over there.

Nearer stands for stronger: with equal masts and one path-loss law the
strongest large-scale power is the nearest site's. Limits: roads bend and
vehicles turn, brake and stop at lights (a standing vehicle is predicted
to stay for ever); shadowing, the LOS state, ``handover_margin_db`` and
``min_rx_power_dbm`` are left out, so a site-to-site handover is
predicted earlier than the margin lets it happen, and a coverage hole
inside the radius is not seen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from crchfl_sumo.links.mobility import NO_SITE

_STANDING_MPS = 1e-6  # slower than this counts as standing: the extrapolation never leaves


@dataclass(frozen=True)
class Pose:
    """Where a vehicle is and how it moves: position [m] in the network frame, speed, heading
    (radians, 0 = east, counter-clockwise: sumo/frame.py's convention)."""

    x_m: float
    y_m: float
    speed_mps: float
    heading_rad: float


@dataclass(frozen=True)
class Coverage:
    """The cells: every site's position [m] (index = site index), their range, the handover's time-to-trigger."""

    sites_xy_m: tuple[tuple[float, float], ...]
    coverage_radius_m: float
    time_to_trigger_s: float = 0.0


def residence_time_s(pose: Pose, site: int, coverage: Coverage) -> float:
    """Seconds until ``site`` stops serving a vehicle at ``pose`` on a straight track (module doc).

    0 if no site serves it (``site`` = -1) or it is already out of range;
    inf if it stands still inside the range.
    """
    if site == NO_SITE:
        return 0.0
    sx, sy = coverage.sites_xy_m[site]
    wx, wy = pose.x_m - sx, pose.y_m - sy  # the vehicle relative to its site
    radius = coverage.coverage_radius_m
    if math.hypot(wx, wy) > radius:
        return 0.0
    if pose.speed_mps < _STANDING_MPS:
        return math.inf
    ux, uy = math.cos(pose.heading_rad), math.sin(pose.heading_rad)
    # |w + v t u|^2 = R^2: v^2 t^2 + 2 v (w.u) t + |w|^2 - R^2 = 0, the root after now
    v = pose.speed_mps
    along = wx * ux + wy * uy
    c = wx * wx + wy * wy - radius * radius
    exit_s = (-along + math.sqrt(max(along * along - c, 0.0))) / v
    leave_s = exit_s
    for j, (jx, jy) in enumerate(coverage.sites_xy_m):
        if j == site:
            continue
        nx, ny = jx - sx, jy - sy
        # nearer to j once 2 p.n > |n|^2 (p relative to s): g(t) = 2 (w + v t u).n - |n|^2 grows at 2 v u.n
        gap = nx * nx + ny * ny - 2.0 * (wx * nx + wy * ny)
        closing = 2.0 * v * (ux * nx + uy * ny)
        if gap <= 0.0:  # already nearer to j: a handover is pending
            cross_s = 0.0
        elif closing > 0.0:
            cross_s = gap / closing
        else:
            continue
        leave_s = min(leave_s, cross_s + coverage.time_to_trigger_s)
    return leave_s


def sites_coverage(sites: Sequence, coverage_radius_m: float, time_to_trigger_s: float) -> Coverage:
    """The Coverage of edge sites (anything with ``x_m`` and ``y_m``: sumo.sites.EdgeSite)."""
    return Coverage(tuple((float(s.x_m), float(s.y_m)) for s in sites), float(coverage_radius_m),
                    float(time_to_trigger_s))
