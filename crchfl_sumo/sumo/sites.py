"""Edge servers (road-side units) placed in the network frame, by hand or automatically.

A site is plain data: where the antenna stands. Which vehicles it serves is
links/mobility.py's business, what rate it gives is links/channel.py's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crchfl_sumo.core.errors import CrchflError


MAX_COORDINATE_M = 1e7  # SUMO networks are in local metres; even UTM northings stay below this
MAX_HEIGHT_M = 1000.0  # above the tallest masts
MAX_SITES = 1000  # edge sites of one network: the planner's topology bound; k-means of more takes minutes a run


@dataclass(frozen=True)
class EdgeSite:
    """One edge server's antenna: name, position [m] in the network frame, height [m]."""

    name: str
    x_m: float
    y_m: float
    height_m: float = 10.0

    def __post_init__(self) -> None:
        if not self.name:
            raise CrchflError("edge_sites: every site needs a non-empty 'name'")
        for key in ("x_m", "y_m"):
            if not abs(_as_float(getattr(self, key))) <= MAX_COORDINATE_M:  # NaN fails too
                raise CrchflError(
                    f"edge_sites.{self.name}.{key}: {getattr(self, key)!r} is not a position in a road network's "
                    f"frame; give metres within +-{MAX_COORDINATE_M:g} (the network's own coordinates)"
                )
        if not 0 < _as_float(self.height_m) <= MAX_HEIGHT_M:
            raise CrchflError(
                f"edge_sites.{self.name}.height_m must be > 0 and at most {MAX_HEIGHT_M:g} m, got {self.height_m!r}"
            )


def _as_float(value) -> float:
    """``value`` as a float; NaN when it is not a number (every range check then fails)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def place_edge_sites(
    road_points_m: np.ndarray, coverage_radius_m: float, max_sites: int = 64, iterations: int = 30
) -> tuple[EdgeSite, ...]:
    """Fewest sites (k-means, k = 1, 2, ...) that put every road point within ``coverage_radius_m``.

    Deterministic: centres start from a farthest-point traversal that begins at
    the road point nearest the centroid, then Lloyd iterations refine them; k
    grows until the farthest road point is covered. Sites are named edge00, edge01...
    """
    points = np.asarray(road_points_m, dtype=np.float64).reshape(-1, 2)
    if len(points) == 0:
        raise CrchflError("cannot place edge sites: the network has no lanes")
    if coverage_radius_m <= 0:
        raise CrchflError(f"mobility.coverage_radius_m must be > 0, got {coverage_radius_m}")
    for k in range(1, max_sites + 1):
        centres = _kmeans(points, _farthest_point_init(points, k), iterations)
        if _distance_to_nearest(points, centres).max() <= coverage_radius_m:
            break
    else:
        raise CrchflError(
            f"{max_sites} edge sites of radius {coverage_radius_m} m cannot cover the network; "
            "raise mobility.coverage_radius_m or give edge_sites explicitly"
        )
    return tuple(EdgeSite(f"edge{i:02d}", float(x), float(y)) for i, (x, y) in enumerate(centres))


def place_edge_site_count(road_points_m: np.ndarray, count: int, iterations: int = 30) -> tuple[EdgeSite, ...]:
    """``count`` sites by the same deterministic k-means as ``place_edge_sites``, named edge00, edge01, ..."""
    points = np.asarray(road_points_m, dtype=np.float64).reshape(-1, 2)
    if count > len(points):
        raise CrchflError(f"sumo.edge_site_count: {count} sites for a network of {len(points)} road points; use fewer")
    centres = _kmeans(points, _farthest_point_init(points, count), iterations)
    return tuple(EdgeSite(f"edge{i:02d}", float(x), float(y)) for i, (x, y) in enumerate(centres))


def _distance_to_nearest(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    return np.sqrt(((points[:, None, :] - centres[None, :, :]) ** 2).sum(-1)).min(axis=1)


def _farthest_point_init(points: np.ndarray, k: int) -> np.ndarray:
    first = np.argmin(((points - points.mean(axis=0)) ** 2).sum(-1))
    centres = [points[first]]
    for _ in range(1, k):
        centres.append(points[np.argmax(_distance_to_nearest(points, np.array(centres)))])
    return np.array(centres)


def _kmeans(points: np.ndarray, centres: np.ndarray, iterations: int) -> np.ndarray:
    # Lloyd's iterations by hand rather than scipy's kmeans2: these ten lines keep an empty
    # cluster's centre where the farthest-point start put it and stop at a fixed point, so
    # placement is reproducible without a seed and the same on every scipy version.
    for _ in range(iterations):
        nearest = np.sqrt(((points[:, None, :] - centres[None, :, :]) ** 2).sum(-1)).argmin(axis=1)
        updated = np.array(
            [points[nearest == i].mean(axis=0) if np.any(nearest == i) else centres[i] for i in range(len(centres))]
        )
        if np.allclose(updated, centres):
            break
        centres = updated
    return centres
