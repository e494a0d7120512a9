"""report.py on hand-written results folders: statistics by hand, gains, figures, report.md, summary.json."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.studies.report import report_command
from crchfl_sumo.studies.statistics import (
    cloud_lines,
    curve_by_bytes,
    curve_by_round,
    elapsed_s,
    mean_std,
    relative_gain_percent,
    timing_groups,
)

GIB = 1024**3
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_mean_std_by_hand():
    stats = mean_std([0.5, 0.7, None])
    assert stats["n"] == 2 and stats["mean"] == pytest.approx(0.6)
    assert stats["std"] == pytest.approx(math.sqrt(0.02))  # ((0.1^2 + 0.1^2) / (2 - 1)) ** 0.5
    # t(0.975, 1 dof) = 12.706205: mean 0.6 +- 12.706 * 0.1
    assert stats["ci95"] == pytest.approx([0.6 - 1.2706205, 0.6 + 1.2706205])
    assert mean_std([0.3]) == {"mean": 0.3, "std": None, "n": 1, "ci95": None}
    assert mean_std([]) == {"mean": None, "std": None, "n": 0, "ci95": None}


def test_relative_gain_percent():
    assert relative_gain_percent(0.66, 0.6) == pytest.approx(10.0)
    assert relative_gain_percent(0.5, 0.625) == pytest.approx(-20.0)
    assert relative_gain_percent(None, 0.5) is None and relative_gain_percent(0.5, 0.0) is None


def _lines(accuracies, losses, round_bytes, stage_one=None):
    """metrics.jsonl lines: an optional stage I line (round 0), then edge (II) and cloud (III) lines."""
    lines = []
    if stage_one is not None:
        acc, loss, spent = stage_one
        lines.append(
            {"step": 0, "stage": "I", "cloud_round": 0, "consumed_bytes": spent, "accuracy": acc, "loss": loss}
        )
        base = spent
    else:
        base = 0
    for k, (acc, loss) in enumerate(zip(accuracies, losses), start=1):
        spent = base + k * round_bytes
        lines.append({"step": 2 * k - 1, "stage": "II", "cloud_round": k - 1, "consumed_bytes": spent - 1,
                      "accuracy": None, "loss": None})
        lines.append({"step": 2 * k, "stage": "III", "cloud_round": k, "consumed_bytes": spent,
                      "accuracy": acc, "loss": loss})
    return lines


def test_curves_group_by_round_and_average_bytes():
    a = _lines([0.5, 0.7], [2.0, 1.0], 100)
    b = _lines([0.7, 0.9, 0.95], [1.0, 0.5, 0.4], 110)
    assert [m["stage"] for m in cloud_lines(a)] == ["III", "III"]
    curve = curve_by_round([a, b], "accuracy")
    assert list(curve["x"]) == [1, 2, 3]
    assert list(curve["mean"]) == pytest.approx([0.6, 0.8, 0.95])
    assert curve["std"][0] == pytest.approx(math.sqrt(0.02)) and math.isnan(curve["std"][2])
    assert list(curve["n"]) == [2, 2, 1]
    by_bytes = curve_by_bytes([a, b], "loss")
    assert list(by_bytes["x"]) == pytest.approx([105, 210, 330])
    assert list(by_bytes["mean"]) == pytest.approx([1.5, 0.75, 0.4])


def test_timing_groups():
    timings = {
        "data": {"wall_s": 2.0, "cpu_s": 3.0},
        "runs/crchfl/seed-0": {"wall_s": 3.0, "cpu_s": 5.0},
        "runs/hfl/seed-0": {"wall_s": 4.0, "cpu_s": 6.0},
        "drives/r/crchfl": {"wall_s": 1.5, "cpu_s": 1.0},
    }
    assert timing_groups(timings) == {
        "data": {"wall_s": 2.0, "cpu_s": 3.0},
        "runs": {"wall_s": 7.0, "cpu_s": 11.0},
        "drives": {"wall_s": 1.5, "cpu_s": 1.0},
        "total": {"wall_s": 10.5, "cpu_s": 15.0, "elapsed_s": 10.5},  # no start times: the parts' sum
    }
    assert timing_groups({}) == {"total": {"wall_s": 0.0, "cpu_s": 0.0, "elapsed_s": 0.0}}


def test_elapsed_time_of_parts_run_side_by_side():
    # [100, 110] and [105, 125] overlap by 5 s; [200, 202] stands apart; a part without a start adds 3 s
    spans = [
        {"wall_s": 10.0, "start_unix": 100.0},
        {"wall_s": 20.0, "start_unix": 105.0},
        {"wall_s": 2.0, "start_unix": 200.0},
        {"wall_s": 3.0},
    ]
    assert elapsed_s(spans) == pytest.approx(25.0 + 2.0 + 3.0)
    # a part inside another adds nothing
    assert elapsed_s([{"wall_s": 10.0, "start_unix": 0.0}, {"wall_s": 2.0, "start_unix": 4.0}]) == 10.0
    assert elapsed_s([]) == 0.0


# ------------------------------------------------------------------ a whole folder


def _write(path: Path, payload) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(payload, list):
        path.write_text("".join(json.dumps(x) + "\n" for x in payload))
    else:
        path.write_text(json.dumps(payload))


# best accuracy per scheme and seed; CRCHFL's mean 0.66, HFL's 0.6, SFL's 0.55
BEST = {"crchfl": (0.64, 0.68), "hfl": (0.58, 0.62), "sfl": (0.5, 0.6)}
ROUNDS = {"crchfl": 9, "hfl": 9, "sfl": 13}


def _fake_run(folder: Path, scheme: str, seed: int, best: float, rounds: int, edge_interval: int = 2) -> None:
    round_bytes = int(2 * GIB)
    accuracies = [best * (k + 1) / rounds for k in range(rounds)]
    losses = [2.0 / (k + 1) for k in range(rounds)]
    stage_one = (0.1, 2.5, int(1.5 * GIB)) if scheme == "crchfl" else None
    lines = _lines(accuracies, losses, round_bytes // 10, stage_one)
    spent = lines[-1]["consumed_bytes"]
    _write(folder / "metrics.jsonl", lines)
    _write(folder / "summary.json", {
        "scheme": scheme, "cloud_rounds": rounds, "edge_aggregations": rounds, "consumed_bytes": spent,
        "budget_bytes": 20 * GIB, "best_accuracy": best, "final_accuracy": accuracies[-1], "best_loss": losses[-1],
        "final_loss": losses[-1], "sim_time_s": 100.0 * rounds, "stop_reason": "budget",
        "bytes_by_stage": {"I": int(1.5 * GIB) if scheme == "crchfl" else 0, "II": 6 * GIB, "III": 12 * GIB},
        "hyper": {"pretrain_batch": 449 if scheme == "crchfl" else 0, "edge_interval": edge_interval,
                  "cloud_interval": 1, "cloud_rounds": rounds},
        "balanced_accuracy": best / 2, "final_balanced_accuracy": best / 4, "best_steer_error": 0.1,
        "best_throttle_error": 0.2, "best_brake_error": 0.3,
        "best_recall": [best, None, 0.5, None, None, None, float(seed)],  # classes 1, 3-5 absent
        "best_confusion": [[seed + 1 if (i, j) == (0, 0) else 0 for j in range(7)] for i in range(7)],
        "baselines": {"always_straight": {"accuracy": 0.55, "balanced_accuracy": 1 / 7}},
    })


@pytest.fixture()
def results(tmp_path) -> Path:
    out = tmp_path / "results"
    for scheme, bests in BEST.items():
        for seed, best in enumerate(bests):
            _fake_run(out / "runs" / scheme / f"seed-{seed}", scheme, seed, best, ROUNDS[scheme])
    for k in (2, 3, 4):
        _fake_run(out / "ablation" / f"ie-{k}" / "seed-0", "crchfl", 0, 0.6 + 0.01 * k, 9, edge_interval=k)
    for seed, (acc, loss) in enumerate(((0.8, 0.6), (0.9, 0.5))):
        folder = out / "centralized" / f"seed-{seed}"
        _write(folder / "metrics.jsonl", [{"epoch": 1, "accuracy": acc - 0.1, "loss": loss + 0.2},
                                          {"epoch": 2, "accuracy": acc, "loss": loss}])
        _write(folder / "summary.json", {"scheme": "centralized", "epochs": 2, "best_accuracy": acc, "best_loss": loss,
                                         "final_accuracy": acc, "final_loss": loss})
    for label, completion in (("crchfl", 1.0), ("hfl", 0.4), ("reference", 1.0)):
        _write(out / "drives" / "town01_right_left" / label / "metrics.json",
               {"route": "town01_right_left", "completion": completion, "collisions": 0, "end_reason": "completed"})
    _write(out / "reproduce.json", {"config": {"name": "test", "seeds": 2}, "seeds": [0, 1], "ablation_seeds": [0],
                                    "started_utc": "2026-11-23T00:00:00Z",
                                    "environment": {"python": "3.x", "bfloat16_cpu": True,
                                                    "versions": {"torch": "2.13.0"}}})
    _write(out / "timings.json", {
        "data": {"wall_s": 1.0, "cpu_s": 1.5},
        "runs/crchfl/seed-0": {"wall_s": 10.0, "cpu_s": 19.0, "start_unix": 1000.0, "jobs": 2},
        "ablation/ie-2/seed-0": {"wall_s": 5.0, "cpu_s": 9.5, "start_unix": 1004.0, "jobs": 2},
    })
    return out


def test_report_of_a_folder(results):
    summary = report_command(results)
    written = json.loads((results / "summary.json").read_text())
    assert written == json.loads(json.dumps(summary))
    crchfl = summary["schemes"]["crchfl"]
    assert crchfl["best_accuracy"]["mean"] == pytest.approx(0.66)
    assert crchfl["best_accuracy"]["std"] == pytest.approx(math.sqrt(0.0008))  # 0.02 either side, ddof 1
    assert crchfl["cloud_rounds"]["mean"] == 9 and summary["schemes"]["sfl"]["cloud_rounds"]["mean"] == 13
    for scheme in ("crchfl", "hfl", "sfl"):
        for key in ("cloud_rounds", "best_accuracy", "final_loss", "consumed_bytes", "closed_loop"):
            assert key in summary["schemes"][scheme]
    assert crchfl["closed_loop"]["town01_right_left"]["completion"] == 1.0
    assert summary["schemes"]["sfl"]["closed_loop"] == {}
    gain = summary["gains"]["best_accuracy"]
    assert gain["hfl"]["relative_percent"] == pytest.approx(10.0)  # 0.66 over 0.6
    assert gain["sfl"]["relative_percent"] == pytest.approx(20.0)  # 0.66 over 0.55
    assert gain["hfl"]["points"] == pytest.approx(6.0)
    assert summary["gains"]["paper_percent"] == {"hfl": 10.33, "sfl": 12.41}
    assert summary["centralized"]["best_accuracy"]["mean"] == pytest.approx(0.85)
    ablation = summary["ablation"]
    assert list(ablation) == ["ie-2", "ie-3", "ie-4"]
    assert ablation["ie-2"]["budget_percent"]["I"] == pytest.approx(7.5)
    assert ablation["ie-2"]["budget_percent"]["unused"] == pytest.approx(2.5)
    # the ablation ran beside the run (1004 to 1009 within 1000 to 1010): 1 + 10 s elapsed
    assert summary["running_time_s"]["total"] == {"wall_s": 16.0, "cpu_s": 30.0, "elapsed_s": 11.0}
    report = (results / "report.md").read_text()
    assert set(summary["figures"]) == {"fig3", "fig4", "fig7", "centralized"}  # the drives lack trajectories
    for path in summary["figures"].values():
        assert (results / path).read_bytes()[:8] == PNG_MAGIC
        assert path in report
    # seed by seed: over HFL +0.06 twice (a point interval); over SFL +0.14 and +0.08: mean 0.11, sem 0.03,
    # t(0.975, 1 dof) = 12.706205, and on 1 dof (Cauchy) p = 1 - 2 atan(0.11 / 0.03) / pi
    over_hfl, over_sfl = (summary["differences"][f"crchfl-{o}"]["best_accuracy"] for o in ("hfl", "sfl"))
    assert over_hfl["mean"] == pytest.approx(0.06) and over_hfl["ci95"] == pytest.approx([0.06, 0.06])
    assert over_hfl["n"] == 2 and over_hfl["p"] == 0.0
    assert over_sfl["mean"] == pytest.approx(0.11)
    assert over_sfl["ci95"] == pytest.approx([0.11 - 12.706205 * 0.03, 0.11 + 12.706205 * 0.03], abs=1e-5)
    assert over_sfl["p"] == pytest.approx(1 - 2 * math.atan(0.11 / 0.03) / math.pi)
    assert summary["differences"]["crchfl-sfl"]["balanced_accuracy"]["mean"] == pytest.approx(0.055)
    assert "over SFL (2 seeds): balanced accuracy +5.50 points" in report and "not distinguishable at 95 %" in report
    # t(0.975, 1 dof) * 0.02 either side of 0.66
    for text in ("+10.33 %", "+12.41 %", "+10.00 %", "+20.00 %", "0.6600 [0.4059, 0.9141]", "town01_right_left", "2.13.0",
                 "bfloat16 arithmetic on the CPU true"):
        assert text in report, text
    assert not list(results.rglob(".*.partial-*"))
    # balanced accuracy beside accuracy, the baseline on the same test set, what the best models learned
    assert crchfl["balanced_accuracy"]["mean"] == pytest.approx(0.33) and crchfl["balanced_accuracy"]["n"] == 2
    assert summary["baselines"] == {"always_straight": {"accuracy": 0.55, "balanced_accuracy": 1 / 7}}
    assert crchfl["recall"] == pytest.approx([0.66, None, 0.5, None, None, None, 0.5], nan_ok=True)
    assert crchfl["confusion"][0][0] == 3 and sum(map(sum, crchfl["confusion"])) == 3  # 1 + 2 over the seeds
    for text in ("Always straight (baseline)", "0.5500", "0.1429", "What the best models learned", "true / predicted"):
        assert text in report, text


def test_no_relative_gain_over_a_scheme_with_a_seed_at_zero(results):
    _fake_run(results / "runs" / "hfl" / "seed-1", "hfl", 1, 0.0, ROUNDS["hfl"])  # a broken run
    gain = report_command(results)["gains"]["best_accuracy"]["hfl"]
    assert gain["relative_percent"] is None  # a percentage of a mean pulled down by 0 says nothing
    assert gain["points"] == pytest.approx(100 * (0.66 - 0.29))


def test_unfinished_runs_are_named_in_the_table(results):
    path = results / "runs" / "hfl" / "seed-1" / "summary.json"
    summary = json.loads(path.read_text())
    path.write_text(json.dumps({**summary, "stop_reason": None}))
    report_command(results)
    assert "| 2 (1 unfinished) |" in (results / "report.md").read_text()


def test_report_is_rebuilt_the_same(results):
    report_command(results)
    first = (results / "summary.json").read_text(), (results / "report.md").read_text()
    report_command(results)
    assert ((results / "summary.json").read_text(), (results / "report.md").read_text()) == first


def test_a_report_sweeps_the_temporaries_a_killed_report_left(results):
    (results / "figures").mkdir(exist_ok=True)
    stale = [results / "figures" / ".fig4_bytes.png.partial-x1.png", results / ".summary.json.partial-x2.json"]
    for path in stale:
        path.write_bytes(b"half a figure")
    keep = results / "figures" / "notes.txt"
    keep.write_text("mine")
    report_command(results)
    assert not any(path.exists() for path in stale) and keep.read_text() == "mine"


def test_report_of_an_empty_folder_says_what_to_run(tmp_path):
    with pytest.raises(CrchflError, match="reproduce"):
        report_command(tmp_path)
    with pytest.raises(CrchflError, match="no such results folder"):
        report_command(tmp_path / "missing")


def test_format_summary_lists_schemes_and_gains(results):
    from crchfl_sumo.studies.report import format_summary

    text = format_summary(report_command(results), results)
    assert "CRCHFL over HFL: +10.00 %" in text and "(paper: +12.41 %)" in text
    assert text.splitlines()[0].startswith("CRCHFL") and str(results / "report.md") in text
    assert "balanced accuracy" in text.splitlines()[0] and "always straight: balanced accuracy" in text


def _fake_bench(folder: Path, success: float, score: float, km: float, collisions: int) -> None:
    """A drive-bench summary.json of one town and task, 4 episodes."""
    _write(folder / "summary.json", {"results": {"town01": {"navigation": {
        "episodes": 4, "success_rate": success, "route_completion": 1.0, "driving_score": score,
        "infractions_per_km": collisions / km, "distance_km": km,
        "infractions": {"collisions": collisions, "red_light_violations": 0, "off_road_events": 0,
                        "lane_departures": 0},
    }}}})


def test_a_benchmark_of_every_seed_gives_all_episodes_and_the_spread_over_seeds(results):
    _fake_bench(results / "drive_bench" / "crchfl" / "seed-0", 0.5, 0.6, 2.0, 2)
    _fake_bench(results / "drive_bench" / "crchfl" / "seed-1", 1.0, 0.8, 3.0, 0)
    _fake_bench(results / "drive_bench" / "reference", 1.0, 1.0, 2.5, 0)
    summary = report_command(results)
    pooled = summary["drive_bench"]["crchfl"]["town01"]["navigation"]
    # 8 episodes: 2 + 4 successes, 2 collisions over 5 km
    assert pooled["episodes"] == 8 and pooled["success_rate"] == pytest.approx(0.75)
    assert pooled["driving_score"] == pytest.approx(0.7) and pooled["infractions_per_km"] == pytest.approx(0.4)
    spread = summary["drive_bench_spread"]["crchfl"]
    assert spread["seeds"] == [0, 1]
    success = spread["town01"]["navigation"]["success_rate"]
    assert success["values"] == [0.5, 1.0] and success["std"] == pytest.approx(math.sqrt(0.125))  # ddof 1
    assert summary["drive_bench"]["reference"]["town01"]["navigation"]["episodes"] == 4
    assert "reference" not in summary["drive_bench_spread"]
    report = (results / "report.md").read_text()
    assert "| CRCHFL | 75 ± 35 / 100 / 70 ± 14 | 0.40 |" in report
    assert "| Reference driver | 100 / 100 / 100 | 0.00 |" in report
    # the terminal's summary ends each scheme's line with its closed loop over all episodes
    from crchfl_sumo.studies.report import format_summary

    assert "driving score 70.0, success 75 %" in format_summary(summary, results).splitlines()[0]


def _fake_episodes(folder: Path, outcomes) -> None:
    """episodes.json beside a benchmark's summary: (index, success, driving score) per episode, on Town01's
    navigation suite, the route named by its index."""
    (folder / "episodes.json").write_text(json.dumps([
        {"town": "town01", "task": "navigation", "index": i, "edges": [f"e{i}"], "success": ok, "driving_score": score}
        for i, ok, score in outcomes
    ]))


def test_the_closed_loop_is_compared_by_seed_and_by_episode(results):
    for label, seed, success, score, outcomes in (
        ("crchfl", 0, 0.5, 0.6, [(0, True, 0.9), (1, False, 0.3)]),
        ("crchfl", 1, 1.0, 0.8, [(0, True, 1.0), (1, True, 0.6)]),
        ("hfl", 0, 0.25, 0.5, [(0, False, 0.5), (1, False, 0.3)]),
        ("hfl", 1, 0.5, 0.6, [(0, True, 1.0), (1, False, 0.2), (5, True, 1.0)]),  # episode 5: CRCHFL did not drive it
    ):
        _fake_bench(results / "drive_bench" / label / f"seed-{seed}", success, score, 2.0, 0)
        _fake_episodes(results / "drive_bench" / label / f"seed-{seed}", outcomes)
    _fake_bench(results / "drive_bench" / "reference", 1.0, 1.0, 2.5, 0)
    summary = report_command(results)
    pair = summary["differences"]["crchfl-hfl"]
    assert pair["balanced_accuracy"]["mean"] == pytest.approx(0.03)  # the offline keys stay
    # by seed: success 0.5 - 0.25 and 1.0 - 0.5, score 0.6 - 0.5 and 0.8 - 0.6
    assert pair["success_rate"]["mean"] == pytest.approx(0.375) and pair["success_rate"]["n"] == 2
    assert pair["driving_score"]["mean"] == pytest.approx(0.15)
    # by episode, the 4 episodes both drove: success 1, 0, 0, 1; score 0.4, 0, 0, 0.4 (sd 0.23094, t(0.975, 3) 3.182446)
    episodes = pair["by_episode"]
    assert episodes["success_rate"]["mean"] == pytest.approx(0.5) and episodes["success_rate"]["n"] == 4
    half = 3.182446 * (0.4 / math.sqrt(3)) / 2
    assert episodes["driving_score"]["ci95"] == pytest.approx([0.2 - half, 0.2 + half], abs=1e-5)
    assert "crchfl-reference" not in summary["differences"]  # one model, no seeds to pair
    assert summary["differences"]["crchfl-sfl"].keys() == {"balanced_accuracy", "best_accuracy"}  # SFL did not drive
    report = (results / "report.md").read_text()
    assert "closed-loop success +37.50 points" in report
    assert "By episode (4 pairs): closed-loop success +50.00 points" in report
    from crchfl_sumo.studies.report import format_summary

    terminal = format_summary(summary, results)
    assert "CRCHFL minus HFL, closed-loop success by episode: +50.00 points" in terminal
    assert "CRCHFL minus SFL, closed-loop" not in terminal


def test_the_budget_sentence_says_where_crchfl_leads_in_accuracy_and_in_driving():
    from crchfl_sumo.studies.report_sections import lead_sentence

    def d(mean, lo, hi):
        return {"mean": mean, "ci95": [lo, hi], "p": 0.01, "n": 3}

    differences = {
        "crchfl-hfl": {
            "2.5": {"balanced_accuracy": d(0.15, -0.1, 0.4), "driving_score": d(0.26, 0.24, 0.28)},
            "5": {"balanced_accuracy": d(0.13, 0.11, 0.16), "driving_score": d(-0.2, -0.3, -0.1)},
        },
        "crchfl-sfl": {
            "2.5": {"balanced_accuracy": d(0.15, 0.1, 0.2)},  # no benchmark at 2.5 GB
            "5": {"balanced_accuracy": d(-0.02, -0.03, -0.01), "driving_score": d(0.0, -0.1, 0.1)},
        },
    }
    assert lead_sentence(differences) == (
        "CRCHFL against the other schemes, paired by seed: "
        "balanced accuracy over HFL ahead beyond noise at 5 GB, not distinguishable at 95 % at 2.5 GB; "
        "over SFL ahead beyond noise at 2.5 GB, behind beyond noise at 5 GB; "
        "closed-loop driving score over HFL ahead beyond noise at 2.5 GB, behind beyond noise at 5 GB; "
        "over SFL not distinguishable at 95 % at 5 GB."
    )
    assert lead_sentence({}) == "CRCHFL against the other schemes by budget: no paired seeds to compare."
