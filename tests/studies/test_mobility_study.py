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
from crchfl_sumo.studies.mobility import BASELINE, Plan, Study, StudyData, parse_study, run_study, study_plan
from crchfl_sumo.studies.mobility_report import markdown_table, study_rows, write_report
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
    plan = Plan(
        (Point(BASELINE, {}, {}),),
        {"speed": ("s8", "s14", BASELINE), "policy": (BASELINE, "miss")},
    )
    summaries = {BASELINE: _summary(0), "s8": _summary(1), "s14": _summary(2), "miss": _summary(3)}
    rows = study_rows(study.factors, plan, summaries)
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
    assert md == markdown_table(rows)
    # s14: accuracy 0.52, balanced 0.32, 5 rounds, 20 handovers, 2 stragglers, 2 MB relayed, 6 MB wasted, 2/20 failed
    assert "| speed | 14.0 | 0.520 | 0.320 | 5 | 20 | 2 | 2 | 6 | 2/20 | 200 | budget |" in md
    assert "| policy | new_edge * |" in md  # the baseline's rows are marked


# ------------------------------------------------------------------ a tiny real study


def test_tiny_study_runs_its_points_and_resumes(tmp_path):
    out = tmp_path / "study"
    write_dataset(out / "data", PAPER_VEHICLES)  # present: the study does not generate one
    base = {k: v for k, v in run_config(Path("unused")).items() if k != "dataset"}
    study = Study("tiny", StudyData("paper", 1, 1, 0), base, parse_study(
        {"data": {"scenario": "paper", "train_samples": 1, "test_samples": 1}, "run": base,
         "factor": [{"name": "edge interval", "key": "federation.edge_interval", "values": [1, 2]}]},
        "tiny.toml").factors)
    rows = run_study(study, out, BackendConfig(num_cpus=2))
    assert [r["point"] for r in rows] == [BASELINE, "federation.edge_interval=2"]
    for row in rows:
        summary = json.loads((out / "runs" / row["point"] / "summary.json").read_text())
        assert row["cloud_rounds"] == summary["cloud_rounds"] == 2
        assert row["best_accuracy"] == summary["best_accuracy"]
    saved = json.loads((out / "study.json").read_text())
    assert saved["factors"][0]["points"] == [BASELINE, "federation.edge_interval=2"]
    assert (out / "plots" / "edge_interval.png").stat().st_size > 0
    before = (out / "runs" / BASELINE / "summary.json").stat().st_mtime_ns
    run_study(study, out, BackendConfig(num_cpus=2))  # a rerun runs nothing again
    assert (out / "runs" / BASELINE / "summary.json").stat().st_mtime_ns == before
