"""The one module that drives SUMO: start, step, read a Frame, stop.

libsumo runs SUMO inside this process (one simulation per process: run parallel
simulations in separate processes). The same code also runs over TraCI (pass
``api=traci``), which the benchmark uses as its comparison. State is read
through one context subscription, so one step costs one bulk read, not one
call per vehicle and variable.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from collections.abc import Collection
from types import ModuleType

import numpy as np

from .errors import CrchflError
from .frame import Frame, sumo_angle_to_heading_rad
from .scenario import Scenario, sumo_binary

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
    ) -> None:
        """``watch``: the vehicles whose signal ahead is read each step (None: all)."""
        self.scenario = scenario
        self._watch = None if watch is None else frozenset(watch)
        self.seed = int(seed)
        self._api = api
        self._extra_options = tuple(extra_options)
        self._uses_libsumo = api is None
        self._static: dict[str, tuple[float, float, float, float]] = {}
        self._tls_ids: tuple[str, ...] = ()
        self._steps = self._departed = self._arrived = self._teleports = self._collisions = 0
        self._running = False

    # --- lifecycle --------------------------------------------------------------------------

    def command(self) -> list[str]:
        """The sumo command line this simulation runs (also usable with the plain binary)."""
        return [
            sumo_binary(),
            *self.scenario.sumo_options,
            f"--seed={self.seed}",
            "--no-step-log=true",
            "--duration-log.disable=true",
            *self._extra_options,
        ]

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
        # One context subscription around a junction, with a radius covering the whole
        # network, returns every vehicle in one bulk read. (Per-vehicle subscriptions
        # cost SUMO time that grows faster than the number of vehicles.)
        bounds = self.scenario.bounds
        radius_m = 2.0 * float(np.hypot(bounds.xmax_m - bounds.xmin_m, bounds.ymax_m - bounds.ymin_m)) + 1e3
        self._anchor = api.junction.getIDList()[0]
        api.junction.subscribeContext(
            self._anchor,
            tc.CMD_GET_VEHICLE_VARIABLE,
            radius_m,
            [tc.VAR_POSITION, tc.VAR_ANGLE, tc.VAR_SPEED, tc.VAR_ACCELERATION, tc.VAR_LANE_ID, tc.VAR_LANEPOSITION],
        )
        self._tls_ids = tuple(sorted(api.trafficlight.getIDList()))
        for tls in self._tls_ids:
            api.trafficlight.subscribe(tls, [tc.TL_RED_YELLOW_GREEN_STATE])
        return self

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
        api.simulationStep()
        self._steps += 1
        sim = api.simulation.getSubscriptionResults()
        for vehicle_id in sim[tc.VAR_DEPARTED_VEHICLES_IDS]:
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

    def _read_frame(self, tc) -> Frame:
        results = self._api.junction.getContextSubscriptionResults(self._anchor)
        ids = sorted(v for v in results if v in self._static)
        rows = [results[v] for v in ids]
        static = np.array([self._static[v] for v in ids], dtype=np.float64).reshape(-1, 4)
        front = np.array([r[tc.VAR_POSITION] for r in rows], dtype=np.float64).reshape(-1, 2)
        heading = sumo_angle_to_heading_rad(np.array([r[tc.VAR_ANGLE] for r in rows], dtype=np.float64))
        half_length = static[:, 0] / 2.0
        # SUMO reports the front bumper; the frame holds the footprint's centre.
        x_m = front[:, 0] - half_length * np.cos(heading)
        y_m = front[:, 1] - half_length * np.sin(heading)
        # The signal ahead walks the route inside SUMO (microseconds a vehicle), so it is
        # read only for the watched vehicles; the others get '' / inf.
        watched = self._watch
        next_tls = [
            self._api.vehicle.getNextTLS(v) if watched is None or v in watched else () for v in ids
        ]
        tls_id = np.array([n[0][0] if n else "" for n in next_tls], dtype=str) if rows else np.zeros(0, str)
        tls_state = np.array([n[0][3] if n else "" for n in next_tls], dtype=str) if rows else np.zeros(0, str)
        tls_dist = np.array([n[0][2] if n else np.inf for n in next_tls], dtype=np.float64)
        tls_results = self._api.trafficlight.getAllSubscriptionResults()
        rygs = tc.TL_RED_YELLOW_GREEN_STATE
        return Frame(
            t_s=self.t_s,
            ids=np.array(ids, dtype=str),
            x_m=x_m,
            y_m=y_m,
            heading_rad=heading,
            speed_mps=np.array([r[tc.VAR_SPEED] for r in rows], dtype=np.float64),
            accel_mps2=np.array([r[tc.VAR_ACCELERATION] for r in rows], dtype=np.float64),
            length_m=static[:, 0].copy(),
            width_m=static[:, 1].copy(),
            max_accel_mps2=static[:, 2].copy(),
            max_decel_mps2=static[:, 3].copy(),
            lane_id=np.array([r[tc.VAR_LANE_ID] for r in rows], dtype=str) if rows else np.zeros(0, str),
            lane_pos_m=np.array([r[tc.VAR_LANEPOSITION] for r in rows], dtype=np.float64),
            tls_ahead_id=tls_id,
            tls_ahead_state=tls_state,
            tls_ahead_dist_m=tls_dist,
            tls_states={tls: tls_results[tls][rygs] for tls in self._tls_ids},
        )
