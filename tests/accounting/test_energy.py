"""Energy per vehicle (accounting/energy.py), by hand."""

from __future__ import annotations

import pytest

from crchfl_sumo.accounting.energy import EnergyConfig, transfer_energy_j, vehicle_energy_j
from crchfl_sumo.accounting.ledger import Record
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.federation.run_config import RunConfig


def _record(link, direction, sender, receiver, size_bytes, start_s, end_s):
    return Record(link, direction, "II", sender, receiver, "model", size_bytes, 1, start_s, end_s)


UP = _record("wireless", "uplink", "a", "e0", 1_000_000, 0.0, 2.0)  # 8 Mbit in 2 s
DOWN = _record("wireless", "downlink", "e0", "a", 1_000_000, 5.0, 6.0)  # 8 Mbit in 1 s
WIRE = _record("wireline", "uplink", "e0", "cloud", 1_000_000, 2.0, 2.1)


def test_a_transfer_costs_its_megabits_and_its_airtime_under_the_lte_model():
    config = EnergyConfig()
    assert transfer_energy_j(UP, config) == pytest.approx((438.39 * 8 + 1288.04 * 2) / 1000)  # 6.0832 J
    assert transfer_energy_j(DOWN, config) == pytest.approx((51.97 * 8 + 1288.04 * 1) / 1000)  # 1.7038 J
    # off for 0.5 s of the upload's 2 s: its radio draws the base power 1.5 s only
    assert transfer_energy_j(UP, config, off_s=0.5) == pytest.approx((438.39 * 8 + 1288.04 * 1.5) / 1000)


def test_each_vehicle_pays_its_own_wireless_transfers_and_its_training():
    energy = vehicle_energy_j([UP, DOWN, WIRE], {"a": 10.0, "b": 2.0}, ["a", "b", "c"], EnergyConfig())
    a, b, c = (energy["vehicles"][v] for v in "abc")
    assert a["radio"] == pytest.approx(6.0832 + 1.7038) and a["compute"] == pytest.approx(300.0)
    assert a["total"] == pytest.approx(a["radio"] + a["compute"])
    assert (b["radio"], b["compute"]) == (0.0, pytest.approx(60.0))  # 2 s at 30 W
    assert c == {"radio": 0.0, "compute": 0.0, "total": 0.0}  # the wireline hop is nobody's
    assert energy["total"] == pytest.approx(a["total"] + b["total"])
    assert energy["radio"] + energy["compute"] == pytest.approx(energy["total"])


def test_bad_power_figures_are_refused_naming_the_key():
    with pytest.raises(CrchflError, match="energy.compute_power_w"):
        from_mapping(RunConfig, {"energy": {"compute_power_w": -1.0}}, "run.toml")
    with pytest.raises(CrchflError, match="unknown key"):
        from_mapping(RunConfig, {"energy": {"watts": 1.0}}, "run.toml")
