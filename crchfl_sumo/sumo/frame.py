"""One simulation step as plain numpy arrays: what every consumer of SUMO state takes.

The simulator (sumo/simulation.py) produces Frames; mobility, the rasterizer and the expert
consume them without ever touching the simulator. Coordinates are SUMO's
network frame: x east [m], y north [m]. Headings follow the mathematical
convention: radians, 0 = east (+x), counter-clockwise positive, so that
(cos h, sin h) is the direction of travel. (SUMO's own "angle" is degrees
clockwise from north: heading_rad = radians(90 - angle).)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

NO_SIGNAL = ""  # tls_ahead_state / tls_ahead_id for a vehicle with no signal ahead
FOE_RANGE_M = 50.0  # how far ahead a watched vehicle's junction foes are looked for (Frame.foe_gap_m)


@dataclass(frozen=True)
class Frame:
    """State of all vehicles at simulated time ``t_s``; arrays are indexed by vehicle.

    Attributes (V = number of vehicles):
      ids             [V] str   vehicle ids, sorted, so two frames index alike
      x_m, y_m        [V] f64   centre of the vehicle's footprint [m] (SUMO
                                reports the front bumper; sumo/simulation.py shifts it)
      heading_rad     [V] f64   direction of travel, math convention (module doc)
      speed_mps       [V] f64
      accel_mps2      [V] f64   acceleration SUMO applied in the last step
      length_m, width_m [V] f64
      max_accel_mps2, max_decel_mps2 [V] f64  the vehicle type's limits
      lane_id         [V] str   current lane ('' if not read: see below)
      lane_pos_m      [V] f64   distance along that lane (nan if not read)
      tls_ahead_id    [V] str   next traffic light on the route ('' if none)
      tls_ahead_state [V] str   its one-letter state for this vehicle's link
                                (SUMO letters: r y g G u o O s; '' if none)
      tls_ahead_dist_m [V] f64  distance to its stop line (inf if none)
      tls_ahead_link  [V] i64   the link index of this vehicle's link at it (-1 if none)
      foe_gap_m       [V] f64   at a junction within FOE_RANGE_M ahead: the distance
                                to the conflict point of the nearest vehicle this one
                                must yield to (SUMO's junction foes; inf if none)
      tls_states      dict tls id -> full SUMO state string (one letter a link;
                                empty from a Simulation with signals=False)

    The lane, tls_ahead_* and foe_gap_m columns cost the simulator a route walk a vehicle,
    so sim.Simulation fills them only for the vehicles it is told to watch.
    """

    t_s: float
    ids: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    max_accel_mps2: np.ndarray
    max_decel_mps2: np.ndarray
    lane_id: np.ndarray
    lane_pos_m: np.ndarray
    tls_ahead_id: np.ndarray
    tls_ahead_state: np.ndarray
    tls_ahead_dist_m: np.ndarray
    foe_gap_m: np.ndarray
    tls_ahead_link: np.ndarray
    tls_states: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.ids)

    def index_of(self, vehicle_id: str) -> int:
        """Row of ``vehicle_id``; raises KeyError if it is not in this frame."""
        hits = np.flatnonzero(self.ids == vehicle_id)
        if len(hits) == 0:
            raise KeyError(vehicle_id)
        return int(hits[0])

    def select(self, rows: np.ndarray) -> "Frame":
        """A frame holding only the given rows (index array or boolean mask)."""
        changes = {
            f.name: getattr(self, f.name)[rows]
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        }
        return dataclasses.replace(self, **changes)


def sumo_angle_to_heading_rad(angle_deg):
    """SUMO angle (degrees clockwise from north) -> heading (radians CCW from east)."""
    return np.radians(90.0 - np.asarray(angle_deg, dtype=np.float64))


def make_frame(t_s: float = 0.0, tls_states: dict[str, str] | None = None, **columns) -> Frame:
    """Build a Frame from per-vehicle columns, filling omitted ones with neutral values.

    Meant for tests and synthetic scenes: ``make_frame(ids=["a"], x_m=[0.0], y_m=[0.0])``.
    """
    ids = np.asarray(columns.pop("ids"), dtype=str)
    n = len(ids)
    defaults = {
        "x_m": 0.0,
        "y_m": 0.0,
        "heading_rad": 0.0,
        "speed_mps": 0.0,
        "accel_mps2": 0.0,
        "length_m": 4.5,
        "width_m": 1.8,
        "max_accel_mps2": 2.6,
        "max_decel_mps2": 4.5,
        "lane_pos_m": 0.0,
        "tls_ahead_dist_m": math.inf,
        "foe_gap_m": math.inf,
    }
    arrays = {}
    for name, default in defaults.items():
        value = columns.pop(name, None)
        arrays[name] = (
            np.full(n, default, dtype=np.float64) if value is None else np.asarray(value, dtype=np.float64)
        )
    link = columns.pop("tls_ahead_link", None)
    arrays["tls_ahead_link"] = np.full(n, -1, dtype=np.int64) if link is None else np.asarray(link, dtype=np.int64)
    for name in ("lane_id", "tls_ahead_id", "tls_ahead_state"):
        value = columns.pop(name, None)
        arrays[name] = np.full(n, "", dtype=object).astype(str) if value is None else np.asarray(value, dtype=str)
    if columns:
        raise TypeError(f"make_frame: unknown columns {sorted(columns)}")
    return Frame(t_s=float(t_s), ids=ids, tls_states=dict(tls_states or {}), **arrays)
