"""Data and test vehicles for a scenario that names none: added through TraCI on seeded random trips.

A plain .sumocfg (or a network with route files) names no vehicle that stays in
the simulation for a whole run, yet a data set, a federated run and a study
need such vehicles. For such a scenario, sumo/scenario.py names
``InjectConfig.data_vehicles`` data and ``test_vehicles`` test vehicles per town
(``TOWN_data_I``, ``TOWN_test_I``), and the Simulation adds them when it
starts (``Injector``):

- trips run within the largest set of edges that passenger cars may use and
  that all reach one another (the edge graph's largest strongly connected
  component, scipy.sparse.csgraph): from any of them there is always a way on;
- each departs at once on a start edge drawn from that set (distinct edges, so
  none waits for another), towards a destination drawn from it;
- on its last edge it is sent on to a new destination (``changeTarget``), so it
  drives for the whole run;
- the draws depend on ``InjectConfig.seed`` and the vehicle alone, never on
  SUMO's seed: the same vehicles take the same trips in a data set and in the
  runs on it (what differs is SUMO's traffic around them).

The scenario's own demand stays as it is: the background traffic.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range

# A copy of SUMO's own passenger car (known in every simulation) under a name of its own, so that a demand
# scale of the background (SumoConfig.scale) leaves these vehicles alone.
INJECTED_TYPE = "crchfl_injected"
MIN_EDGE_M = 20.0  # shorter edges (junction stubs, connectors) are neither starts nor destinations
MIN_TRIP_EDGES = 3  # a destination this many edges away at least, so that a trip passes junctions
DRAWS = 50  # destinations tried before a vehicle is declared stuck
MAX_INJECTED = 1000


@dataclass(frozen=True)
class InjectConfig:
    """How many vehicles a scenario that names none gets per town, and the seed of their trips
    (TOML ``[sumo] data_vehicles``, ``test_vehicles``, ``inject_seed``)."""

    data_vehicles: int = 5  # the paper's: 2 in Town01, 3 in Town02
    test_vehicles: int = 1
    seed: int = 0

    def __post_init__(self) -> None:
        check_range(self.data_vehicles, "sumo.data_vehicles", 0, MAX_INJECTED, "vehicles a town")
        check_range(self.test_vehicles, "sumo.test_vehicles", 0, MAX_INJECTED, "vehicles a town")
        check_range(self.seed, "sumo.inject_seed", 0, 2**31 - 1, "a seed")

    def names(self, town: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """The data and the test vehicles of ``town``."""
        return (tuple(f"{town}_data_{i}" for i in range(self.data_vehicles)),
                tuple(f"{town}_test_{i}" for i in range(self.test_vehicles)))


class Injector:
    """Adds the injected vehicles to a running simulation and keeps them driving (see the module doc)."""

    def __init__(self, api, vehicles: tuple[str, ...], seed: int) -> None:
        self._api = api
        self._vehicles = vehicles
        # one generator a vehicle: its trips do not depend on when the others arrive
        self._rng = {v: np.random.default_rng([seed, i]) for i, v in enumerate(vehicles)}
        self._starts = np.random.default_rng([seed, len(vehicles)])
        self._edges = _looping_edges(api)
        if len(self._edges) < MIN_TRIP_EDGES:
            raise CrchflError(
                f"no data vehicle can be added: the network's roads hold no loop of {MIN_TRIP_EDGES} or more edges a "
                "car can keep driving on (one-way corridors end); name vehicles that stay in a scenario.toml "
                "(docs/scenarios.md)"
            )

    def insert(self) -> None:
        """Add every vehicle now, each on its own start edge (as many as the network has), towards a destination."""
        api = self._api
        if INJECTED_TYPE not in api.vehicletype.getIDList():
            api.vehicletype.copy("DEFAULT_VEHTYPE", INJECTED_TYPE)
        starts = self._starts.permutation(len(self._edges))
        for i, vehicle in enumerate(self._vehicles):
            start = self._edges[int(starts[i % len(starts)])]
            route = self._trip_from(vehicle, start)
            api.route.add(f"{vehicle}__trip", route)
            api.vehicle.add(vehicle, f"{vehicle}__trip", typeID=INJECTED_TYPE, depart="now", departPos="base",
                            departSpeed="0", departLane="best")

    def keep_driving(self, present: Collection[str]) -> None:
        """Send every injected vehicle in ``present`` (the vehicles in the network) that is on its route's last
        edge on to a new destination."""
        api = self._api
        for vehicle in self._vehicles:
            if vehicle not in present:
                continue
            try:
                route, index = api.vehicle.getRoute(vehicle), api.vehicle.getRouteIndex(vehicle)
            except api.TraCIException:  # being teleported: not on a lane this step
                continue
            if index >= len(route) - 1:
                api.vehicle.setRoute(vehicle, self._trip_from(vehicle, route[-1]))

    def _trip_from(self, vehicle: str, start: str) -> list[str]:
        """A route from ``start`` to a destination drawn for ``vehicle`` that it reaches."""
        rng = self._rng[vehicle]
        for _ in range(DRAWS):
            destination = self._edges[int(rng.integers(len(self._edges)))]
            if destination == start:
                continue
            edges = list(self._api.simulation.findRoute(start, destination, vType="DEFAULT_VEHTYPE").edges)
            if len(edges) >= MIN_TRIP_EDGES:
                return edges
        raise CrchflError(
            f"vehicle '{vehicle}': no destination reachable from edge '{start}' in {DRAWS} draws; the network's "
            "roads are not connected enough for added data vehicles: name them in a scenario.toml (docs/scenarios.md)"
        )


def _looping_edges(api) -> list[str]:
    """The largest strongly connected set of the network's normal edges that passenger cars may use (each reaches
    every other), less those too short to start on; sorted."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = []
    for edge in sorted(api.edge.getIDList()):
        if edge.startswith(":"):
            continue
        lanes = [f"{edge}_{i}" for i in range(api.edge.getLaneNumber(edge))]
        if any(not api.lane.getAllowed(lane) or "passenger" in api.lane.getAllowed(lane) for lane in lanes):
            edges.append(edge)
    index = {edge: i for i, edge in enumerate(edges)}
    pairs = {
        (index[edge], index[link[0].rsplit("_", 1)[0]])
        for edge in edges
        for lane in range(api.edge.getLaneNumber(edge))
        for link in api.lane.getLinks(f"{edge}_{lane}")
        if link[0].rsplit("_", 1)[0] in index
    }
    if not pairs:
        return []
    rows, cols = zip(*sorted(pairs))
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(edges), len(edges)))
    _, labels = connected_components(graph, directed=True, connection="strong")
    largest = np.bincount(labels).argmax()
    return [edge for i, edge in enumerate(edges)
            if labels[i] == largest and api.lane.getLength(f"{edge}_0") >= MIN_EDGE_M]
