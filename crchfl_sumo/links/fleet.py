"""The federated vehicles as devices: how fast each one trains, and when it is on.

Two settings of a run's ``[clock]`` table (federation/run_config.py) describe them:

* ``compute_profile``: each vehicle's compute speed, as a factor on
  ``federation.compute_s_per_sample`` (2 = a vehicle that needs twice as long):
  "equal" (every vehicle 1, the paper), "lognormal" (``exp(compute_sigma * z)``,
  z standard normal: median 1, a long tail of slow vehicles, the shape of the
  on-device training times that FedScale's device traces give, Lai et al.,
  ICML 2022) or "tiers" (each vehicle one of ``compute_tiers``, drawn uniformly:
  a fleet of a few car computer generations).
* ``availability``: when a vehicle is on. "always" (the paper), "onoff" (each
  vehicle alternates on and off periods with exponential lengths of mean
  ``mean_on_s`` and ``mean_off_s``, starting on with probability
  mean_on / (mean_on + mean_off): an alternating renewal process, the usual
  model of client churn) or "trace" (``availability_trace``: a CSV file with
  the header ``vehicle,off_start_s,off_end_s``, one row per time a vehicle is
  parked or its ignition is off; a vehicle the file does not name is always on).

While a vehicle is off it neither trains nor transmits: its training pauses
and goes on when it is back (``Fleet.work_end_s``), and its link carries
nothing (``AvailableClock``: rate 0 and no serving site, an outage to every
transfer). The draws are seeded by the run's seed and the vehicle's place,
so a resumed run sees the same fleet.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_SIMULATED_S, check_range
from crchfl_sumo.links.mobility import NO_SITE

COMPUTE_PROFILES = ("equal", "lognormal", "tiers")
AVAILABILITIES = ("always", "onoff", "trace")
_EPS_S = 1e-9


@dataclass(frozen=True)
class FleetConfig:
    """The devices' settings, as ``[clock]`` names them (module docstring)."""

    compute_profile: str = "equal"
    compute_sigma: float = 0.5
    compute_tiers: tuple[float, ...] = (1.0, 2.0, 4.0)
    availability: str = "always"
    mean_on_s: float = 600.0
    mean_off_s: float = 120.0
    availability_trace: str = ""

    def __post_init__(self) -> None:
        if self.compute_profile not in COMPUTE_PROFILES:
            raise CrchflError(
                f"clock.compute_profile: {self.compute_profile!r} is not one of "
                f"{', '.join(map(repr, COMPUTE_PROFILES))}"
            )
        check_range(self.compute_sigma, "clock.compute_sigma", 0, 3, "the spread of log(speed factor)")
        if not self.compute_tiers:
            raise CrchflError("clock.compute_tiers: give at least one speed factor, e.g. [1.0, 2.0, 4.0]")
        for i, tier in enumerate(self.compute_tiers):
            check_range(tier, f"clock.compute_tiers[{i}]", 0, 1000, "a speed factor (2 = twice as slow)",
                        lo_open=True)
        if self.availability not in AVAILABILITIES:
            raise CrchflError(
                f"clock.availability: {self.availability!r} is not one of {', '.join(map(repr, AVAILABILITIES))}"
            )
        for key in ("mean_on_s", "mean_off_s"):
            check_range(getattr(self, key), f"clock.{key}", 0, MAX_SIMULATED_S, "simulated seconds", lo_open=True)
        if (self.availability == "trace") != bool(self.availability_trace):
            raise CrchflError(
                "clock.availability_trace: give the CSV file exactly when availability = \"trace\" "
                f"(availability is {self.availability!r}, availability_trace {self.availability_trace!r})"
            )


@dataclass(frozen=True)
class Fleet:
    """Each vehicle's compute factor and off periods.

    compute_factor: vehicle -> factor on the nominal time per sample (a vehicle not named: 1).
    off_s: vehicle -> [N, 2] array of sorted, disjoint [start, end) periods it is off (not named: always on).
    start_s: when the federation starts (the draws start there).
    """

    compute_factor: Mapping[str, float] = field(default_factory=dict)
    off_s: Mapping[str, np.ndarray] = field(default_factory=dict)
    start_s: float = 0.0  # the federation's first moment

    @property
    def intermittent(self) -> bool:
        return any(len(periods) for periods in self.off_s.values())

    def factor(self, vehicle: str) -> float:
        return float(self.compute_factor.get(vehicle, 1.0))

    def _periods(self, vehicle: str) -> np.ndarray:
        return self.off_s.get(vehicle, _NONE)

    def is_on(self, vehicle: str, t_s: float) -> bool:
        return bool(self.on_mask(vehicle, np.array([t_s]))[0])

    def off_s_within(self, vehicle: str, from_s: float, to_s: float) -> float:
        """How long ``vehicle`` is off within ``[from_s, to_s]`` [s]."""
        periods = self._periods(vehicle)
        overlap = np.minimum(periods[:, 1], to_s) - np.maximum(periods[:, 0], from_s)
        return float(np.sum(np.maximum(overlap, 0.0)))

    def off_between(self, vehicle: str, from_s: float, to_s: float) -> bool:
        """Whether ``vehicle`` is off at any moment of ``[from_s, to_s]``."""
        periods = self._periods(vehicle)
        return bool(np.any((periods[:, 0] <= to_s) & (periods[:, 1] > from_s)))

    def work_end_s(self, vehicle: str, start_s: float, work_s: float) -> float:
        """When ``work_s`` seconds of on-time after ``start_s`` have passed (training pauses while off)."""
        t, left = start_s, work_s
        for off_start, off_end in self._periods(vehicle):
            if off_end <= t:
                continue
            if off_start > t:
                if t + left <= off_start:
                    return t + left
                left -= off_start - t
            t = max(t, off_end)
        return t + left

    def on_mask(self, vehicle: str, t_s: np.ndarray) -> np.ndarray:
        """For each time of ``t_s``: is ``vehicle`` on then?"""
        periods = self._periods(vehicle)
        i = np.searchsorted(periods[:, 0], t_s, side="right") - 1
        inside = (i >= 0) & (t_s < periods[np.maximum(i, 0), 1]) if len(periods) else np.zeros(len(t_s), bool)
        return ~inside

    def boundaries(self, vehicle: str, from_s: float, to_s: float) -> np.ndarray:
        """The times within ``(from_s, to_s)`` at which ``vehicle`` turns off or on."""
        edges = self._periods(vehicle).ravel()
        return edges[(edges > from_s) & (edges < to_s)]


_NONE = np.zeros((0, 2))


def draw_fleet(config: FleetConfig, vehicles: Sequence[str], seed: int, start_s: float = 0.0) -> Fleet:
    """The fleet of ``config`` for ``vehicles`` (in their run order), seeded by ``seed``.

    On/off periods are drawn from ``start_s`` (the federation's first moment) for a simulated day.
    """
    factors = {}
    for i, v in enumerate(vehicles):
        rng = np.random.default_rng([seed, 7, i])
        if config.compute_profile == "lognormal":
            factors[v] = float(np.exp(config.compute_sigma * rng.standard_normal()))
        elif config.compute_profile == "tiers":
            factors[v] = float(config.compute_tiers[int(rng.integers(len(config.compute_tiers)))])
    if config.availability == "onoff":
        off = {v: _on_off_periods(config, np.random.default_rng([seed, 8, i]), start_s) for i, v in enumerate(vehicles)}
    elif config.availability == "trace":
        off = read_availability_trace(Path(config.availability_trace), vehicles)
    else:
        off = {}
    return Fleet(factors, off, start_s)


def _on_off_periods(config: FleetConfig, rng: np.random.Generator, start_s: float) -> np.ndarray:
    """Alternating exponential on and off periods from ``start_s`` for a simulated day; the off ones."""
    share_on = config.mean_on_s / (config.mean_on_s + config.mean_off_s)
    on = bool(rng.random() < share_on)
    t, periods = start_s, []
    while t < start_s + MAX_SIMULATED_S:
        length = rng.exponential(config.mean_on_s if on else config.mean_off_s)
        if not on:
            periods.append((t, t + length))
        t += length
        on = not on
    return np.array(periods, dtype=float).reshape(-1, 2)


def read_availability_trace(path: Path, vehicles: Sequence[str]) -> dict[str, np.ndarray]:
    """``vehicle,off_start_s,off_end_s`` rows of ``path`` as each vehicle's sorted off periods (overlaps merged)."""
    header = ["vehicle", "off_start_s", "off_end_s"]
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as exc:
        raise CrchflError(f"clock.availability_trace: cannot read {path} ({exc}); give a CSV file with the "
                          f"header {','.join(header)}") from None
    if not rows or [c.strip() for c in rows[0]] != header:
        raise CrchflError(f"{path}: the first line must be the header {','.join(header)}")
    known, periods = set(vehicles), {}
    for line, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) != 3:
            raise CrchflError(f"{path}, line {line}: expected 3 values ({','.join(header)}), got {len(row)}")
        vehicle = row[0].strip()
        if vehicle not in known:
            raise CrchflError(f"{path}, line {line}: vehicle {vehicle!r} is not federated in this run "
                              f"(the run's vehicles: {', '.join(vehicles)})")
        try:
            start, end = float(row[1]), float(row[2])
        except ValueError:
            raise CrchflError(
                f"{path}, line {line}: off_start_s and off_end_s must be numbers, got {row[1:]!r}"
            ) from None
        if not (math.isfinite(start) and math.isfinite(end) and 0 <= start < end):
            raise CrchflError(f"{path}, line {line}: need finite times with 0 <= off_start_s < off_end_s, "
                              f"got {start}, {end}")
        periods.setdefault(vehicle, []).append((start, end))
    return {v: _merged(p) for v, p in periods.items()}


def _merged(periods: list[tuple[float, float]]) -> np.ndarray:
    merged: list[list[float]] = []
    for start, end in sorted(periods):
        if merged and start <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([start, end])
    return np.array(merged, dtype=float).reshape(-1, 2)


class AvailableClock:
    """``clock`` with every vehicle's link dead while it is off: rate 0 and no serving site, with a
    sample at each moment it turns off or on. Everything else is the wrapped clock's."""

    def __init__(self, clock, fleet: Fleet) -> None:
        self._clock = clock
        self._fleet = fleet

    def __getattr__(self, name):  # start_s, step_s, handovers, pose, collected, ...
        return getattr(self._clock, name)

    def series(self, vehicle: str, kind: str, from_s: float, to_s: float):
        link = self._clock.series(vehicle, kind, from_s, to_s)
        extra = self._fleet.boundaries(vehicle, float(link.t_s[0]), float(link.t_s[-1]))
        t = np.union1d(link.t_s, extra) if len(extra) else link.t_s
        at = np.searchsorted(link.t_s, t, side="right") - 1  # the link sample in force at each time
        on = self._fleet.on_mask(vehicle, t)
        rate = np.where(on, link.rate_bps[at], 0.0)
        site = np.where(on, link.site[at], NO_SITE)
        return type(link)(t, rate, site)
