"""Any SUMO scenario a user brings: here an OSM import with a 3-lane motorway and ramps."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from crchfl_sumo.studies.simulate import SimulateConfig, simulate, summarize
from crchfl_sumo.sumo.scenario import load_scenario, sumo_binary, sumo_tool_script

FIXTURE = Path(__file__).parents[1] / "fixtures" / "motorway_ramps.osm"


@pytest.fixture(scope="module")
def osm_scenario(tmp_path_factory):
    folder = tmp_path_factory.mktemp("osm")
    subprocess.run(
        [sumo_binary("netconvert"), "--osm-files", str(FIXTURE), "-o", str(folder / "osm.net.xml"),
         "--ramps.guess", "--geometry.remove", "--no-turnarounds"],
        check=True, capture_output=True,
    )
    subprocess.run(
        [sys.executable, sumo_tool_script("randomTrips.py"), "-n", str(folder / "osm.net.xml"),
         "-o", str(folder / "trips.trips.xml"), "-r", str(folder / "osm.rou.xml"), "-e", "120", "-p", "1.5",
         "--seed", "7", "--validate", "--fringe-factor", "10"],
        check=True, capture_output=True,
    )
    (folder / "osm.sumocfg").write_text(
        """<configuration>
  <input><net-file value="osm.net.xml"/><route-files value="osm.rou.xml"/></input>
  <time><step-length value="0.1"/></time>
</configuration>
"""
    )
    return folder / "osm.sumocfg"


def test_osm_motorway_with_ramps_runs_with_sites_placed_automatically(osm_scenario):
    scenario = load_scenario(osm_scenario, coverage_radius_m=300.0)
    import sumolib

    net = sumolib.net.readNet(str(scenario.net_path))
    assert max(e.getLaneNumber() for e in net.getEdges()) >= 3  # multi-lane motorway
    assert any("ramp" in e.getID().lower() or e.getLaneNumber() == 1 for e in net.getEdges())
    assert scenario.step_length_s == pytest.approx(0.1)
    assert len(scenario.edge_sites) >= 2  # 1.6 km of motorway cannot be covered by one 300 m site
    cfg = SimulateConfig(seed=2)
    trace = simulate(scenario, 60.0, cfg)
    summary = summarize(trace, scenario, 60.0, cfg)
    assert summary["steps"] == 600
    assert summary["vehicles"] >= 20
    assert summary["teleports"] == 0
    assert summary["coverage_fraction"] > 0.5
    assert np.all(np.isfinite(trace.x_m)) and np.all(trace.rate_bps >= 0)
