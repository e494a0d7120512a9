"""`crchfl-sumo sweep`: parameters, grid expansion, resume of an interrupted sweep; the [sumo] settings."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from crchfl_sumo.cli import main
from crchfl_sumo.core.backend import BackendConfig
from crchfl_sumo.core.config import from_mapping, toml_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.manifest import Manifest
from crchfl_sumo.data.shards import DatasetWriter, ShardData
from crchfl_sumo.federation.run import run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.links.clock import ScriptedClock, Segment
from crchfl_sumo.studies.sweep import expand_grid, parse_param, point_name, run_sweep, split_values
from crchfl_sumo.sumo.scenario import SumoConfig, configured_scenario
from crchfl_sumo.sumo.simulation import Simulation

from helpers import PAPER_VEHICLES, Killed, kill_after, result_files, run_config, write_dataset

# ------------------------------------------------------------------ parameters and the grid


def test_param_values_are_toml_values_split_on_top_level_commas():
    assert parse_param("sumo.scale=0.5,1,2").values == (0.5, 1, 2)
    assert parse_param("federation.scheme=hfl,\"sfl\"").values == ("hfl", "sfl")
    assert parse_param("federation.deadline_s=inf,30.5").values == (math.inf, 30.5)
    sites = parse_param('sumo.edge_sites=[{name = "a", x_m = 1.0, y_m = 2.0}],[{name = "b", x_m = 3, y_m = 4}, {name = "c", x_m = 5, y_m = 6}]')
    assert [len(v) for v in sites.values] == [1, 2] and sites.values[1][1]["name"] == "c"
    assert split_values('"a,b", [1, 2], {x = "}"}') == ['"a,b"', "[1, 2]", '{x = "}"}']
    for bad, message in [
        ("sumo.scale", "PATH=V1,V2"),
        ("sumo..scale=1", "PATH=V1,V2"),
        ("backend.kind=ray", "--backend"),
        ("sumo.scale=", "no values"),
        ("sumo.scale=1,1", "twice"),
    ]:
        with pytest.raises(CrchflError, match=message):
            parse_param(bad)


def test_grid_is_every_combination_first_parameter_slowest(tmp_path):
    base = {"dataset": "d", "federation": {"scheme": "hfl"}, "clock": {"kind": "constant"}}
    params = [parse_param("federation.edge_interval=1,2"), parse_param("ledger.budget_gb=5,10,20")]
    points = expand_grid(base, params)
    assert [(p.values["federation.edge_interval"], p.values["ledger.budget_gb"]) for p in points] == [
        (1, 5), (1, 10), (1, 20), (2, 5), (2, 10), (2, 20)
    ]
    assert points[4].name == "federation.edge_interval=2__ledger.budget_gb=10"
    assert points[4].mapping["federation"] == {"scheme": "hfl", "edge_interval": 2}
    assert points[4].mapping["ledger"] == {"budget_gb": 10}
    assert base["federation"] == {"scheme": "hfl"}  # the base is not changed
    assert len({p.name for p in points}) == 6


def test_grid_rejects_unknown_paths_and_bad_values_naming_the_param():
    base = {"clock": {"kind": "sumo"}}
    with pytest.raises(CrchflError, match=r"--param federation.deadlin_s=1.*unknown key.*'deadlin_s'"):
        expand_grid(base, [parse_param("federation.deadlin_s=1")])
    with pytest.raises(CrchflError, match=r"--param sumo.scale=-1.*sumo.scale"):
        expand_grid(base, [parse_param("sumo.scale=1,-1")])
    with pytest.raises(CrchflError, match="'scenario' is a value, not a table"):
        expand_grid({**base, "scenario": "paper"}, [parse_param("scenario.name=x")])
    with pytest.raises(CrchflError, match=r"--param scenario.name=x: config.scenario: expected a string"):
        expand_grid(base, [parse_param("scenario.name=x")])
    with pytest.raises(CrchflError, match="swept twice"):
        expand_grid(base, [parse_param("sumo.scale=1"), parse_param("sumo.scale=2")])


def test_point_names_are_stable_and_lists_are_hashed():
    a = point_name({"sumo.scale": 0.5, "federation.scheme": "hfl"})
    assert a == "sumo.scale=0.5__federation.scheme=hfl" == point_name({"sumo.scale": 0.5, "federation.scheme": "hfl"})
    sites = point_name({"sumo.edge_sites": [{"name": "a", "x_m": 1.0, "y_m": 2.0}]})
    assert sites.startswith("sumo.edge_sites=") and len(sites) == len("sumo.edge_sites=") + 10
    assert sites != point_name({"sumo.edge_sites": [{"name": "a", "x_m": 1.0, "y_m": 3.0}]})
    assert point_name({"federation.deadline_s": math.inf}) == "federation.deadline_s=inf"


# ------------------------------------------------------------------ running and resuming


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data"), PAPER_VEHICLES)


def _base(dataset: Path) -> dict:
    return run_config(dataset, scheme="hfl", cloud_interval=1, cloud_rounds=2)


def test_interrupted_sweep_resumes_without_redoing_finished_runs(tmp_path, dataset):
    base = _base(dataset)
    params = [parse_param("federation.edge_interval=1,2")]
    points = expand_grid(base, params)
    out = tmp_path / "sweep"
    runs = out / "runs"
    # before the "interruption": point 0 finished, point 1 killed after its first step
    first = from_mapping(RunConfig, points[0].mapping)
    run_federation_dir(first, read_inputs(first), runs / points[0].name, config_text=toml_text(points[0].mapping))
    second = from_mapping(RunConfig, points[1].mapping)
    with pytest.raises(Killed):
        run_federation_dir(second, read_inputs(second), runs / points[1].name, after_checkpoint=kill_after(1),
                           config_text=toml_text(points[1].mapping))
    finished_mtime = (runs / points[0].name / "summary.json").stat().st_mtime_ns
    rows = run_sweep(base, params, out, BackendConfig(num_cpus=2))
    assert (runs / points[0].name / "summary.json").stat().st_mtime_ns == finished_mtime  # not redone
    # the killed run ends like an uninterrupted one
    run_federation_dir(second, read_inputs(second), tmp_path / "whole")
    assert result_files(runs / points[1].name) == result_files(tmp_path / "whole")
    assert [r["federation.edge_interval"] for r in rows] == [1, 2]
    for row, point in zip(rows, points):
        summary = json.loads((runs / point.name / "summary.json").read_text())
        assert row["cloud_rounds"] == summary["cloud_rounds"] == 2
        assert row["final_accuracy"] == summary["final_accuracy"]
        straight = summary["baselines"]["always_straight"]  # what the accuracies read against, in every row
        assert (row["always_straight_accuracy"], row["always_straight_balanced_accuracy"]) == (
            straight["accuracy"], straight["balanced_accuracy"])
        assert row["wireless_bytes"] == summary["bytes_by_link"]["wireless"] > 0
        assert row["handovers"] == 0  # the constant clock has no mobility
        assert row["relayed_transfers"] == row["relay_bytes"] == row["downloads_failed"] == 0
        # each point's folder holds its config, runnable on its own
        assert tomllib.loads((runs / point.name / "config.toml").read_text())["federation"]["edge_interval"] == row[
            "federation.edge_interval"
        ]
    with open(out / "results.csv", newline="") as handle:
        table = list(csv.DictReader(handle))
    assert [t["point"] for t in table] == [p.name for p in points]
    assert [float(t["always_straight_accuracy"]) for t in table] == [r["always_straight_accuracy"] for r in rows]
    assert (out / "results.md").read_text().count("\n") == 2 + len(points)
    assert (out / "plots" / "federation.edge_interval.png").stat().st_size > 0
    # a second rerun runs nothing: every folder is untouched
    before = {p.name: (runs / p.name / "summary.json").stat().st_mtime_ns for p in points}
    run_sweep(base, params, out, BackendConfig(num_cpus=2))
    assert {p.name: (runs / p.name / "summary.json").stat().st_mtime_ns for p in points} == before
    # a point finished by a version that stored train.precision undecided ("auto") is still this sweep's
    stored_path = runs / points[0].name / "config.json"
    stored = json.loads(stored_path.read_text())
    decided_here = stored["config"]["train"]["precision"]
    stored["config"]["train"]["precision"] = "auto"
    stored_path.write_text(json.dumps(stored))
    run_sweep(base, params, out, BackendConfig(num_cpus=2))
    assert {p.name: (runs / p.name / "summary.json").stat().st_mtime_ns for p in points} == before
    # and so is one whose "auto" was decided otherwise where it ran (a Ray worker with another CPU)
    stored["config"]["train"]["precision"] = "fp32" if decided_here == "bf16" else "bf16"
    stored_path.write_text(json.dumps(stored))
    run_sweep(base, params, out, BackendConfig(num_cpus=2))
    assert {p.name: (runs / p.name / "summary.json").stat().st_mtime_ns for p in points} == before
    # the same folder with another base config: its finished runs are not taken for this sweep's
    other = {**base, "ledger": {"nominal_model_mb": 20.0}}
    with pytest.raises(CrchflError, match=r"other settings .*differs in ledger\.nominal_model_mb"):
        run_sweep(other, params, out, BackendConfig(num_cpus=2))


def test_sweep_command_line_two_parameters(tmp_path, dataset, capsys):
    config = tmp_path / "base.toml"
    config.write_text(toml_text(_base(dataset)))
    argv = ["sweep", str(config), "--param", "ledger.budget_gb=0.05,20", "--param", "federation.scheme=hfl",
            "--out", str(tmp_path / "s")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "2 runs" in out and "| ledger.budget_gb | federation.scheme |" in out
    with open(tmp_path / "s" / "results.csv", newline="") as handle:
        table = list(csv.DictReader(handle))
    rounds = {(t["ledger.budget_gb"], t["federation.scheme"]): (int(t["cloud_rounds"]), t["stop_reason"]) for t in table}
    # 0.05 GB cannot carry the 10 MB models of 5 vehicles for two rounds: the budget stops that run
    assert rounds[("20", "hfl")] == (2, "cloud_rounds")
    assert rounds[("0.05", "hfl")][1] == "budget" and rounds[("0.05", "hfl")][0] < 2
    # a figure per swept key; the scheme, given one value, is a fixed setting without one
    assert sorted(p.name for p in (tmp_path / "s" / "plots").iterdir()) == ["ledger.budget_gb.png"]
    assert main(["sweep", str(config), "--param", "federation.edge_intervall=1", "--out", str(tmp_path / "x")]) == 2
    assert "--param federation.edge_intervall" in capsys.readouterr().err


# ------------------------------------------------------------------ [sumo] settings


def test_sumo_config_validation():
    for bad, key in [({"scale": 0}, "sumo.scale"), ({"speed_limit_mps": -1.0}, "sumo.speed_limit_mps"),
                     ({"edge_site_count": -1}, "sumo.edge_site_count")]:
        with pytest.raises(CrchflError, match=key):
            SumoConfig(**bad)
    with pytest.raises(CrchflError, match="not both"):
        from_mapping(SumoConfig, {"edge_site_count": 2, "edge_sites": [{"name": "a", "x_m": 1.0, "y_m": 1.0}]})
    with pytest.raises(CrchflError, match=r"\[sumo\]"):
        from_mapping(RunConfig, {"clock": {"kind": "constant"}, "sumo": {"scale": 2.0}})


def _count_after(scenario, steps: int) -> tuple[int, set, float]:
    with Simulation(scenario, seed=0, watch=(), keep_demand=[v for v, _, _ in PAPER_VEHICLES]) as sim:
        top = 0.0
        for _ in range(steps):
            frame = sim.step()
            top = max(top, float(frame.speed_mps.max(initial=0.0)))
    return len(frame.ids), {str(v) for v in frame.ids}, top


def test_traffic_scale_and_speed_cap_change_sumo_but_keep_the_data_vehicles():
    steps = 240  # 60 s
    counts = {}
    for scale in (0.5, 1.0, 2.0):
        n, ids, _ = _count_after(configured_scenario("paper", SumoConfig(scale=scale), 250.0), steps)
        counts[scale] = n
        assert {v for v, _, _ in PAPER_VEHICLES} <= ids
    assert counts[0.5] < counts[1.0] < counts[2.0]
    _, _, free = _count_after(configured_scenario("paper", SumoConfig(), 250.0), steps)
    _, _, capped = _count_after(configured_scenario("paper", SumoConfig(speed_limit_mps=4.0), 250.0), steps)
    assert free > 4.5 and capped <= 4.0 + 1e-9


def test_edge_site_count_places_that_many_sites_on_the_map():
    scenario = configured_scenario("paper", SumoConfig(edge_site_count=3), 250.0)
    assert [s.name for s in scenario.edge_sites] == ["edge00", "edge01", "edge02"]
    assert all(scenario.bounds.contains(s.x_m, s.y_m) for s in scenario.edge_sites)
    assert configured_scenario("paper", SumoConfig(edge_site_count=3), 250.0).edge_sites == scenario.edge_sites


def _positioned_dataset(root: Path, positions: dict[str, tuple[float, float]]) -> Path:
    """write_dataset's tiny data, with each vehicle's samples at a given place (the first one there)."""
    rng = np.random.default_rng(0)
    header = Manifest(scenario="paper", seed=0, sample_period_s=0.25, image_height=48, image_width=64, compression="none")
    writer = DatasetWriter(root, header)

    def data(n, x, y):
        return ShardData(
            rng.integers(0, 256, (n, 4, 48, 64, 3), dtype=np.uint8), rng.random((n, 3), dtype=np.float32),
            rng.integers(0, 7, n), rng.integers(0, 4, n), rng.uniform(0, 14, n).astype(np.float32),
            rng.uniform(0, 14, n).astype(np.float32), np.zeros((n, 3), np.float32), np.arange(n) * 0.25,
            x + 100.0 * np.arange(n), np.full(n, y), np.zeros(n),
        )

    for i, (vehicle, town, edge) in enumerate(PAPER_VEHICLES):
        writer.add(f"{town}-train-{i}.h5", data(2, *positions[vehicle]), vehicle=vehicle, town=town, edge=edge, split="train")
    writer.add("town01-test-0.h5", data(2, 0.0, 0.0), vehicle="t01_test_0", town="town01", edge="edge01", split="test")
    return root


def test_other_sites_than_the_data_sets_give_each_vehicle_its_nearest_site(tmp_path):
    positions = {v: ((50.0, 60.0) if town == "town01" else (650.0, 150.0)) for v, town, _ in PAPER_VEHICLES}
    positions["t01_data_1"] = (690.0, 200.0)  # recorded in town01's shard, but first seen near the east site
    data = _positioned_dataset(tmp_path / "data", positions)
    sites = [{"name": "east", "x_m": 700.0, "y_m": 200.0}, {"name": "west", "x_m": 100.0, "y_m": 100.0}]
    mapping = {**run_config(data), "clock": {"kind": "sumo"}, "sumo": {"edge_sites": sites}}
    inputs = read_inputs(from_mapping(RunConfig, mapping))
    assert inputs.edges == ("east", "west")
    assert inputs.home_site == {"t01_data_0": 1, "t01_data_1": 0, "t02_data_0": 0, "t02_data_1": 0, "t02_data_2": 0}
    # without [sumo] sites the data set's recorded edges hold
    plain = read_inputs(from_mapping(RunConfig, {**run_config(data), "clock": {"kind": "sumo"}}))
    assert plain.home_site == {"t01_data_0": 0, "t01_data_1": 0, "t02_data_0": 1, "t02_data_1": 1, "t02_data_2": 1}


def test_scripted_clock_counts_site_to_site_handovers():
    clock = ScriptedClock({
        "a": [Segment(0.0, 0, 1e6), Segment(10.0, 1, 1e6), Segment(20.0, -1, 0.0), Segment(30.0, 0, 1e6)],
        "b": [Segment(0.0, 1, 1e6), Segment(5.0, 0, 1e6)],
    })
    # a: 0->1 at 10 counts; 1->none->0 are losses and gains of coverage, not handovers; b: 1->0 at 5
    assert [clock.handovers(t) for t in (4.0, 5.0, 10.0, 35.0)] == [0, 1, 2, 2]


@pytest.mark.slow
def test_sumo_clock_sweep_over_site_counts_reports_handovers(tmp_path, dataset):
    base = run_config(dataset, scheme="hfl", cloud_rounds=1, compute_s_per_sample=5.0, deadline_s=120.0)
    base["clock"] = {"kind": "sumo"}
    base["mobility"] = {"coverage_radius_m": 150.0}
    [row] = run_sweep(base, [parse_param("sumo.edge_site_count=6")], tmp_path / "s", BackendConfig(num_cpus=2))
    resolved = json.loads((tmp_path / "s" / "runs" / row["point"] / "config.json").read_text())
    assert resolved["edges"] == [f"edge{i:02d}" for i in range(6)]
    assert resolved["config"]["sumo"]["edge_site_count"] == 6
    assert row["cloud_rounds"] == 1
    assert isinstance(row["handovers"], int) and row["handovers"] > 0  # six small cells: moving vehicles change cells


def test_a_sweep_with_seeds_gives_each_point_its_means_and_intervals(tmp_path, dataset):
    from scipy import stats

    out = tmp_path / "sweep"
    rows = run_sweep(_base(dataset), [parse_param("federation.edge_interval=1,2")], out, BackendConfig(num_cpus=2),
                     seeds=2)
    assert [r["federation.edge_interval"] for r in rows] == [1, 2] and all(r["seeds"] == 2 for r in rows)
    for row in rows:
        runs = [json.loads((out / "runs" / row["point"] / f"seed-{s}" / "summary.json").read_text()) for s in (0, 1)]
        configs = [json.loads((out / "runs" / row["point"] / f"seed-{s}" / "config.json").read_text()) for s in (0, 1)]
        assert [c["config"]["federation"]["seed"] for c in configs] == [0, 1]
        values = [r["balanced_accuracy"] for r in runs]
        assert row["balanced_accuracy"] == pytest.approx(sum(values) / 2)
        spread = stats.sem(values)
        lo, hi = stats.t.interval(0.95, 1, loc=sum(values) / 2, scale=spread) if spread else (values[0], values[0])
        assert (row["balanced_accuracy_ci_lo"], row["balanced_accuracy_ci_hi"]) == (pytest.approx(lo), pytest.approx(hi))
        assert row["cloud_rounds"] == sum(r["cloud_rounds"] for r in runs) / 2
        # both seeds test on the same data: the always-straight figures are that test set's
        assert row["always_straight_accuracy"] == pytest.approx(runs[0]["baselines"]["always_straight"]["accuracy"])
    with open(out / "results.csv", newline="") as handle:
        header = next(csv.reader(handle))
    assert header[:8] == ["point", "federation.edge_interval", "seeds", "balanced_accuracy_ci_lo",
                          "balanced_accuracy_ci_hi", "best_accuracy_ci_lo", "best_accuracy_ci_hi", "best_accuracy"]
    assert header[9:12] == ["final_accuracy", "always_straight_accuracy", "always_straight_balanced_accuracy"]
