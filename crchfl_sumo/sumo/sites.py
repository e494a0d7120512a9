"""Edge servers (road-side units) placed in the network frame, by hand or automatically.

A site is plain data: where the antenna stands. Which vehicles it serves is
links/mobility.py's business, what rate it gives is links/channel.py's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

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


# How sites are placed automatically: a hexagonal layout (city scale, the default) or k-means (small networks).
SITE_PLACEMENTS = ("hex", "kmeans")


def hex_lattice(bounds_m: tuple[float, float, float, float], spacing_m: float) -> np.ndarray:
    """[N, 2] points of a hexagonal lattice (neighbours ``spacing_m`` apart) centred on the bounds
    (xmin, ymin, xmax, ymax), row by row: every point of the bounds lies within spacing / sqrt(3)
    of one of them (the circumradius of a hexagonal cell)."""
    xmin, ymin, xmax, ymax = bounds_m
    if not (xmax >= xmin and ymax >= ymin and spacing_m > 0):
        raise CrchflError(f"hexagonal layout: bad bounds {bounds_m} or spacing {spacing_m}")
    cx, cy = (xmin + xmax) / 2.0, (ymin + ymax) / 2.0
    row_m = spacing_m * math.sqrt(3.0) / 2.0
    n_rows = math.ceil((ymax - cy) / row_m) + 1
    n_cols = math.ceil((xmax - cx) / spacing_m) + 1
    rows, cols = np.meshgrid(np.arange(-n_rows, n_rows + 1), np.arange(-n_cols, n_cols + 1), indexing="ij")
    x = cx + cols * spacing_m + np.where(rows % 2 != 0, spacing_m / 2.0, 0.0)
    y = cy + rows * row_m
    points = np.stack([x.ravel(), y.ravel()], axis=1)
    # the sites whose cell can touch the bounds
    keep = ((points[:, 0] >= xmin - spacing_m) & (points[:, 0] <= xmax + spacing_m)
            & (points[:, 1] >= ymin - spacing_m) & (points[:, 1] <= ymax + spacing_m))
    return points[keep]


def place_edge_sites(
    road_points_m: np.ndarray,
    coverage_radius_m: float,
    max_sites: int = 64,
    iterations: int = 30,
    method: str = "hex",
    inter_site_distance_m: float | None = None,
) -> tuple[EdgeSite, ...]:
    """Sites that put every road point within ``coverage_radius_m`` of one, named edge00, edge01, ...

    ``method`` "hex" (default): 3GPP TR 38.901's hexagonal layout (Table 7.2-1: sites on a
    hexagonal grid of inter-site distance ISD) with ``inter_site_distance_m`` = sqrt(3) x the
    coverage radius by default (a hexagonal cell's circumradius is ISD / sqrt(3), so every point
    is covered); the sites kept are those nearest to some road point. Thousands of sites in seconds.
    "kmeans": fewest sites (k = 1, 2, ... up to ``max_sites``) by deterministic k-means: centres
    start from a farthest-point traversal that begins at the road point nearest the centroid,
    then Lloyd iterations refine them; k grows until the farthest road point is covered.
    """
    points = np.asarray(road_points_m, dtype=np.float64).reshape(-1, 2)
    if len(points) == 0:
        raise CrchflError("cannot place edge sites: the network has no lanes")
    if coverage_radius_m <= 0:
        raise CrchflError(f"mobility.coverage_radius_m must be > 0, got {coverage_radius_m}")
    if method not in SITE_PLACEMENTS:
        raise CrchflError(f"sumo.site_placement: {method!r} is unknown; use one of {', '.join(SITE_PLACEMENTS)}")
    if method == "hex":
        return _hex_sites(points, coverage_radius_m, inter_site_distance_m)
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


def _hex_sites(points: np.ndarray, coverage_radius_m: float, inter_site_distance_m: float | None) -> tuple[EdgeSite, ...]:
    spacing = math.sqrt(3.0) * coverage_radius_m if inter_site_distance_m is None else float(inter_site_distance_m)
    if not 0 < spacing <= math.sqrt(3.0) * coverage_radius_m * (1 + 1e-9):
        raise CrchflError(
            f"sumo.inter_site_distance_m: {inter_site_distance_m!r} leaves road points uncovered by a "
            f"{coverage_radius_m:g} m radius; give at most sqrt(3) x the radius ({math.sqrt(3.0) * coverage_radius_m:.1f} m)"
        )
    lo, hi = points.min(axis=0), points.max(axis=0)
    lattice = hex_lattice((lo[0], lo[1], hi[0], hi[1]), spacing)
    _, nearest = cKDTree(lattice).query(points)
    kept = lattice[np.unique(nearest)]  # in lattice order: row by row
    width = max(2, len(str(len(kept) - 1)))
    return tuple(EdgeSite(f"edge{i:0{width}d}", float(x), float(y)) for i, (x, y) in enumerate(kept))


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
