"""Data and test vehicles for a scenario that names none: added on seeded trips, kept for the whole run."""

from __future__ import annotations

import numpy as np
import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.injection import INJECTED_TYPE, InjectConfig
from crchfl_sumo.sumo.scenario import SumoConfig, configured_scenario, load_scenario
from crchfl_sumo.sumo.simulation import Simulation


def _drive(scenario, seed, duration_s=600.0):
    """Per step: the injected vehicles present; and each vehicle's first route."""
    with Simulation(scenario, seed=seed, watch=set(scenario.injected)) as sim:
        first = {v: tuple(sim._api.vehicle.getRoute(v)) for v in scenario.injected}
        frames = list(sim.run(duration_s))
        types = {sim._api.vehicle.getTypeID(v) for v in scenario.injected}
    return first, frames, types


def test_a_scenario_naming_no_vehicle_gets_them_for_the_whole_run(grid_dir):
    scenario = load_scenario(grid_dir / "grid.sumocfg")
    (town,) = scenario.towns
    assert town.data_vehicles == tuple(f"grid_data_{i}" for i in range(5)) and town.test_vehicles == ("grid_test_0",)
    assert scenario.injected == (*town.data_vehicles, *town.test_vehicles)
    first, frames, types = _drive(scenario, seed=1)
    assert types == {INJECTED_TYPE}
    # the routes the grid's flows end on arrive; the added vehicles are there at every step after the first
    assert all(set(scenario.injected) <= set(f.ids) for f in frames[1:])
    assert all(len(route) >= 3 for route in first.values())
    moved = {v: np.hypot(*np.diff([[f.x_m[f.index_of(v)], f.y_m[f.index_of(v)]] for f in (frames[1], frames[-1])], axis=0)[0])
             for v in scenario.injected}
    assert all(m > 50.0 for m in moved.values())  # they drive on: sent on to a new destination each time
    # the same seed gives the same trips and frames; another SUMO seed keeps each vehicle's first trip
    again, frames_again, _ = _drive(scenario, seed=1)
    assert again == first
    assert all(np.array_equal(a.x_m, b.x_m) for a, b in zip(frames, frames_again))
    other_sumo, _, _ = _drive(scenario, seed=2, duration_s=1.0)
    assert other_sumo == first
    # another injection seed draws other trips
    reseeded = configured_scenario(grid_dir / "grid.sumocfg", SumoConfig(inject_seed=5), 250.0)
    assert _drive(reseeded, seed=1, duration_s=1.0)[0] != first


def test_a_scenario_that_names_vehicles_gets_none_added_and_counts_are_settings(grid_dir):
    assert load_scenario("paper").injected == ()
    two = configured_scenario(grid_dir / "grid.sumocfg", SumoConfig(data_vehicles=2, test_vehicles=0), 250.0)
    assert two.injected == ("grid_data_0", "grid_data_1") and two.towns[0].test_vehicles == ()
    with pytest.raises(CrchflError, match="sumo.data_vehicles: -1 is out of range"):
        SumoConfig(data_vehicles=-1)
    with pytest.raises(CrchflError, match="sumo.test_vehicles"):
        InjectConfig(test_vehicles=10**6)
