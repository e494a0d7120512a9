import subprocess
import sys

import numpy as np
import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation
from crchfl_sumo.sumo.sites import EdgeSite, place_edge_sites


def test_user_config_with_gui_options_relative_paths_and_several_files(grid_dir, tmp_path, monkeypatch):
    # A user config in another folder, relative paths, two route files, an additional
    # file, GUI-only options (whose settings file does not even exist), an output file.
    user = tmp_path / "user"
    (user / "routes").mkdir(parents=True)
    (user / "routes" / "a.rou.xml").write_text((grid_dir / "routes.rou.xml").read_text())
    (user / "routes" / "b.rou.xml").write_text(
        '<routes><vehicle id="extra" type="DEFAULT_VEHTYPE" depart="1"><route edges="C0B0 B0A0"/></vehicle></routes>'
    )
    (user / "stops.add.xml").write_text("<additional/>")
    (user / "my.sumocfg").write_text(
        f"""<configuration>
  <input>
    <net-file value="{grid_dir / 'grid.net.xml'}"/>
    <route-files value="routes/a.rou.xml, routes/b.rou.xml"/>
    <additional-files value="stops.add.xml"/>
  </input>
  <time><step-length value="0.2"/><end value="50"/></time>
  <output><tripinfo-output value="trips.out.xml"/></output>
  <gui_only><gui-settings-file value="missing-view.xml"/><start value="true"/></gui_only>
  <delay value="100"/>
</configuration>
"""
    )
    monkeypatch.chdir(tmp_path)  # relative paths must resolve against the config, not the cwd
    scenario = load_scenario(user / "my.sumocfg")
    assert scenario.step_length_s == pytest.approx(0.2)
    assert {"gui-settings-file", "start", "delay", "tripinfo-output"} <= set(scenario.dropped_options)
    with Simulation(scenario, seed=1) as sim:
        frames = list(sim.run(10.0))
    assert len(frames) == 50
    assert frames[-1].t_s == pytest.approx(10.0)
    assert "extra" in set(np.concatenate([f.ids for f in frames]))
    assert not (user / "trips.out.xml").exists()  # the user's outputs are never written


def test_user_config_without_sites_gets_sites_covering_every_road(grid_dir):
    scenario = load_scenario(grid_dir / "grid.sumocfg", coverage_radius_m=150.0)
    assert len(scenario.edge_sites) >= 2
    assert len(scenario.towns) == 1 and scenario.towns[0].name == "grid"


def test_explicit_sites_override_and_off_map_site_is_refused(grid_dir):
    site = EdgeSite("rsu", 200.0, 200.0)
    assert load_scenario(grid_dir / "grid.sumocfg", edge_sites=(site,)).edge_sites == (site,)
    with pytest.raises(CrchflError, match="off the map"):
        load_scenario(grid_dir / "grid.sumocfg", edge_sites=(EdgeSite("far", 5000.0, 0.0),))


@pytest.mark.parametrize(
    "content, message",
    [
        (None, "not found"),
        ("<configuration><input>", "malformed XML"),
        ('<configuration><input><route-files value="x.rou.xml"/></input></configuration>', "does not exist"),
        ("<configuration><time><end value='5'/></time></configuration>", "no <net-file>"),
    ],
)
def test_bad_configs_give_clear_errors(tmp_path, content, message):
    path = tmp_path / "bad.sumocfg"
    if content is not None:
        path.write_text(content)
    with pytest.raises(CrchflError, match=message):
        load_scenario(path)


def test_unknown_name_lists_builtins():
    with pytest.raises(CrchflError, match="not a built-in scenario"):
        load_scenario("no-such-town")


def test_malformed_net_is_refused(tmp_path):
    (tmp_path / "broken.net.xml").write_text("<net><location convBoundary='a,b'/></net>")
    (tmp_path / "x.sumocfg").write_text(
        '<configuration><input><net-file value="broken.net.xml"/></input></configuration>'
    )
    with pytest.raises(CrchflError, match="malformed SUMO network"):
        load_scenario(tmp_path / "x.sumocfg")


def _farthest(points, sites):
    centres = np.array([(s.x_m, s.y_m) for s in sites])
    return np.sqrt(((points[:, None] - centres[None]) ** 2).sum(-1)).min(axis=1).max()


def test_kmeans_site_placement_covers_all_points_with_few_sites():
    # Points along a 1000 m x 200 m strip: a 250 m radius needs 3 sites, not 1 or 10.
    xs, ys = np.meshgrid(np.linspace(0, 1000, 51), np.linspace(0, 200, 11))
    points = np.stack([xs.ravel(), ys.ravel()], axis=1)
    sites = place_edge_sites(points, 250.0, method="kmeans")
    assert _farthest(points, sites) <= 250.0
    assert len(sites) == 3
    assert place_edge_sites(points, 250.0, method="kmeans") == sites  # deterministic


def test_hexagonal_site_placement_by_hand():
    # A straight 1000 m road on y = 0, radius 100 m: inter-site distance 100 sqrt(3) = 173.2 m, the
    # lattice centred on the road's middle; the row on the road holds every nearest site, at
    # x = 500 + 173.2 k for k = -3 .. 3 (the road's ends 19.6 m from the outer two): 7 sites.
    road = np.stack([np.linspace(0.0, 1000.0, 1001), np.zeros(1001)], axis=1)
    sites = place_edge_sites(road, 100.0)
    assert [round(s.x_m, 1) for s in sites] == [round(500 + 173.2051 * k, 1) for k in range(-3, 4)]
    assert all(s.y_m == 0.0 for s in sites) and [s.name for s in sites][:2] == ["edge00", "edge01"]
    assert _farthest(road, sites) == pytest.approx(173.2051 / 2, abs=0.1)
    # a denser layout, and one too sparse to cover the road
    assert len(place_edge_sites(road, 100.0, inter_site_distance_m=100.0)) == 11
    with pytest.raises(CrchflError, match="inter_site_distance_m.*at most sqrt\\(3\\)"):
        place_edge_sites(road, 100.0, inter_site_distance_m=200.0)


def test_hexagonal_placement_covers_every_point_of_a_scattered_network():
    rng = np.random.default_rng(4)
    points = np.concatenate([rng.uniform(0, 3000, (2000, 2)), rng.uniform(5000, 6000, (500, 2))])
    sites = place_edge_sites(points, 250.0)
    assert _farthest(points, sites) <= 250.0
    # only the sites that cover a road: none over the empty 3 to 5 km gap
    assert not any(3250 < s.x_m < 4750 and 3250 < s.y_m < 4750 for s in sites)
    assert place_edge_sites(points, 250.0) == sites


@pytest.mark.parametrize("name", ["town01", "town02", "paper", "paper_linked"])
def test_each_builtin_runs_and_its_data_vehicles_drive_in_their_town(name):
    scenario = load_scenario(name)
    named = {v: town for town in scenario.towns for v in town.data_vehicles + town.test_vehicles}
    with Simulation(scenario, seed=0) as sim:
        frames = list(sim.run(15.0))
        stats = sim.stats()
    assert stats.teleports == 0 and stats.collisions == 0
    last = frames[-1]
    assert set(named) <= set(last.ids.tolist())
    for vehicle, town in named.items():
        row = last.index_of(vehicle)
        if not vehicle.startswith("link_"):  # link vehicles drive between the towns
            assert town.contains(last.x_m[row], last.y_m[row])
    assert all(scenario.bounds.contains(s.x_m, s.y_m) for s in scenario.edge_sites)


def test_a_folder_laid_out_as_a_builtin_scenario_loads_with_its_towns_and_sites(tmp_path):
    import shutil

    from crchfl_sumo.core.resources import scenarios_dir

    folder = tmp_path / "my_town"
    shutil.copytree(scenarios_dir() / "town01", folder)
    mine, builtin = load_scenario(folder), load_scenario("town01")
    assert mine.name == "my_town"
    assert mine.towns == builtin.towns and mine.edge_sites == builtin.edge_sites
    assert mine.net_path.parent == folder.resolve() and mine.net_path.name == builtin.net_path.name


@pytest.mark.parametrize(
    ("site", "message"),
    [
        (dict(name="a", x_m=1e308, y_m=0.0), r"edge_sites\.a\.x_m: 1e\+308 is not a position"),
        (dict(name="a", x_m=0.0, y_m=float("nan")), r"edge_sites\.a\.y_m: nan is not a position"),
        (dict(name="a", x_m=0.0, y_m=0.0, height_m=1e6), r"height_m must be > 0 and at most 1000 m"),
        (dict(name="a", x_m=0.0, y_m=0.0, height_m=0.0), r"height_m must be > 0"),
    ],
)
def test_edge_sites_out_of_any_network_are_refused(site, message):
    with pytest.raises(CrchflError, match=message):
        EdgeSite(**site)
    assert EdgeSite("a", -9.9e6, 5e6, 999.0).x_m == -9.9e6  # the edges of the range still pass


@pytest.mark.parametrize("step, message", [("0", "step-length"), ("nan", "not a finite time"), ("fast", "not a time"),
                                           ("1e9", "step-length")])
def test_a_bad_step_length_is_refused_by_name(grid_dir, tmp_path, step, message):
    path = tmp_path / "step.sumocfg"
    path.write_text(f'<configuration><input><net-file value="{grid_dir / "grid.net.xml"}"/></input>'
                    f'<time><step-length value="{step}"/></time></configuration>')
    with pytest.raises(CrchflError, match=message):
        load_scenario(path)


def test_a_loop_of_symbolic_links_is_refused_by_name(tmp_path):
    (tmp_path / "a.sumocfg").symlink_to(tmp_path / "b.sumocfg")
    (tmp_path / "b.sumocfg").symlink_to(tmp_path / "a.sumocfg")
    with pytest.raises(CrchflError, match="a.sumocfg: cannot be followed"):
        load_scenario(tmp_path / "a.sumocfg")


def test_a_traci_server_port_is_dropped_and_the_simulation_finishes(grid_dir, tmp_path):
    # with <remote-port> sumo would wait for a TraCI client for ever; in a child process with a deadline
    path = tmp_path / "server.sumocfg"
    path.write_text(f'<configuration><input><net-file value="{grid_dir / "grid.net.xml"}"/>'
                    f'<route-files value="{grid_dir / "routes.rou.xml"}"/></input>'
                    '<traci_server><remote-port value="8873"/><num-clients value="2"/></traci_server>'
                    '<time><step-length value="0.5"/></time></configuration>')
    assert {"remote-port", "num-clients"} <= set(load_scenario(path).dropped_options)
    done = subprocess.run(
        [sys.executable, "-m", "crchfl_sumo.cli", "simulate", str(path), "--duration-s", "5", "--out",
         str(tmp_path / "out")], capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "out" / "summary.json").is_file()


def test_sumo_times_read_as_sumolib_reads_them_and_bad_ones_are_refused(tmp_path):
    from crchfl_sumo.sumo.sumocfg import sumo_time_s

    cfg = tmp_path / "a.sumocfg"
    for text, seconds in (("90", 90.0), ("0:01:30", 90.0), ("1:00:00", 3600.0), ("1:00:00:10", 86410.0), ("0.5", 0.5)):
        assert sumo_time_s(text, cfg, "end") == seconds
    for text in ("soon", "", "1:2:3:4:5", "nan", "inf", "1:x:00", "1:30"):  # SUMO's forms: s, h:m:s, d:h:m:s
        with pytest.raises(CrchflError, match="<end>"):
            sumo_time_s(text, cfg, "end")
