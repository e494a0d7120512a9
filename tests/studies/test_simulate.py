import csv
import json
import re

import numpy as np
import pytest

from crchfl_sumo.cli import main
from crchfl_sumo.core.resources import scenarios_dir
from crchfl_sumo.links.mobility import NO_SITE, LinkModel, MobilityConfig
from crchfl_sumo.links.snapshots import Handover
from crchfl_sumo.studies.simulate import SimulateConfig, Trace, simulate, summarize
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation
from crchfl_sumo.sumo.sites import EdgeSite


def _trace(site, rate, handovers=()):
    n = len(site)
    return Trace(
        t_s=np.arange(n, dtype=float),
        vehicle=np.array(["a", "b"] * (n // 2)),
        x_m=np.zeros(n),
        y_m=np.zeros(n),
        speed_mps=np.zeros(n),
        site=np.array(site),
        rate_bps=np.array(rate, dtype=float),
        handovers=tuple(handovers),
        steps=n // 2,
        teleports=0,
        collisions=0,
    )


def test_summary_figures_by_hand(grid_dir):
    scenario = load_scenario(grid_dir / "grid.sumocfg", edge_sites=(EdgeSite("e0", 0, 0), EdgeSite("e1", 400, 400)))
    trace = _trace(
        [0, 1, 0, -1],
        [4e6, 2e6, 6e6, 0.0],
        [Handover(1.0, "a", -1, 0), Handover(2.0, "b", 0, 1), Handover(3.0, "b", 1, -1)],
    )
    summary = summarize(trace, scenario, 2.0, SimulateConfig())
    assert summary["vehicles"] == 2
    assert summary["coverage_fraction"] == pytest.approx(0.75)  # 3 of 4 samples served
    assert summary["mean_rate_bps"] == pytest.approx(4e6)  # (4 + 2 + 6) / 3 over served samples
    assert summary["handovers"] == 1  # only e0 -> e1; attach and loss are coverage changes
    assert summary["coverage_changes"] == 2
    assert summary["ping_pongs"] == 0
    assert summary["per_edge"]["e0"] == {"samples": 2, "mean_rate_bps": pytest.approx(5e6)}


def test_simulate_gives_what_full_frames_and_the_link_model_give_on_town01():
    """simulate reads lean frames (no lanes, signals ahead or signal states); its positions, speeds,
    association, rates and handovers must equal those of full frames (as simulate read them before:
    every column, the data vehicles watched) fed to the link model, to the last bit."""
    corners = [(60.0, 60.0), (330.0, 60.0), (60.0, 270.0), (330.0, 270.0)]
    cfg = SimulateConfig(
        seed=2,
        edge_sites=tuple(EdgeSite(f"e{i}", x, y) for i, (x, y) in enumerate(corners)),
        mobility=MobilityConfig(coverage_radius_m=150.0),  # cells overlap and leave a gap: handovers and losses
    )
    scenario = load_scenario("town01", cfg.edge_sites, cfg.mobility.coverage_radius_m)
    trace = simulate(scenario, 120.0, cfg)

    links = LinkModel(scenario.edge_sites, cfg.channel, cfg.mobility, seed=cfg.seed)
    watched = [v for town in scenario.towns for v in town.data_vehicles]
    with Simulation(scenario, seed=cfg.seed, watch=watched) as sim:
        frames = list(sim.run(120.0))
    snapshots = [links.step(frame) for frame in frames]
    assert trace.steps == len(frames) == 480
    assert np.array_equal(trace.t_s, np.concatenate([np.full(len(f), f.t_s) for f in frames]))
    assert np.array_equal(trace.vehicle, np.concatenate([f.ids for f in frames]))
    for column in ("x_m", "y_m", "speed_mps"):
        assert np.array_equal(getattr(trace, column), np.concatenate([getattr(f, column) for f in frames]))
    assert np.array_equal(trace.site, np.concatenate([s.site for s in snapshots]))
    assert np.array_equal(trace.rate_bps, np.concatenate([s.rate_bps for s in snapshots]))
    assert trace.handovers == tuple(h for s in snapshots for h in s.handovers)
    between_sites = [h for h in trace.handovers if NO_SITE not in (h.from_site, h.to_site)]
    assert len(between_sites) >= 3 and any(h.to_site == NO_SITE for h in trace.handovers)


def test_simulate_command_writes_consistent_outputs(tmp_path):
    out = tmp_path / "run"
    assert main(["simulate", "town02", "--duration-s", "20", "--out", str(out), "--seed", "3"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for key in ("vehicles", "steps", "handovers", "mean_rate_bps", "coverage_fraction"):
        assert key in summary
    assert summary["steps"] == 80  # 20 s at 0.25 s
    assert summary["teleports"] == 0 and summary["collisions"] == 0
    with open(out / "trace.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len({r["vehicle"] for r in rows}) == summary["vehicles"]
    assert {r["edge"] for r in rows} <= {"edge02", ""}
    served = [float(r["rate_bps"]) for r in rows if r["edge"]]
    assert sum(1 for r in rows if r["edge"]) / len(rows) == pytest.approx(summary["coverage_fraction"])
    assert np.mean(served) == pytest.approx(summary["mean_rate_bps"], rel=1e-3)
    assert (out / "map.png").stat().st_size > 10_000 and (out / "rate.png").stat().st_size > 10_000
    # Same seed, same figures.
    again = tmp_path / "again"
    assert main(["simulate", "town02", "--duration-s", "20", "--out", str(again), "--seed", "3"]) == 0
    assert (again / "trace.csv").read_text() == (out / "trace.csv").read_text()


def test_simulate_refuses_to_overwrite_other_settings_unless_told(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", "town02", "--duration-s", "2", "--out", str(out), "--seed", "3"]) == 0
    first = (out / "trace.csv").read_text()
    assert main(["simulate", "town02", "--duration-s", "2", "--out", str(out), "--seed", "4"]) == 2
    err = capsys.readouterr().err
    assert "simulate --out" in err and "with other settings" in err and "--overwrite" in err
    assert (out / "trace.csv").read_text() == first  # nothing lost
    assert main(["simulate", "town02", "--duration-s", "2", "--out", str(out), "--seed", "3"]) == 0  # a rerun
    assert main(["simulate", "town02", "--duration-s", "2", "--out", str(out), "--seed", "4", "--overwrite"]) == 0


@pytest.mark.parametrize(
    "config, message",
    [
        ("seed = 1\nsed = 2\n", "unknown key(s) 'sed'"),
        ("[mobility]\ncoverage_radius = 5\n", "mobility: unknown key(s) 'coverage_radius'"),
        ("[mobility]\ncoverage_radius_m = -5.0\n", "coverage_radius_m must be > 0"),
        ('[[edge_sites]]\nname = "far"\nx_m = 1e5\ny_m = 0.0\n', "off the map"),
        ("seed = [\n", "malformed TOML"),
    ],
)
def test_bad_config_exits_2_with_named_key_and_writes_nothing(tmp_path, capsys, config, message):
    path = tmp_path / "bad.toml"
    path.write_text(config)
    out = tmp_path / "out"
    code = main(["simulate", "town01", "--duration-s", "5", "--out", str(out), "--config", str(path)])
    assert code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()


def test_a_sumocfg_with_an_end_runs_its_own_length_unless_told(tmp_path, capsys):
    town = scenarios_dir() / "town02"
    net, routes = town / "town02.net.xml", f"{town / 'town02.ego.rou.xml'},{town / 'town02.bg.rou.xml'}"
    config = tmp_path / "timed.sumocfg"
    config.write_text(
        f'<configuration><input><net-file value="{net}"/><route-files value="{routes}"/>'
        f'<additional-files value="{town / "vtypes.add.xml"}"/></input>'
        '<time><begin value="5"/><end value="0:0:17.5"/><step-length value="0.25"/></time></configuration>'
    )
    assert main(["simulate", str(config), "--out", str(tmp_path / "own")]) == 0
    assert json.loads((tmp_path / "own" / "summary.json").read_text())["duration_s"] == 12.5
    assert json.loads((tmp_path / "own" / "summary.json").read_text())["steps"] == 50  # 12.5 s at 0.25 s
    assert main(["simulate", str(config), "--duration-s", "2", "--out", str(tmp_path / "told")]) == 0
    assert json.loads((tmp_path / "told" / "summary.json").read_text())["steps"] == 8
    config.write_text(config.read_text().replace('"0:0:17.5"', '"soon"'))
    assert main(["simulate", str(config), "--out", str(tmp_path / "bad")]) == 2
    assert "timed.sumocfg: <end> 'soon' is not a time; give seconds" in capsys.readouterr().err
    config.write_text(config.read_text().replace('"soon"', '"5"'))
    assert main(["simulate", str(config), "--out", str(tmp_path / "bad")]) == 2
    assert "<end> is not after <begin>" in capsys.readouterr().err


def test_missing_config_and_negative_duration_exit_2(tmp_path, capsys):
    assert main(["simulate", "town01", "--out", str(tmp_path / "o"), "--config", str(tmp_path / "none.toml")]) == 2
    assert "config file not found" in capsys.readouterr().err
    assert main(["simulate", "town01", "--duration-s", "-1", "--out", str(tmp_path / "o")]) == 2
    assert "simulate --duration-s: -1 is out of range; give simulated seconds in (0, 86400]" in capsys.readouterr().err
    # shorter than one step of the town (0.25 s): refused before anything is written
    assert main(["simulate", "town01", "--duration-s", "0.1", "--out", str(tmp_path / "short")]) == 2
    assert "shorter than one step of town01 (0.25 s)" in capsys.readouterr().err
    assert not (tmp_path / "short").exists()


def test_plan_json_has_the_four_hyper_parameters(capsys):
    assert main(["plan", "--budget-gb", "20", "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    for key in ("pretrain_batch", "edge_interval", "cloud_interval", "cloud_rounds", "objective", "stage_bytes"):
        assert key in plan
    assert sum(plan["stage_bytes"].values()) <= 20 * 1024**3


def test_plan_with_too_small_budget_exits_2(capsys):
    assert main(["plan", "--budget-gb", "0.1"]) == 2
    assert "budget_gb" in capsys.readouterr().err


def test_simulate_writes_sumos_own_fcd_with_every_vehicle_of_the_trace(tmp_path, capsys):
    import csv

    import sumolib

    from crchfl_sumo.cli import main

    out = tmp_path / "out"
    assert main(["simulate", "town01", "--duration-s", "30", "--sumo-output", "fcd,tripinfo", "--out", str(out)]) == 0
    fcd = {v.id for v in sumolib.xml.parse_fast(str(out / "sumo-fcd.xml"), "vehicle", ["id"])}
    with open(out / "trace.csv", newline="") as handle:
        traced = {row["vehicle"] for row in csv.DictReader(handle)}
    assert fcd == traced and len(fcd) > 10
    assert (out / "sumo-tripinfo.xml").is_file() and not list(out.glob(".*.partial"))  # renamed once SUMO closed it
    capsys.readouterr()
    assert main(["simulate", "town01", "--duration-s", "5", "--sumo-output", "fcd,emissions", "--out",
                 str(tmp_path / "other")]) == 2
    assert "--sumo-output: emissions unknown; choose from fcd, tripinfo, summary" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


def test_simulate_a_bare_network_with_route_files_and_no_sumocfg(tmp_path, grid_dir, capsys):
    import gzip
    import json

    from crchfl_sumo.cli import main

    packed = tmp_path / "grid.net.xml.gz"
    packed.write_bytes(gzip.compress((grid_dir / "grid.net.xml").read_bytes()))
    out = tmp_path / "out"
    assert main(["simulate", "--net", str(packed), "--routes", str(grid_dir / "routes.rou.xml"), "--duration-s", "30",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenario"] == "grid" and (out / "grid.sumocfg").is_file()
    # the flows of routes.rou.xml drive, beside the 6 vehicles a scenario naming none gets added
    assert summary["vehicles"] > 6
    capsys.readouterr()
    for argv, message in (
        (["simulate", "town01", "--net", str(packed)], "give a SCENARIO or --net"),
        (["simulate", "--net", str(tmp_path / "none.net.xml")], "--net .*none.net.xml: no such file"),
        (["simulate", "town01", "--routes", "r.rou.xml"], "route files go with --net"),
    ):
        assert main([*argv, "--duration-s", "5", "--out", str(tmp_path / "refused")]) == 2
        assert re.search(message, capsys.readouterr().err)
