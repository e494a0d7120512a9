"""Any SUMO scenario a user brings: here an OSM import with a 3-lane motorway and ramps."""

import gzip
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from crchfl_sumo.cli import main
from crchfl_sumo.core.resources import scenarios_dir
from crchfl_sumo.studies.simulate import SimulateConfig, simulate, summarize
from crchfl_sumo.sumo.injection import InjectConfig
from crchfl_sumo.sumo.installation import sumo_binary, sumo_tool_script
from crchfl_sumo.sumo.scenario import load_scenario

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


def _gzip_copy(source: Path, target: Path) -> None:
    with open(source, "rb") as plain, gzip.open(target, "wb") as packed:
        shutil.copyfileobj(plain, packed)


def test_gzipped_copy_of_a_builtin_town_simulates_like_the_plain_one(tmp_path):
    # town01 with its network, routes and additional file gzipped, and the
    # configuration written in the other forms sumo reads: 'v' for 'value',
    # the value as the element's text, an option outside any section, a synonym.
    town = scenarios_dir() / "town01"
    for name in ("town01.net.xml", "town01.ego.rou.xml", "town01.bg.rou.xml", "vtypes.add.xml"):
        _gzip_copy(town / name, tmp_path / f"{name}.gz")
    (tmp_path / "packed.sumocfg").write_text(
        """<configuration>
  <input>
    <net-file v="town01.net.xml.gz"/>
    <route-files>town01.ego.rou.xml.gz, town01.bg.rou.xml.gz</route-files>
  </input>
  <a value="vtypes.add.xml.gz"/>
  <step-length value="0.25"/>
  <seed value="42"/>
</configuration>
"""
    )
    sites = load_scenario("town01").edge_sites
    # none added (a plain .sumocfg names no vehicles and would get some): the built-in's vehicles alone
    packed = load_scenario(tmp_path / "packed.sumocfg", edge_sites=sites, inject=InjectConfig(0, 0))
    plain = load_scenario("town01")
    assert packed.bounds == plain.bounds
    assert packed.step_length_s == pytest.approx(0.25)
    cfg = SimulateConfig(seed=1)
    a = summarize(simulate(packed, 15.0, cfg), packed, 15.0, cfg)
    b = summarize(simulate(plain, 15.0, cfg), plain, 15.0, cfg)
    assert a["steps"] == 60 and a["vehicles"] > 0
    for key in ("vehicles", "handovers", "mean_rate_bps", "coverage_fraction"):
        assert a[key] == b[key], key
    # And through the command line.
    assert main(["simulate", str(tmp_path / "packed.sumocfg"), "--duration-s", "5", "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "handovers.csv").is_file()
    # The rasterizer's world and the benchmark's routes read the gzipped files too.
    from crchfl_sumo.driving.drive_bench_tasks import data_routes, longest_waits_s
    from crchfl_sumo.vision.world import build_world

    packed_world, plain_world = build_world(packed.net_path), build_world(plain.net_path)
    assert np.array_equal(packed_world.texture, plain_world.texture) and packed_world.heads == plain_world.heads
    waits = longest_waits_s(Path(packed.net_path))
    assert waits == longest_waits_s(Path(plain.net_path)) and max(waits.values()) > 0
    assert data_routes(packed) == []  # its gzipped route files parse; the copy names no data vehicles


def test_truncated_gzipped_network_is_refused_by_name(tmp_path, capsys):
    (tmp_path / "net.net.xml.gz").write_bytes(gzip.compress(b"<net><location convBoundary='0,0,1,1'")[:-12])
    (tmp_path / "x.sumocfg").write_text('<configuration><net-file value="net.net.xml.gz"/></configuration>')
    assert main(["simulate", str(tmp_path / "x.sumocfg"), "--duration-s", "1", "--out", str(tmp_path / "o")]) == 2
    assert "net.net.xml.gz: malformed SUMO network" in capsys.readouterr().err
