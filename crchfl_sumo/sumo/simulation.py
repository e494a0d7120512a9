"""The one module that drives SUMO: start, step, read a Frame, stop.

libsumo runs SUMO inside this process (one simulation per process: run parallel
simulations in separate processes). The same code also runs over TraCI (pass
``api=traci``), which the benchmark uses as its comparison.

How state is read, and why (measured, docs/benchmarks.md): simulation-wide
counters and signal states come through subscriptions; vehicle state through
three in-process getters a vehicle (position, angle, speed). In SUMO 1.28
variable subscriptions on every vehicle cost SUMO time that grows faster than
the number of vehicles, and a network-wide context subscription costs several
times what three libsumo getters do; SUMO's own FCD output costs SUMO more than
the getters (writing it), before any reading. Lane and signal ahead need
a route walk inside SUMO, so they are read only for the vehicles a caller watches,
and signal states only when the caller asks for them (``signals``).

Most callers need only a few vehicles and their surroundings (the federated
vehicles for the link models, the sampled ones and what their cameras see).
With ``focus`` the frame holds only those vehicles and, through one context
subscription each (a circle of ``around_m`` that SUMO evaluates in C++), their
neighbours; the getters then run for tens of vehicles instead of all of them.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.frame import FOE_RANGE_M, Frame, sumo_angle_to_heading_rad
from crchfl_sumo.sumo.injection import Injector
from crchfl_sumo.sumo.installation import sumo_binary
from crchfl_sumo.sumo.scenario import Scenario

log = logging.getLogger(__name__)

_active_libsumo = False  # libsumo holds one simulation per process


@dataclass(frozen=True)
class SimStats:
    """Counters since the start: what makes a run trustworthy (zero teleports, zero collisions)."""

    steps: int
    departed: int
    arrived: int
    teleports: int
    collisions: int


class Simulation:
    """A running SUMO simulation of a Scenario; use as a context manager.

    >>> with Simulation(load_scenario("town01"), seed=1) as sim:
    ...     frame = sim.step()
    """

    def __init__(
        self,
        scenario: Scenario,
        seed: int = 0,
        api: ModuleType | None = None,
        extra_options: tuple[str, ...] = (),
        watch: Collection[str] | None = None,
        keep_demand: Collection[str] = (),
        focus: Collection[str] | None = None,
        around_m: float = 0.0,
        signals: bool = True,
    ) -> None:
        """``watch``: the vehicles whose lane and signal ahead are read each step (None: all).

        ``signals``: read every signal's state into ``Frame.tls_states`` each
        step (False: the frames hold none, and SUMO keeps no subscription for them).

        ``focus``: None, the frame holds every vehicle; otherwise only these
        vehicles and every vehicle within ``around_m`` of one of them (distance
        between SUMO's front-bumper positions; 0: the focus vehicles alone).

        ``keep_demand``: vehicles whose types the scenario's ``demand_scale``
        leaves alone (the scenario's named vehicles are always kept).
        """
        self.scenario = scenario
        self._keep_demand = tuple(keep_demand)
        self._watch = None if watch is None else frozenset(watch)
        if not (math.isfinite(around_m) and around_m >= 0):
            raise ValueError(f"Simulation: around_m must be a finite distance >= 0, got {around_m}")
        self._focus = None if focus is None else frozenset(focus)
        self._around_m = float(around_m)
        self.seed = int(seed)
        self._api = api
        self._extra_options = tuple(extra_options)
        self._uses_libsumo = api is None
        self._static: dict[str, tuple[float, float, float, float]] = {}
        self._tls_ids: tuple[str, ...] = ()
        self._signals = bool(signals)
        self._steps = self._departed = self._arrived = self._teleports = self._collisions = 0
        self._running = False
        # The previous step's sorted ids with their speeds and static values, so a step
        # only looks up what changed (vectorised merge instead of dict lookups a vehicle).
        self._previous_ids = np.zeros(0, dtype=str)
        self._previous_speed = np.zeros(0)
        self._previous_static = np.zeros((0, 4))
        self._step_s = scenario.step_length_s
        self._injector: Injector | None = None
        self.injection_error: str | None = None  # why the scenario's added vehicles could not be added

    # --- lifecycle --------------------------------------------------------------------------

    def command(self) -> list[str]:
        """The sumo command line this simulation runs (also usable with the plain binary).

        Options set here (the seed above all) replace the same options from the
        scenario's configuration: sumo refuses an option given twice.
        """
        ours = [f"--seed={self.seed}", "--no-step-log=true", "--duration-log.disable=true", *self._extra_options]
        overridden = {option.split("=", 1)[0] for option in ours}
        kept = [o for o in self.scenario.sumo_options if o.split("=", 1)[0] not in overridden]
        return [sumo_binary(), *kept, *ours]

    def __enter__(self) -> "Simulation":
        global _active_libsumo
        if self._uses_libsumo:
            if _active_libsumo:
                raise CrchflError(
                    "a libsumo simulation is already running in this process; "
                    "close it first or run the second one in another process"
                )
            import libsumo

            self._api = libsumo
        api = self._api
        try:
            api.start(self.command())
        except Exception as exc:  # SUMO reports bad input as a generic error
            raise CrchflError(
                f"SUMO could not load scenario '{self.scenario.name}' ({self.scenario.sumocfg_path}): {exc}"
            ) from None
        if self._uses_libsumo:
            _active_libsumo = True
        self._running = True
        tc = api.constants
        api.simulation.subscribe(
            [
                tc.VAR_DEPARTED_VEHICLES_IDS,
                tc.VAR_ARRIVED_VEHICLES_IDS,
                tc.VAR_TELEPORT_STARTING_VEHICLES_NUMBER,
                tc.VAR_COLLIDING_VEHICLES_NUMBER,
            ]
        )
        self._tls_ids = tuple(sorted(api.trafficlight.getIDList())) if self._signals else ()
        for tls in self._tls_ids:
            api.trafficlight.subscribe(tls, [tc.TL_RED_YELLOW_GREEN_STATE])
        if self.scenario.injected:  # before the demand scale, which then knows their type and keeps it
            try:
                self._injector = Injector(api, self.scenario.injected, self.scenario.inject_seed)
                self._injector.insert()
            except CrchflError as exc:  # a run that needs them says so (injection_error); one that does not runs on
                self.injection_error = str(exc)
                log.warning("scenario '%s': %s", self.scenario.name, exc)
        if self.scenario.demand_scale != 1.0:
            self._scale_demand(self.scenario.demand_scale)
        if math.isfinite(self.scenario.speed_limit_mps):
            cap = self.scenario.speed_limit_mps
            for lane in api.lane.getIDList():
                api.lane.setMaxSpeed(lane, min(api.lane.getMaxSpeed(lane), cap))
        return self

    def _scale_demand(self, scale: float) -> None:
        """Scale the demand of every vehicle type known now except the kept vehicles' types (SUMO's vType scale)."""
        api = self._api
        named = [v for town in self.scenario.towns for v in (*town.data_vehicles, *town.test_vehicles)]
        kept_types = set()
        for vehicle_id in dict.fromkeys([*self._keep_demand, *named]):
            try:  # vehicles SUMO has loaded (departed or not) answer; later ones are not known yet
                kept_types.add(api.vehicle.getTypeID(vehicle_id))
            except api.TraCIException:
                if vehicle_id in self._keep_demand:
                    raise CrchflError(
                        f"sumo.scale: vehicle '{vehicle_id}' is not loaded when SUMO starts, so its type cannot "
                        "be kept out of the scaling; leave sumo.scale at 1 for this scenario"
                    ) from None
        for type_id in api.vehicletype.getIDList():
            if type_id not in kept_types:
                api.vehicletype.setScale(type_id, api.vehicletype.getScale(type_id) * scale)

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        global _active_libsumo
        if self._running:
            self._api.close()
            self._running = False
            if self._uses_libsumo:
                _active_libsumo = False

    # --- stepping ---------------------------------------------------------------------------

    @property
    def t_s(self) -> float:
        return float(self._api.simulation.getTime())

    def step(self) -> Frame:
        """Advance one simulation step and return the state after it."""
        api = self._api
        tc = api.constants
        if self._injector is not None:
            self._injector.keep_driving(self._static)  # the vehicles in the network: departed, not yet arrived
        api.simulationStep()
        self._steps += 1
        sim = api.simulation.getSubscriptionResults()
        capped = math.isfinite(self.scenario.speed_limit_mps)
        for vehicle_id in sim[tc.VAR_DEPARTED_VEHICLES_IDS]:
            if self._focus is not None and self._around_m > 0 and vehicle_id in self._focus:
                # any variable will do: SUMO then reports the ids within the circle, this step on
                api.vehicle.subscribeContext(vehicle_id, tc.CMD_GET_VEHICLE_VARIABLE, self._around_m, [tc.VAR_SPEED])
            if capped:  # the lanes are capped too; this stops a speed factor > 1 from exceeding the cap
                api.vehicle.setMaxSpeed(vehicle_id, min(api.vehicle.getMaxSpeed(vehicle_id), self.scenario.speed_limit_mps))
            vtype = api.vehicle.getTypeID(vehicle_id)
            self._static[vehicle_id] = (
                api.vehicletype.getLength(vtype),
                api.vehicletype.getWidth(vtype),
                api.vehicletype.getAccel(vtype),
                api.vehicletype.getDecel(vtype),
            )
        for vehicle_id in sim[tc.VAR_ARRIVED_VEHICLES_IDS]:
            self._static.pop(vehicle_id, None)
        self._departed += len(sim[tc.VAR_DEPARTED_VEHICLES_IDS])
        self._arrived += len(sim[tc.VAR_ARRIVED_VEHICLES_IDS])
        self._teleports += sim[tc.VAR_TELEPORT_STARTING_VEHICLES_NUMBER]
        self._collisions += sim[tc.VAR_COLLIDING_VEHICLES_NUMBER]
        return self._read_frame(tc)

    def run(self, duration_s: float):
        """Yield a Frame per step for ``duration_s`` simulated seconds."""
        if duration_s < 0:
            raise CrchflError(f"--duration-s must be >= 0, got {duration_s}")
        steps = int(round(duration_s / self.scenario.step_length_s))
        for _ in range(steps):
            yield self.step()

    def stats(self) -> SimStats:
        return SimStats(self._steps, self._departed, self._arrived, self._teleports, self._collisions)

    def tls_ids(self) -> tuple[str, ...]:
        return self._tls_ids

    # --- a vehicle driven from outside (driving/drive.py) --------------------------------------------

    def vehicle_type_ids(self) -> tuple[str, ...]:
        """The vehicle types this simulation knows."""
        return tuple(self._api.vehicletype.getIDList())

    def add_external_vehicle(self, vehicle_id: str, edges: Sequence[str], type_id: str) -> None:
        """Ask SUMO to insert a vehicle on ``edges`` now, standing, its rear at the first lane's start.

        SUMO inserts it at a later step when the spot is free. Its speed and lane
        change modes are off: from then on ``place_vehicle`` moves it, not SUMO.
        """
        api = self._api
        try:
            api.route.add(f"{vehicle_id}__route", list(edges))
            api.vehicle.add(
                vehicle_id, f"{vehicle_id}__route", typeID=type_id, depart="now", departPos="base", departSpeed="0"
            )
        except Exception as exc:  # libsumo reports bad ids as a generic error
            raise CrchflError(f"SUMO refused vehicle '{vehicle_id}' on edges {list(edges)}: {exc}") from None
        api.vehicle.setSpeedMode(vehicle_id, 0)
        api.vehicle.setLaneChangeMode(vehicle_id, 0)

    def place_vehicle(
        self, vehicle_id: str, x_front_m: float, y_front_m: float, heading_rad: float, speed_mps: float,
        lane_id: str | None = None,
    ) -> None:
        """Put a vehicle's FRONT bumper at (x, y), facing ``heading_rad``, at the next step.

        With ``lane_id`` (a lane of its route, internal lanes too, and a pose on that lane's centre line):
        moveToXY with keepRoute=1 and the lane as the hint keeps it on that lane, so SUMO never maps it
        onto another lane or edge. Without, free placement (keepRoute=2) maps it onto whatever lane lies
        at (x, y) (or none, off the road) with its exact lateral offset; so does a pose SUMO cannot map
        onto the route. The speed is set so that the vehicles around it react to it as to any other.
        """
        angle_deg = (90.0 - math.degrees(heading_rad)) % 360.0
        vehicle = self._api.vehicle
        placed = False
        if lane_id:
            edge_id, _, index = lane_id.rpartition("_")
            try:
                vehicle.moveToXY(vehicle_id, edge_id, int(index), float(x_front_m), float(y_front_m), angle_deg, 1)
                placed = True
            except Exception:  # libsumo's error when the pose is far off the route
                pass
        if not placed:
            vehicle.moveToXY(vehicle_id, "", -1, float(x_front_m), float(y_front_m), angle_deg, 2)
        vehicle.setSpeed(vehicle_id, max(0.0, float(speed_mps)))

    def colliding_vehicles(self) -> tuple[str, ...]:
        """Vehicles SUMO found in a collision during the last step."""
        return tuple(self._api.simulation.getCollidingVehiclesIDList())

    def _frame_ids(self) -> Collection[str]:
        vehicle = self._api.vehicle
        if self._focus is None:
            return vehicle.getIDList()
        if self._around_m > 0:  # each subscribed focus vehicle reports itself and its neighbours
            return set().union(*vehicle.getAllContextSubscriptionResults().values())
        return self._focus.intersection(vehicle.getIDList())

    def _read_frame(self, tc) -> Frame:
        vehicle = self._api.vehicle
        ids = sorted(self._frame_ids())
        n = len(ids)
        # fromiter over the flattened pairs: a third of np.array's time on a list of tuples
        front = np.fromiter(itertools.chain.from_iterable(map(vehicle.getPosition, ids)), np.float64, count=2 * n)
        front = front.reshape(n, 2)
        heading = sumo_angle_to_heading_rad(np.fromiter(map(vehicle.getAngle, ids), np.float64, count=n))
        speed = np.fromiter(map(vehicle.getSpeed, ids), np.float64, count=n)
        id_array = np.array(ids, dtype=str)
        # Vehicles already there last step keep their static values; SUMO's acceleration is
        # exactly the speed change over the step (0 on the first), which spares a call each.
        known = self._previous_ids
        at = np.minimum(np.searchsorted(known, id_array), max(len(known) - 1, 0))
        seen = (known[at] == id_array) if len(known) else np.zeros(n, dtype=bool)
        static = np.empty((n, 4))
        static[seen] = self._previous_static[at[seen]]
        for row in np.flatnonzero(~seen):
            static[row] = self._static[ids[row]]
        accel = np.zeros(n)
        accel[seen] = (speed[seen] - self._previous_speed[at[seen]]) / self._step_s
        self._previous_ids, self._previous_speed, self._previous_static = id_array, speed, static
        half_length = static[:, 0] / 2.0
        # SUMO reports the front bumper; the frame holds the footprint's centre.
        x_m = front[:, 0] - half_length * np.cos(heading)
        y_m = front[:, 1] - half_length * np.sin(heading)
        # Lane and the signal ahead cost SUMO a route walk a vehicle, so they are read
        # only for the watched vehicles; the others get '' / nan / inf.
        watched = ids if self._watch is None else [v for v in ids if v in self._watch]
        rows = np.searchsorted(id_array, np.array(watched, dtype=str)) if watched else np.zeros(0, dtype=np.intp)
        lane_pos = np.full(n, np.nan)
        lane_pos[rows] = [vehicle.getLanePosition(v) for v in watched]
        # the first signal ahead: (id, link index, distance, state), or none
        ahead = [next(iter(vehicle.getNextTLS(v)), ("", -1, np.inf, "")) for v in watched]
        tls_dist = np.full(n, np.inf)
        tls_dist[rows] = [a[2] for a in ahead]
        tls_link = np.full(n, -1, dtype=np.int64)
        tls_link[rows] = [int(a[1]) for a in ahead]
        foe_gap = np.full(n, np.inf)
        foe_gap[rows] = [yield_gap_m(vehicle.getJunctionFoes(v, FOE_RANGE_M)) for v in watched]
        tls_results = self._api.trafficlight.getAllSubscriptionResults() if self._tls_ids else {}
        rygs = tc.TL_RED_YELLOW_GREEN_STATE
        return Frame(
            t_s=self.t_s,
            ids=id_array,
            x_m=x_m,
            y_m=y_m,
            heading_rad=heading,
            speed_mps=speed,
            accel_mps2=accel,
            length_m=static[:, 0].copy(),  # copies: the next step must not share them
            width_m=static[:, 1].copy(),
            max_accel_mps2=static[:, 2].copy(),
            max_decel_mps2=static[:, 3].copy(),
            lane_id=_strings(n, rows, [vehicle.getLaneID(v) for v in watched]),
            lane_pos_m=lane_pos,
            tls_ahead_id=_strings(n, rows, [a[0] for a in ahead]),
            tls_ahead_state=_strings(n, rows, [a[3] for a in ahead]),
            tls_ahead_dist_m=tls_dist,
            foe_gap_m=foe_gap,
            tls_ahead_link=tls_link,
            tls_states={tls: tls_results[tls][rygs] for tls in self._tls_ids},
        )


def yield_gap_m(foes) -> float:
    """From SUMO's junction foes of a vehicle (tuples: foe id, ego distance, foe distance, ego exit
    distance, foe exit distance, ego lane, foe lane, ego must respond, foe must respond): the
    smallest distance to the conflict point of a foe that this vehicle must yield to and that has
    not yet cleared the conflict; inf if none."""
    gaps = [foe[2] for foe in foes if foe[7] and foe[4] > 0.0]
    return float(min(gaps)) if gaps else math.inf


def _strings(n: int, rows: np.ndarray, values: list[str]) -> np.ndarray:
    """A str column of ``n`` rows: ``values`` at ``rows``, '' elsewhere."""
    if not len(rows):  # nobody watched: skip the object array (a third of a frame's array work)
        return np.full(n, "", dtype=str)
    column = np.full(n, "", dtype=object)
    column[rows] = values
    return column.astype(str)
