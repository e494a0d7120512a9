"""A Scenario: a SUMO configuration made safe to run headless, plus edge sites and towns.

Every command takes either a built-in scenario name (a folder under
``scenarios/`` holding ``scenario.toml``) or a path to any
``.sumocfg``, whose options sumo/sumocfg.py reads and sanitises.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crchfl_sumo.core.config import from_mapping, read_toml
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.core.resources import builtin_names, scenarios_dir
from crchfl_sumo.sumo.injection import InjectConfig
from crchfl_sumo.sumo.network import Bounds, lane_points, read_net_bounds
from crchfl_sumo.sumo.sites import (
    MAX_COORDINATE_M,
    MAX_SITES,
    SITE_PLACEMENTS,
    EdgeSite,
    place_edge_site_count,
    place_edge_sites,
)
from crchfl_sumo.sumo.sumocfg import _option_value, resolved_path, sumo_options_from_config, sumo_time_s

log = logging.getLogger(__name__)


# A town's box spans its junction centres; lanes and their vehicles lie up to a
# lane width or two beside the outermost ones.
TOWN_MARGIN_M = 10.0


@dataclass(frozen=True)
class Town:
    """A named region of the network (the paper's Town01/Town02) and its named vehicles."""

    name: str
    xmin_m: float
    ymin_m: float
    xmax_m: float
    ymax_m: float
    data_vehicles: tuple[str, ...] = ()
    test_vehicles: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for key in ("xmin_m", "ymin_m", "xmax_m", "ymax_m"):  # a box in the network's frame, as edge sites are
            check_range(getattr(self, key), f"towns.{self.name}.{key}", -MAX_COORDINATE_M, MAX_COORDINATE_M,
                        "metres in the network's frame")
        if not (self.xmin_m <= self.xmax_m and self.ymin_m <= self.ymax_m):
            raise CrchflError(f"towns.{self.name}: its box has xmin_m > xmax_m or ymin_m > ymax_m; swap them")

    def contains(self, x_m: np.ndarray, y_m: np.ndarray, margin_m: float = TOWN_MARGIN_M) -> np.ndarray:
        """Whether positions lie in the town: its box (junction centres) widened by ``margin_m``."""
        x_m, y_m = np.asarray(x_m), np.asarray(y_m)
        return (
            (x_m >= self.xmin_m - margin_m)
            & (x_m <= self.xmax_m + margin_m)
            & (y_m >= self.ymin_m - margin_m)
            & (y_m <= self.ymax_m + margin_m)
        )


@dataclass(frozen=True)
class ScenarioFile:
    """The schema of a built-in scenario's ``scenario.toml``."""

    sumocfg: str
    description: str = ""
    edge_sites: tuple[EdgeSite, ...] = ()
    towns: tuple[Town, ...] = ()



@dataclass(frozen=True)
class Scenario:
    """What a simulation needs: sumo options, the network, edge sites and towns."""

    name: str
    sumocfg_path: Path
    net_path: Path
    step_length_s: float
    sumo_options: tuple[str, ...]
    bounds: Bounds
    edge_sites: tuple[EdgeSite, ...]
    towns: tuple[Town, ...]
    description: str = ""
    dropped_options: tuple[str, ...] = field(default=(), compare=False)
    length_s: float | None = None  # the configuration's <end> less its <begin>; None: it sets no end
    demand_scale: float = 1.0  # SumoConfig.scale: applied by sim.Simulation
    speed_limit_mps: float = math.inf  # SumoConfig.speed_limit_mps: applied by sim.Simulation
    # the towns' vehicles that sim.Simulation adds itself (a scenario that names none: sumo/injection.py)
    injected: tuple[str, ...] = ()
    inject_seed: int = 0

    def town_of(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Town name per position ('' outside every town)."""
        names = np.full(np.shape(x_m), "", dtype=object)
        for town in self.towns:
            names[town.contains(x_m, y_m) & (names == "")] = town.name
        return names.astype(str)


DEFAULT_COVERAGE_RADIUS_M = 250.0  # what automatic site placement covers when no run config says otherwise
MAX_DEMAND_SCALE = 100.0  # SUMO inserts this many times the scenario's vehicles at most
MAX_SPEED_MPS = 200.0  # 720 km/h: no road vehicle's; a cap above it caps nothing (inf says so)
# A SUMO step longer than this is no traffic simulation a vehicle's link or camera can follow.
MAX_STEP_LENGTH_S = 60.0


@dataclass(frozen=True)
class SumoConfig:
    """How a run's SUMO differs from its scenario's own (TOML ``[sumo]``): the mobility study's knobs.

    scale: traffic density: SUMO's demand scale of the background traffic
        (0.5 = half the vehicles, 2 = twice as many). Every vehicle type known
        when SUMO starts is scaled except the types of the federated and the
        scenario's named vehicles, so those always drive.
    speed_limit_mps: a cap on every lane's speed limit and on every vehicle's
        top speed [m/s] (inf = the network's own limits).
    edge_sites: explicit edge servers replacing the scenario's.
    edge_site_count: this many edge servers placed by k-means over the
        network's lanes instead of the scenario's (0 = the scenario's).
        A run with other sites than the data set's maps each vehicle to the
        site nearest its first recorded sample (run.read_inputs).
    site_placement: how a scenario without sites (a plain .sumocfg) gets them:
        "hex" (default: TR 38.901's hexagonal layout, city scale) or "kmeans"
        (fewest sites, small networks); sites.place_edge_sites.
    inter_site_distance_m: the hexagonal layout's spacing (0 = sqrt(3) x the
        coverage radius, the largest that covers every road point).
    data_vehicles, test_vehicles, inject_seed: what a scenario that names no
        vehicle gets (a plain .sumocfg): this many data and test vehicles a
        town, on random trips of this seed (sumo/injection.py).
    """

    scale: float = 1.0
    speed_limit_mps: float = math.inf
    edge_sites: tuple[EdgeSite, ...] = ()
    edge_site_count: int = 0
    site_placement: str = "hex"
    inter_site_distance_m: float = 0.0
    data_vehicles: int = InjectConfig.data_vehicles
    test_vehicles: int = InjectConfig.test_vehicles
    inject_seed: int = InjectConfig.seed

    def __post_init__(self) -> None:
        self.inject  # checked here: a bad count is named before anything runs
        if not (math.isfinite(self.scale) and 0 < self.scale <= MAX_DEMAND_SCALE):
            raise CrchflError(
                f"sumo.scale: {self.scale} must be a number in (0, {MAX_DEMAND_SCALE:g}] (1 = the scenario's traffic)"
            )
        check_range(self.speed_limit_mps, "sumo.speed_limit_mps", 0, MAX_SPEED_MPS, "m/s (or inf: no cap)",
                    lo_open=True, inf_ok=True)
        check_range(self.edge_site_count, "sumo.edge_site_count", 0, MAX_SITES,
                    "a number of sites (0 = the scenario's)")
        if self.edge_sites and self.edge_site_count:
            raise CrchflError("sumo: give either edge_sites or edge_site_count, not both")
        if self.site_placement not in SITE_PLACEMENTS:
            raise CrchflError(
                f"sumo.site_placement: {self.site_placement!r} is unknown; use one of {', '.join(SITE_PLACEMENTS)}"
            )
        check_range(self.inter_site_distance_m, "sumo.inter_site_distance_m", 0, 1e5,
                    "metres (0 = from the coverage radius)")
        names = [site.name for site in self.edge_sites]
        if len(set(names)) != len(names):
            raise CrchflError(f"sumo.edge_sites: site names must be distinct, got {names}")

    @property
    def inject(self) -> InjectConfig:
        return InjectConfig(self.data_vehicles, self.test_vehicles, self.inject_seed)

    @property
    def replaces_sites(self) -> bool:
        return bool(self.edge_sites) or self.edge_site_count > 0


def configured_scenario(name_or_path: str | Path, sumo: SumoConfig, coverage_radius_m: float) -> Scenario:
    """The scenario as ``sumo`` changes it: its edge sites, traffic density and speed cap."""
    scenario = load_scenario(name_or_path, sumo.edge_sites or None, coverage_radius_m, sumo.site_placement,
                             sumo.inter_site_distance_m or None, sumo.inject)
    if sumo.edge_site_count:
        sites = place_edge_site_count(lane_points(scenario.net_path), sumo.edge_site_count)
        scenario = dataclasses.replace(scenario, edge_sites=sites)
    return dataclasses.replace(scenario, demand_scale=sumo.scale, speed_limit_mps=sumo.speed_limit_mps)


def load_scenario(
    name_or_path: str | Path,
    edge_sites: tuple[EdgeSite, ...] | None = None,
    coverage_radius_m: float = DEFAULT_COVERAGE_RADIUS_M,
    site_placement: str = "hex",
    inter_site_distance_m: float | None = None,
    inject: InjectConfig = InjectConfig(),
) -> Scenario:
    """Resolve a built-in name, a folder laid out as a built-in one, or a .sumocfg path into a runnable Scenario.

    Such a folder holds a scenario.toml (its towns, named vehicles and edge
    sites, as scenarios/*/scenario.toml) beside the SUMO files it names; its
    name is the folder's.

    ``edge_sites`` (from an experiment config) override the scenario's own; a
    user's .sumocfg without sites gets them placed automatically so that every
    road point lies within ``coverage_radius_m`` of a site (sites.place_edge_sites, by
    ``site_placement``: "hex", TR 38.901's hexagonal layout of ``inter_site_distance_m``
    (default sqrt(3) x the radius), or "kmeans").

    A scenario whose towns name no vehicle (a plain .sumocfg) gets ``inject``'s data and test vehicles in
    each town, which the Simulation adds on seeded random trips (sumo/injection.py).
    """
    text = str(name_or_path)
    builtin, own = scenarios_dir() / text / "scenario.toml", Path(text) / "scenario.toml"
    if Path(text).name == text and builtin.is_file():  # a built-in name
        described, name = builtin, text
    elif own.is_file():  # a folder laid out as a built-in one brings its towns and sites
        described, name = own, own.parent.resolve().name
    else:
        described = None
    if described is not None:
        spec = from_mapping(ScenarioFile, read_toml(described), where=str(described))
        cfg_path = resolved_path(described.parent / spec.sumocfg)
        description, towns, sites = spec.description, spec.towns, spec.edge_sites
    elif text.endswith(".sumocfg") or Path(text).is_file():
        cfg_path = resolved_path(Path(text))
        name, description, towns, sites = cfg_path.stem.removesuffix(".sumo"), "", (), ()
    else:
        raise CrchflError(
            f"{text}: not a built-in scenario ({', '.join(builtin_names())}), a .sumocfg file nor a folder "
            "with a scenario.toml; pass one of those names or a path to a SUMO configuration"
        )
    options, dropped = sumo_options_from_config(cfg_path)
    net_path = Path(_option_value(options, "net-file") or "")
    if not net_path.name:
        raise CrchflError(f"{cfg_path}: no <net-file> in the configuration; add one under <input>")
    bounds = read_net_bounds(net_path)
    step = _option_value(options, "step-length")
    step_length_s = sumo_time_s(step, cfg_path, "step-length") if step else 1.0
    if not 0.0 < step_length_s <= MAX_STEP_LENGTH_S:
        raise CrchflError(
            f"{cfg_path}: <step-length> {step!r} must lie in (0, {MAX_STEP_LENGTH_S:g}] s; give the simulation "
            "step in seconds (the towns use 0.25)"
        )
    end = _option_value(options, "end")
    length_s = None if end is None else sumo_time_s(end, cfg_path, "end") - sumo_time_s(
        _option_value(options, "begin") or "0", cfg_path, "begin"
    )
    if length_s is not None and length_s <= 0:
        raise CrchflError(f"{cfg_path}: <end> is not after <begin>; set a later end or remove it")
    if edge_sites is not None:
        sites = tuple(edge_sites)
    for site in sites:  # given by hand; a placed site may stand beyond the network's edge
        if not bounds.contains(site.x_m, site.y_m):
            raise CrchflError(
                f"edge site '{site.name}' at ({site.x_m:.1f}, {site.y_m:.1f}) m is off the map "
                f"{net_path.name} (x {bounds.xmin_m:.1f}..{bounds.xmax_m:.1f}, "
                f"y {bounds.ymin_m:.1f}..{bounds.ymax_m:.1f}); move it inside"
            )
    if not sites:
        sites = place_edge_sites(lane_points(net_path), coverage_radius_m, method=site_placement,
                                 inter_site_distance_m=inter_site_distance_m)
        log.info("placed %d edge sites automatically over %s", len(sites), net_path.name)
    if not towns:
        towns = (Town(name, bounds.xmin_m, bounds.ymin_m, bounds.xmax_m, bounds.ymax_m),)
    injected: tuple[str, ...] = ()
    if not any(town.data_vehicles or town.test_vehicles for town in towns):  # names none: they are added
        named = []
        for town in towns:
            data, test = inject.names(town.name)
            named.append(dataclasses.replace(town, data_vehicles=data, test_vehicles=test))
        towns = tuple(named)
        injected = tuple(v for town in towns for v in (*town.data_vehicles, *town.test_vehicles))
    return Scenario(
        name=name,
        sumocfg_path=cfg_path,
        net_path=net_path,
        step_length_s=step_length_s,
        sumo_options=tuple(options),
        bounds=bounds,
        edge_sites=tuple(sites),
        towns=tuple(towns),
        description=description,
        dropped_options=tuple(dropped),
        length_s=length_s,
        injected=injected,
        inject_seed=inject.seed,
    )


def study_scenario(name_or_path: str) -> tuple[Scenario, str]:
    """The scenario a study moves to (`reproduce --scenario S`, `mobility-study --scenario S`) and the name its
    runs take: a path made absolute, so that every run (and a Ray task) finds it. One whose towns name no
    data or no test vehicles is refused (a plain .sumocfg gets them added)."""
    scenario = load_scenario(name_or_path)
    if Path(name_or_path).exists():
        name_or_path = str(Path(name_or_path).resolve())
    if not all(any(getattr(t, kind) for t in scenario.towns) for kind in ("data_vehicles", "test_vehicles")):
        raise CrchflError(f"--scenario {name_or_path}: its towns name no data or no test vehicles; name them in a "
                          "scenario.toml, or let it have some added ([sumo] data_vehicles, docs/scenarios.md)")
    return scenario, str(name_or_path)
