"""Energy per vehicle: its radio's, from the wireless transfers the ledger charged, and its computer's,
from the time it trained (TOML ``[energy]``; summary.json ``energy_j``).

* Radio: the LTE power model of Huang et al., "A Close Examination of Performance and Power
  Characteristics of 4G LTE Networks", MobiSys 2012: while it transfers, the radio draws
  P = a_u r_u + a_d r_d + b (throughputs r in Mbit/s), fitted on a phone as a_u = 438.39 mW per
  Mbit/s, a_d = 51.97 mW per Mbit/s and b = 1288.04 mW. A transfer of M Mbit over T seconds so
  costs a M + b T millijoules. T runs from the transfer's start to its end on the clock, stalls
  included (the modem stays connected), less the time the vehicle was off (links/fleet.py: its
  radio is off too); M is the bytes the ledger charged for it.
* Computer: ``compute_power_w`` while it trains, for as long as it trains at its own speed
  (links/fleet.py; the time it is off does not count). The default, 30 W, is the highest power
  mode of NVIDIA's Jetson AGX Xavier, an in-vehicle AI computer (its modes are 10, 15 and 30 W).

Wireline transfers and the cloud's work are not the vehicles' and are not counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Mapping, Sequence

from crchfl_sumo.accounting.ledger import Record
from crchfl_sumo.core.numbers import check_range


@dataclass(frozen=True)
class EnergyConfig:
    """The power figures (module docstring): radio in mW and mW per Mbit/s, computer in W."""

    uplink_mw_per_mbps: float = 438.39
    downlink_mw_per_mbps: float = 51.97
    radio_base_mw: float = 1288.04
    compute_power_w: float = 30.0

    def __post_init__(self) -> None:
        for key in ("uplink_mw_per_mbps", "downlink_mw_per_mbps", "radio_base_mw"):
            check_range(getattr(self, key), f"energy.{key}", 0, 1e6, "milliwatts (per Mbit/s)")
        check_range(self.compute_power_w, "energy.compute_power_w", 0, 1e5, "watts")


def transfer_energy_j(record: Record, config: EnergyConfig, off_s: float = 0.0) -> float:
    """The radio energy of one wireless transfer [J]; ``off_s``: how long of it the vehicle was off."""
    mbit = 8.0 * record.size_bytes / 1e6
    per_mbit = config.uplink_mw_per_mbps if record.direction == "uplink" else config.downlink_mw_per_mbps
    airtime_s = max(record.end_s - record.start_s - off_s, 0.0)
    return (per_mbit * mbit + config.radio_base_mw * airtime_s) / 1000.0


def vehicle_energy_j(
    records: Iterable[Record],
    train_s: Mapping[str, float],
    vehicles: Sequence[str],
    config: EnergyConfig,
    off_s_within: Callable[[str, float, float], float] | None = None,
) -> dict:
    """summary.json's ``energy_j``: per vehicle its radio, compute and total joules, and the sums.
    ``off_s_within(vehicle, from_s, to_s)``: how long the vehicle was off then (links.fleet.Fleet)."""
    radio = dict.fromkeys(vehicles, 0.0)
    for r in records:
        if r.link != "wireless":
            continue
        vehicle = r.sender if r.direction == "uplink" else r.receiver
        if vehicle in radio:
            off_s = off_s_within(vehicle, r.start_s, r.end_s) if off_s_within else 0.0
            radio[vehicle] += transfer_energy_j(r, config, off_s)
    per_vehicle = {}
    for v in vehicles:
        compute = config.compute_power_w * train_s.get(v, 0.0)
        per_vehicle[v] = {"radio": radio[v], "compute": compute, "total": radio[v] + compute}
    return {
        "total": sum(e["total"] for e in per_vehicle.values()),
        "radio": sum(e["radio"] for e in per_vehicle.values()),
        "compute": sum(e["compute"] for e in per_vehicle.values()),
        "vehicles": per_vehicle,
    }
