"""What a LinkModel (links/mobility.py) reports: each step's LinkSnapshot with its Handovers, and one
vehicle's rate series over recorded snapshots."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass(frozen=True)
class Handover:
    """A change of serving site; -1 on either side is an attach or a loss of coverage."""

    t_s: float
    vehicle_id: str
    from_site: int
    to_site: int


@dataclass(frozen=True)
class LinkSnapshot:
    """Link state of every vehicle of one frame; arrays are aligned with ``ids``.

    site            [V] int   serving site index (-1: no coverage)
    rx_power_dbm    [V] f64   large-scale received power from it (NaN if none)
    snr_db          [V] f64   large-scale SNR, before fading (NaN if none)
    rate_bps        [V] f64   rate this step after sharing and fading (0 if none)
    cell_load       [V] int   vehicles the cell's bandwidth is split among (0 if none)
    handovers       the serving-site changes that happened at this step
    """

    t_s: float
    ids: np.ndarray
    site: np.ndarray
    rx_power_dbm: np.ndarray
    snr_db: np.ndarray
    rate_bps: np.ndarray
    cell_load: np.ndarray
    handovers: tuple[Handover, ...] = ()

    def rate_of(self, vehicle_id: str) -> float:
        """Rate [bit/s] of one vehicle; 0 when it is not in this snapshot."""
        hits = np.flatnonzero(self.ids == vehicle_id)
        return float(self.rate_bps[hits[0]]) if len(hits) else 0.0




def rate_series(snapshots: Sequence[LinkSnapshot], vehicle_id: str) -> tuple[np.ndarray, np.ndarray]:
    """(t_s, rate_bps) of one vehicle over recorded snapshots; 0 where it is absent or uncovered.

    The result feeds transfer.transfer(): rates hold from one sample to the next.
    """
    t_s = np.array([s.t_s for s in snapshots], dtype=np.float64)
    rate_bps = np.array([s.rate_of(vehicle_id) for s in snapshots], dtype=np.float64)
    return t_s, rate_bps
