"""`crchfl-sumo mobility-study`: the preset, the one-factor-at-a-time plan, the report, a tiny real study."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from crchfl_sumo.cli import main
from crchfl_sumo.core.backend import BackendConfig
from crchfl_sumo.core.config import read_toml
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.studies.mobility_study import BASELINE, StudyPlan, Study, StudyData, parse_study, run_study, study_plan
from crchfl_sumo.studies.mobility_study_report import markdown_table, study_rows, write_report
from crchfl_sumo.studies.sweep import Point

from helpers import PAPER_VEHICLES, run_config, write_dataset

# the repository's presets (not the installed package's: the tests check this checkout)
PRESETS = Path(__file__).resolve().parents[2] / "scenarios" / "experiments"

BASE = {
    "scenario": "paper_linked",
    "federation": {"scheme": "hfl", "handover_policy": "new_edge", "deadline_s": 240.0},
    "clock": {"kind": "sumo"},
}


def _raw(*factors: dict, **extra) -> dict:
    return {"data": {"scenario": "paper_linked", "train_samples": 2, "test_samples": 2}, "run": BASE,
            "factor": list(factors), **extra}


def _study(*factors: dict) -> Study:
    return parse_study(_raw(*factors), "study.toml")


# ------------------------------------------------------------------ the plan


def test_plan_is_the_baseline_and_one_factor_changed_at_a_time():
    study = _study(
        {"name": "speed", "key": "sumo.speed_limit_mps", "values": [8.0, float("inf")], "labels": ["8", "none"]},
        {"name": "density", "key": "sumo.scale", "values": [0.5, 1.0, 2.0]},
        {"name": "policy", "key": "federation.handover_policy", "values": ["new_edge", "miss"]},
    )
    plan = study_plan(study.base, study.factors)
    names = [p.name for p in plan.points]
    # values equal to the baseline's settings (no cap, scale 1, new_edge) are the baseline run itself
    assert names == [BASELINE, "sumo.speed_limit_mps=8.0", "sumo.scale=0.5", "sumo.scale=2.0",
                     "federation.handover_policy=miss"]
    assert plan.factor_points == {
        "speed": ("sumo.speed_limit_mps=8.0", BASELINE),
        "density": ("sumo.scale=0.5", BASELINE, "sumo.scale=2.0"),
        "policy": (BASELINE, "federation.handover_policy=miss"),
    }
    points = {p.name: p for p in plan.points}
    assert points[BASELINE].mapping == BASE
    # each point changes only its factor's key; the rest is the baseline's
    assert points["sumo.scale=2.0"].mapping == {**BASE, "sumo": {"scale": 2.0}}
    assert points["federation.handover_policy=miss"].mapping["federation"] == {**BASE["federation"], "handover_policy": "miss"}
    assert points["federation.handover_policy=miss"].values == {"federation.handover_policy": "miss"}
    assert study.factors[0].labels == ("8", "none") and study.factors[1].labels == ("0.5", "1.0", "2.0")


def test_shipped_presets_parse_and_plan():
    for name, runs in [("mobility_quick", 13), ("mobility_full", 21)]:
        path = PRESETS / f"{name}.toml"
        study = parse_study(read_toml(path), str(path))
        plan = study_plan({**study.base, "dataset": "d"}, study.factors, str(path))
        assert len(plan.points) == runs and plan.points[0].name == BASELINE
        keys = {f.param.path for f in study.factors}
        assert {"sumo.speed_limit_mps", "sumo.scale", "sumo.edge_site_count", "sumo.edge_sites",
                "federation.handover_policy"} <= keys
        assert all(len(f.param.values) >= 3 for f in study.factors)


def test_bad_factor_key_or_value_names_the_factor():
    study = _study({"name": "speed", "key": "sumo.sped_limit_mps", "values": [8.0]})
    with pytest.raises(CrchflError, match=r"factor 'speed': sumo.sped_limit_mps=8.0.*unknown key.*'sped_limit_mps'"):
        study_plan(study.base, study.factors)
    study = _study({"name": "density", "key": "sumo.scale", "values": [1.0, -1.0]})
    with pytest.raises(CrchflError, match=r"factor 'density': sumo.scale=-1.0.*sumo.scale"):
        study_plan(study.base, study.factors)


@pytest.mark.parametrize("raw, message", [
    (_raw({"key": "sumo.scale", "values": [1.0]}, extra=1), r"unknown key 'extra'"),
    (_raw({"key": "sumo.scale", "value": [1.0]}), r"\[\[factor\]\] 1: unknown key 'value'"),
    (_raw({"key": "sumo.scale", "values": []}), r"\[\[factor\]\] 1: give key .* non-empty list of values"),
    (_raw({"key": "sumo.scale", "values": [1.0, 2.0], "labels": ["a"]}), r"1 labels for 2 values"),
    (_raw(), r"no \[\[factor\]\] tables"),
    ({**_raw({"key": "sumo.scale", "values": [1.0]}), "run": {**BASE, "backend": {}}}, r"\[run\]: leave out 'backend'"),
    ({**_raw({"key": "sumo.scale", "values": [1.0]}), "data": {"scenario": "paper"}}, r"\[data\]: 'train_samples' is missing"),
    (_raw({"key": "sumo.scale", "values": [1.0]}, seeds=0), r"study.toml: seeds: 0 is out of range"),
    (_raw({"key": "sumo.scale", "values": [1.0]}, seeds=1.5), r"study.toml: seeds = 1.5; give a whole number"),
    (_raw({"key": "sumo.scale", "values": [1.0]}, bench_episodes=-1), r"study.toml: bench_episodes: -1 is out of range"),
    ({**_raw({"key": "sumo.scale", "values": [1.0]}),
      "data": {"scenario": "paper", "train_samples": 1, "test_samples": 1, "sample_period_s": 0.0}},
     r"\[data\]: sample_period_s: 0 is out of range; give simulated seconds in \(0, 60\]"),
])
def test_bad_preset_is_a_clear_error(raw, message):
    with pytest.raises(CrchflError, match=message):
        parse_study(raw, "study.toml")


def test_cli_names_a_bad_key_before_anything_runs(tmp_path, capsys):
    text = (PRESETS / "mobility_quick.toml").read_text().replace('key = "sumo.scale"', 'key = "sumo.scal"')
    (tmp_path / "bad.toml").write_text(text)
    assert main(["mobility-study", "--config", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "factor 'traffic density': sumo.scal=0.5" in err and "'scal'" in err
    assert not (tmp_path / "out" / "data").exists()  # checked before the data set is generated


# ------------------------------------------------------------------ the report


def _summary(i: int) -> dict:
    return {
        "best_accuracy": 0.5 + i / 100, "balanced_accuracy": 0.3 + i / 100, "cloud_rounds": 3 + i, "handovers": 10 * i,
        "stragglers": i, "relay_bytes": i * 2**20, "wasted_bytes": 3 * i * 2**20, "uploads_failed": i, "uploads": 20,
        "relayed_transfers": i, "downloads_failed": 0, "edge_aggregations": 6, "sim_time_s": 100.0 * i,
        "stop_reason": "budget",
    }


def test_report_rows_table_and_figures_from_hand_made_summaries(tmp_path):
    study = _study(
        {"name": "speed", "key": "sumo.speed_limit_mps", "values": [8.0, 14.0, float("inf")]},
        {"name": "policy", "key": "federation.handover_policy", "values": ["new_edge", "miss"]},
    )
    plan = StudyPlan(
        (Point(BASELINE, {}, {}),),
        {"speed": ("s8", "s14", BASELINE), "policy": (BASELINE, "miss")},
    )
    summaries = {BASELINE: _summary(0), "s8": _summary(1), "s14": _summary(2), "miss": _summary(3)}
    rows = study_rows(study.factors, plan, {point: {0: summary} for point, summary in summaries.items()})
    assert [(r["factor"], r["value"], r["point"]) for r in rows] == [
        ("speed", "8.0", "s8"), ("speed", "14.0", "s14"), ("speed", "inf", BASELINE),
        ("policy", "new_edge", BASELINE), ("policy", "miss", "miss"),
    ]
    for row in rows:
        summary = summaries[row["point"]]
        assert {k: row[k] for k in summary} == summary
    figures = write_report(tmp_path, study.factors, rows)
    assert [f.name for f in figures] == ["speed.png", "policy.png"] and all(f.stat().st_size > 0 for f in figures)
    with open(tmp_path / "results.csv", newline="") as handle:
        table = list(csv.DictReader(handle))
    assert [t["point"] for t in table] == [r["point"] for r in rows]
    assert float(table[1]["wasted_bytes"]) == summaries["s14"]["wasted_bytes"]
    assert int(table[4]["handovers"]) == 30 and table[4]["stop_reason"] == "budget"
    md = (tmp_path / "results.md").read_text()
    assert md.startswith(markdown_table(rows)) and "## Findings" in md
    assert "One seed a point: no intervals, so no findings" in md
    # s14: accuracy 0.52, balanced 0.32, 5 rounds, 20 handovers, 2 stragglers, 2 MB relayed, 6 MB wasted, 2/20 failed
    assert "| speed | 14.0 | 1 | 0.520 | 0.320 | - | - | - | 5 | 20 | 2 | 2 | 6 | 2/20 | 200 | budget |" in md
    assert "| policy | new_edge * |" in md  # the baseline's rows are marked
    assert "Always straight" not in md  # these summaries recorded no baseline


def test_report_reads_the_accuracies_against_always_straight(tmp_path):
    study = _study({"name": "policy", "key": "federation.handover_policy", "values": ["new_edge", "miss"]})
    plan = StudyPlan((Point(BASELINE, {}, {}),), {"policy": (BASELINE, "miss")})
    straight = {"always_straight": {"accuracy": 0.775, "balanced_accuracy": 1 / 7, "steer_error": 0.07}}
    summaries = {p: {s: {**_summary(i), "baselines": straight} for s in range(2)}
                 for i, p in enumerate((BASELINE, "miss"))}
    rows = study_rows(study.factors, plan, summaries)
    write_report(tmp_path, study.factors, rows)
    md = (tmp_path / "results.md").read_text()
    assert "Always straight on the study's test set: accuracy 0.775, balanced accuracy 0.143." in md
    with open(tmp_path / "results.csv", newline="") as handle:
        table = list(csv.DictReader(handle))
    assert {(t["always_straight_accuracy"], t["always_straight_balanced_accuracy"]) for t in table} == {
        ("0.775", str(1 / 7))}


def test_table_gives_a_count_averaged_over_seeds_to_one_decimal():
    study = _study({"name": "policy", "key": "federation.handover_policy", "values": ["new_edge", "miss"]})
    plan = StudyPlan((Point(BASELINE, {}, {}),), {"policy": (BASELINE, "miss")})
    # seeds 1 and 2 of _summary: 4 and 5 rounds, 10 and 20 handovers, 1 and 2 stragglers, 1/20 and 2/20 failed
    summaries = {BASELINE: {0: _summary(0), 1: _summary(0)}, "miss": {0: _summary(1), 1: _summary(2)}}
    md = markdown_table(study_rows(study.factors, plan, summaries))
    assert "| policy | miss | 2 | 0.515 | 0.315 [" in md
    assert "| 4.5 | 15 | 1.5 | 2 | 4 | 1.5/20 | 150 | budget |" in md
    assert "| policy | new_edge * | 2 | 0.500 | 0.300 [0.300, 0.300] | - | - | - | 3 | 0 | 0 | 0 | 0 | 0/20 | 0 |" in md


# ------------------------------------------------------------------ a tiny real study


def test_tiny_study_runs_its_points_and_resumes(tmp_path):
    out = tmp_path / "study"
    write_dataset(out / "data", PAPER_VEHICLES)  # present: the study does not generate one
    base = {k: v for k, v in run_config(Path("unused")).items() if k != "dataset"}
    study = Study("tiny", StudyData("paper", 1, 1, 0), base, parse_study(
        {"data": {"scenario": "paper", "train_samples": 1, "test_samples": 1}, "run": base,
         "factor": [{"name": "edge interval", "key": "federation.edge_interval", "values": [1, 2]}]},
        "tiny.toml").factors, seeds=2, bench_episodes=1)
    rows = run_study(study, out, BackendConfig(num_cpus=2))
    # two seeds a point, each run's best model benchmarked: straight and one_turn in both towns, one episode each
    assert all(r["seeds"] == 2 for r in rows)
    for seed in (0, 1):
        bench = json.loads((out / "bench" / BASELINE / f"seed-{seed}" / "summary.json").read_text())
        assert {(town, task) for town, tasks in bench["results"].items() for task in tasks} == {
            ("town01", "straight"), ("town01", "one_turn"), ("town02", "straight"), ("town02", "one_turn")}
        assert json.loads((out / "runs" / BASELINE / f"seed-{seed}" / "config.json").read_text()
                          )["config"]["federation"]["seed"] == seed
    assert rows[0]["driving_score_mean"] is not None and rows[0]["balanced_accuracy_ci_lo"] is not None
    assert [r["point"] for r in rows] == [BASELINE, "federation.edge_interval=2"]
    for row in rows:
        summary = json.loads((out / "runs" / row["point"] / "seed-0" / "summary.json").read_text())
        assert row["cloud_rounds"] == summary["cloud_rounds"] == 2
        assert row["best_accuracy"] == summary["best_accuracy"]
    saved = json.loads((out / "study.json").read_text())
    assert saved["factors"][0]["points"] == [BASELINE, "federation.edge_interval=2"]
    assert (out / "plots" / "edge_interval.png").stat().st_size > 0
    before = (out / "runs" / BASELINE / "seed-0" / "summary.json").stat().st_mtime_ns
    run_study(study, out, BackendConfig(num_cpus=2))  # a rerun runs nothing again
    assert (out / "runs" / BASELINE / "seed-0" / "summary.json").stat().st_mtime_ns == before


def test_rows_over_seeds_carry_intervals_the_closed_loop_and_the_findings(tmp_path):
    from scipy import stats

    study = _study({"name": "density", "key": "sumo.scale", "values": [0.5, 1.0, 2.0]})
    plan = StudyPlan((Point(BASELINE, {}, {}),), {"density": ("d05", BASELINE, "d2")})
    accuracy = {BASELINE: [0.50, 0.52, 0.51], "d05": [0.50, 0.53, 0.49], "d2": [0.30, 0.31, 0.33]}
    rate = {BASELINE: [20.0, 21.0, 19.0], "d05": [30.0, 29.0, 31.0], "d2": [10.0, 11.0, 9.0]}
    summaries = {p: {s: {**_summary(1), "balanced_accuracy": accuracy[p][s], "mean_uplink_rate_mbps": rate[p][s]}
                     for s in range(3)} for p in accuracy}

    def bench(score, success):  # two cells of 2 and 6 episodes
        return {"results": {"town01": {"straight": {"episodes": 2, "driving_score": score[0], "success_rate": success[0]}},
                            "town02": {"one_turn": {"episodes": 6, "driving_score": score[1], "success_rate": success[1]}}}}

    benches = {p: {s: bench((0.8, 0.4), (1.0, 0.5)) for s in range(3)} for p in accuracy}
    rows = study_rows(study.factors, plan, summaries, benches)
    d2 = next(r for r in rows if r["point"] == "d2")
    lo, hi = stats.t.interval(0.95, 2, loc=sum(accuracy["d2"]) / 3, scale=stats.sem(accuracy["d2"]))
    assert d2["seeds"] == 3 and d2["balanced_accuracy_mean"] == pytest.approx(0.94 / 3)
    assert (d2["balanced_accuracy_ci_lo"], d2["balanced_accuracy_ci_hi"]) == (pytest.approx(lo), pytest.approx(hi))
    assert d2["driving_score_mean"] == pytest.approx((2 * 0.8 + 6 * 0.4) / 8)  # the cells weighted by episodes
    assert d2["success_rate_mean"] == pytest.approx((2 * 1.0 + 6 * 0.5) / 8)
    assert d2["mean_uplink_rate_mbps"] == pytest.approx(10.0)
    write_report(tmp_path, study.factors, rows)
    with open(tmp_path / "results.csv", newline="") as handle:
        table = {t["point"]: t for t in csv.DictReader(handle)}
    for column in ("seeds", "balanced_accuracy_mean", "balanced_accuracy_ci_lo", "balanced_accuracy_ci_hi",
                   "driving_score_mean", "success_rate_mean", "mean_uplink_rate_mbps"):
        assert table["d2"][column] != ""
    md = (tmp_path / "results.md").read_text()
    # paired by seed against the baseline: density 2 lowers the accuracy (-0.197) and the rate (-10.0);
    # density 0.5's accuracy differences (0, +0.01, -0.02) cover 0; the closed loop is the same everywhere
    assert "| density | balanced accuracy | moves: 2.0 -0.197 |" in md
    assert "| density | uplink Mbit/s | moves: 0.5 +10.0; 2.0 -10.0 |" in md
    assert "| density | driving score | not distinguishable at any value |" in md


def test_a_study_moves_to_another_scenario_and_drops_the_factors_bound_to_its_own(grid_dir):
    from crchfl_sumo.studies.mobility_study import BENCH_TOWNS, for_scenario

    study = parse_study(read_toml(PRESETS / "mobility_quick.toml"), "mobility_quick.toml")
    cfg = str(grid_dir / "grid.sumocfg")
    moved, dropped = for_scenario(study, cfg)
    assert dropped == ["edge-site placement"]
    assert [f.name for f in moved.factors] == [f.name for f in study.factors if f.name != "edge-site placement"]
    assert moved.data.scenario == moved.base["scenario"] == str(Path(cfg).resolve())
    assert moved.bench_towns == (str(Path(cfg).resolve()),)  # it drives where it learned
    assert moved.data.train_samples == study.data.train_samples  # the same samples per vehicle
    paper, dropped = for_scenario(study, "paper")
    assert paper.bench_towns == BENCH_TOWNS and dropped == ["edge-site placement"]
    assert for_scenario(study, "paper_linked") == (study, [])


def test_a_tiny_study_runs_in_a_plain_sumocfg(grid_dir, tmp_path):
    from crchfl_sumo.studies.mobility_study import for_scenario

    base = {"scenario": "unused", "federation": {"scheme": "hfl", "edge_interval": 1, "cloud_rounds": 1},
            "ledger": {"nominal_model_mb": 10.0},
            "train": {"device": "cpu"}, "clock": {"kind": "sumo"}}
    study = parse_study({"data": {"scenario": "paper", "train_samples": 2, "test_samples": 2}, "run": base,
                         "factor": [{"name": "edge interval", "key": "federation.edge_interval", "values": [1, 2]}],
                         "bench_episodes": 1}, "tiny.toml")
    study, _ = for_scenario(study, str(grid_dir / "grid.sumocfg"))
    rows = run_study(study, tmp_path / "study", BackendConfig(num_cpus=2))
    assert [r["point"] for r in rows] == [BASELINE, "federation.edge_interval=2"]
    bench = json.loads((tmp_path / "study" / "bench" / BASELINE / "seed-0" / "summary.json").read_text())
    assert set(bench["results"]) == {"grid"}  # driven in the scenario it learned in
    assert json.loads((tmp_path / "study" / "study.json").read_text())["bench_towns"] == list(study.bench_towns)


@pytest.mark.slow
def test_a_data_set_cut_off_while_generating_is_finished_not_used_half_made(tmp_path):
    from crchfl_sumo.data.manifest import MANIFEST_NAME
    from crchfl_sumo.studies.mobility_study import make_data

    data = StudyData("paper", 1, 1, 0)
    out = make_data(data, tmp_path / "data")
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    files = [shard["file"] for shard in manifest["shards"]]
    assert len(files) == 7  # the paper scenario's 5 data and 2 test vehicles, one shard each
    whole = {name: (out / name).read_bytes() for name in files}
    # a generation cut off before its last shard: the manifest lists the others, the shard is not there
    manifest["shards"] = [shard for shard in manifest["shards"] if shard["file"] != files[-1]]
    (out / MANIFEST_NAME).write_text(json.dumps(manifest))
    (out / files[-1]).unlink()
    make_data(data, out)
    again = json.loads((out / MANIFEST_NAME).read_text())
    assert [shard["file"] for shard in again["shards"]] == files
    assert {name: (out / name).read_bytes() for name in files} == whole
