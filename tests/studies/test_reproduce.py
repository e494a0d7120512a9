"""`reproduce`: run configs, part plan, resume rules, and a tiny end-to-end reproduction of every scheme."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from crchfl_sumo.core.config import deep_merge, toml_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.studies.reproduce import RAY_PART, best_seed, reproduce, reproduce_command
from crchfl_sumo.studies.reproduce_plan import (
    ReproduceConfig,
    load_reproduce_config,
    plan_parts,
    run_config,
    run_mapping,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def test_deep_merge_merges_tables_and_replaces_values():
    base = {"a": 1, "t": {"x": 1, "y": {"z": 2}}, "l": [1]}
    assert deep_merge(base, {"t": {"y": {"w": 3}}, "l": [2], "b": 4}) == {
        "a": 1, "t": {"x": 1, "y": {"z": 2, "w": 3}}, "l": [2], "b": 4,
    }
    assert base == {"a": 1, "t": {"x": 1, "y": {"z": 2}}, "l": [1]}  # not modified


def test_run_mapping_lays_overrides_data_and_seed_over_the_builtin():
    config = ReproduceConfig(run={"ledger": {"budget_gb": 10.0}, "clock": {"kind": "constant"}})
    mapping = run_mapping(config, "crchfl", 7, Path("/data/x"), fix_edge_interval=3)
    run = run_config(mapping, "test")
    assert run.dataset == "/data/x" and run.scenario == "paper"
    assert run.federation.scheme == "crchfl" and run.federation.seed == 7 and run.federation.use_plan
    assert run.allocation.fix_edge_interval == 3
    assert run.ledger.budget_gb == 10.0 and run.ledger.model_size == "nominal"  # the built-in's keys stay
    assert run.clock.kind == "constant"
    assert run_config(run_mapping(config, "sfl", 0, Path("d")), "t").federation.scheme == "sfl"


@pytest.mark.parametrize(
    "mapping, match",
    [
        ({"seeds": 0}, "reproduce.seeds"),
        ({"schemes": ["crchfl", "fedprox"]}, "reproduce.schemes"),
        ({"ablation_edge_intervals": [1, 2]}, "ablation_edge_intervals"),
        ({"run": {"dataset": "x"}}, "reproduce.run.dataset"),
        ({"run": {"federation": {"seed": 1}}}, "reproduce.run.federation.seed"),
        ({"run": {"ledger": {"budget_gb": -1.0}}}, "budget_gb"),
        ({"run": {"federation": {"typo": 1}}}, "typo"),
        ({"steer_decoding": "mean"}, "reproduce.steer_decoding: use one of auto"),
        ({"centralized_epochs": 0, "dagger_iterations": 1}, "reproduce.dagger_iterations: DAgger refines"),
        ({"dagger_iterations": -1}, "reproduce.dagger_iterations"),
        ({"dagger": {"tasks": ["parking"]}}, "parking"),
    ],
)
def test_config_errors_name_the_key(tmp_path, mapping, match):
    path = tmp_path / "r.toml"
    path.write_text(toml_text(mapping))
    with pytest.raises(CrchflError, match=match):
        load_reproduce_config(path)


def test_presets_and_seed_override():
    quick, full = load_reproduce_config("quick"), load_reproduce_config("full", seeds=4)
    assert quick.name == "quick" and quick.seed_list == [0] and quick.ablation_seed_list == []
    assert quick.steer_decoding == "argmax" and full.steer_decoding == "auto"
    assert full.seed_list == [0, 1, 2, 3] and full.ablation_seed_list == [0, 1, 2]
    assert sum(sum(t.train_samples) for t in full.generate.dataset.towns) == 12584  # the paper's split
    keys = [p.key for p in plan_parts(quick)]
    assert keys == ["data", "centralized/seed-0", "runs/crchfl/seed-0", "runs/hfl/seed-0", "runs/sfl/seed-0"]
    assert [p.key for p in plan_parts(full)][-3:] == ["ablation/ie-2/seed-2", "ablation/ie-3/seed-2", "ablation/ie-4/seed-2"]
    # the full mode has the budget curve (CRCHFL again at each smaller budget); quick keeps one budget
    assert full.budgets_gb == (2.5, 5.0, 10.0, 20.0) and quick.budgets_gb == ()
    assert "budget_curve/runs/crchfl/gb-10/seed-3" in [p.key for p in plan_parts(full)]


def test_the_benchmark_drives_the_best_seed_or_every_seed():
    from crchfl_sumo.studies.reproduce_plan import bench_parts

    config = ReproduceConfig(seeds=2, schemes=("crchfl", "hfl"), bench_episodes=1)
    assert [(p.key, p.scheme, p.seed) for p in bench_parts(config)] == [
        ("drive_bench/crchfl", "crchfl", None), ("drive_bench/hfl", "hfl", None),
        ("drive_bench/centralized", "centralized", None), ("drive_bench/reference", "reference", None),
    ]
    every = ReproduceConfig(seeds=2, schemes=("crchfl",), bench_episodes=1, bench_all_seeds=True, first_seed=3)
    assert [p.key for p in bench_parts(every)] == [
        "drive_bench/crchfl/seed-3", "drive_bench/crchfl/seed-4", "drive_bench/centralized/seed-3",
        "drive_bench/centralized/seed-4", "drive_bench/reference",
    ]
    assert bench_parts(ReproduceConfig(bench_episodes=0, bench_all_seeds=True)) == []


def test_a_seed_names_its_own_model():
    from crchfl_sumo.studies.reproduce import model_for

    assert model_for(Path("r"), "hfl", 2) == Path("r/runs/hfl/seed-2/best_model.pt")
    assert model_for(Path("r"), "centralized", 0) == Path("r/centralized/seed-0/checkpoint.pt")
    assert model_for(Path("r"), "centralized_dagger", 1) == Path("r/centralized_dagger/seed-1/checkpoint.pt")


def test_a_run_whose_vehicles_labelled_with_dagger_drives_its_last_model(tmp_path):
    import json

    from crchfl_sumo.studies.reproduce import model_for

    for seed, summary in ((0, {"balanced_accuracy": 0.7, "dagger_rounds": [3, 6]}), (1, {"balanced_accuracy": 0.6}),
                          (2, {"balanced_accuracy": 0.5, "dagger_rounds": []})):
        (tmp_path / "runs" / "hfl" / f"seed-{seed}").mkdir(parents=True)
        (tmp_path / "runs" / "hfl" / f"seed-{seed}" / "summary.json").write_text(json.dumps(summary))
    runs = tmp_path / "runs" / "hfl"
    # the best offline round cannot judge what the labels teach: a [dagger] run's last cloud model drives
    assert model_for(tmp_path, "hfl", 0) == runs / "seed-0" / "final_model.pt"
    assert model_for(tmp_path, "hfl") == runs / "seed-0" / "final_model.pt"  # the seed of the best balanced accuracy
    assert model_for(tmp_path, "hfl", 1) == runs / "seed-1" / "best_model.pt"
    assert model_for(tmp_path, "hfl", 2) == runs / "seed-2" / "best_model.pt"  # no labelling round happened


def test_dagger_refines_every_centralized_seed_and_drives_beside_it():
    from crchfl_sumo.studies.reproduce_plan import bench_parts, dagger_parts, drive_labels

    config = ReproduceConfig(seeds=2, schemes=("crchfl",), bench_episodes=1, bench_all_seeds=True, dagger_iterations=1)
    assert [(p.key, p.kind, p.seed) for p in dagger_parts(config)] == [
        ("centralized_dagger/seed-0", "dagger", 0), ("centralized_dagger/seed-1", "dagger", 1),
    ]
    assert drive_labels(config) == ["crchfl", "centralized", "centralized_dagger", "reference"]
    assert "drive_bench/centralized_dagger/seed-1" in [p.key for p in bench_parts(config)]
    assert dagger_parts(ReproduceConfig()) == [] and "centralized_dagger" not in drive_labels(ReproduceConfig())
    # the full preset refines its centralized models once (docs/model.md, "Clearing the junction"); quick has no time
    full = load_reproduce_config("full")
    assert full.dagger_iterations == 1 and load_reproduce_config("quick").dagger_iterations == 0
    assert [p.key for p in dagger_parts(full)] == [f"centralized_dagger/seed-{s}" for s in (0, 1, 2)]
    assert "drive_bench/centralized_dagger/seed-2" in [p.key for p in bench_parts(full)]


def test_best_seed():
    assert best_seed({0: {"balanced_accuracy": 0.5}, 1: {"balanced_accuracy": 0.7}, 2: {"balanced_accuracy": 0.7}}) == 1
    assert best_seed({0: {"balanced_accuracy": None}, 3: {"balanced_accuracy": 0.1}}) == 3
    assert best_seed({0: {"best_accuracy": 0.9}, 1: {"best_accuracy": 0.1}}, key="best_accuracy") == 0
    with pytest.raises(CrchflError):
        best_seed({})


TINY = """
name = "tiny"
scenario = "paper"
seeds = 2
ablation_seeds = 1
ablation_edge_intervals = [2, 3]
centralized_epochs = 1
dagger_iterations = 1
dagger_epochs = 1
drive_routes = ["town01_right_left"]
drive_max_s = 3.0
bench_episodes = 1
bench_towns = ["town02"]
bench_tasks = ["straight"]

[drive]
warmup_s = 0.0

[dagger]
tasks = ["straight"]
episodes = 1
max_s = 3.0
corrections_only = false

[generate.dataset]
[[generate.dataset.towns]]
town = "town01"
train_samples = [3, 3]
test_samples = [3]
[[generate.dataset.towns]]
town = "town02"
train_samples = [3, 2, 2]
test_samples = [3]

[generate.raster.camera]
height_px = 48
width_px = 64

[run.model]
image_height = 48
image_width = 64
[run.train]
device = "cpu"
[run.federation]
pretrain_epochs = 1
[run.ledger]
budget_gb = 5.0
[run.clock]
kind = "constant"
"""


@pytest.mark.slow
def test_tiny_reproduction_of_every_scheme_end_to_end(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    out = tmp_path / "results"
    seen = []
    folder, summary = reproduce_command(
        out_dir=out, config_path=path, progress=lambda u: seen.append((u.done, u.total, u.detail["part"]))
    )
    assert folder == out
    assert seen[0] == (0, 25, "data") and seen[-1] == (25, 25, "report")  # 1 + 2 + 6 + 2 + 2 + 6 + 6 parts
    assert json.loads((out / "summary.json").read_text()) == json.loads(json.dumps(summary))
    # 5 GB of 150 MB models: SFL 10 transfers a round (3 rounds), HFL 14 (2 rounds)
    assert summary["schemes"]["sfl"]["cloud_rounds"]["values"] == [3, 3]
    assert summary["schemes"]["hfl"]["cloud_rounds"]["values"] == [2, 2]
    for scheme in ("crchfl", "hfl", "sfl"):
        stats = summary["schemes"][scheme]
        assert stats["seeds"] == [0, 1] and stats["best_accuracy"]["n"] == 2
        assert 0.0 <= stats["best_accuracy"]["mean"] <= 1.0 and stats["best_accuracy"]["std"] is not None
        assert stats["consumed_bytes"]["mean"] <= stats["budget_bytes"]
        drive = stats["closed_loop"]["town01_right_left"]
        assert drive["model"].endswith("best_model.pt") and 0.0 <= drive["completion"] <= 1.0
        run_summary = json.loads((out / "runs" / scheme / "seed-1" / "summary.json").read_text())
        assert run_summary["scheme"] == scheme and run_summary["stop_reason"] in ("budget", "cloud_rounds")
        assert tomllib.loads((out / "configs" / f"runs_{scheme}_seed-1.toml").read_text())["federation"]["seed"] == 1
    labels = {"crchfl", "hfl", "sfl", "centralized", "centralized_dagger", "reference"}
    assert set(summary["closed_loop"]["town01_right_left"]) == labels
    assert [a["hyper"]["edge_interval"] for a in summary["ablation"].values()] == [2, 3]
    assert summary["centralized"]["best_accuracy"]["n"] == 2
    assert set(summary["figures"]) == {"fig3", "fig4", "fig7", "centralized", "fig5_town01_right_left"}
    for figure in summary["figures"].values():
        assert (out / figure).is_file()
    timings = json.loads((out / "timings.json").read_text())
    assert len(timings) == 25 and all(t["wall_s"] >= 0 for t in timings.values())
    # the benchmark: every model and the reference, results[TOWN][TASK] with the keys other tools read
    bench = summary["drive_bench"]
    assert list(bench) == ["crchfl", "hfl", "sfl", "centralized", "centralized_dagger", "reference"]
    # DAgger refined each seed's centralized model: its drives' labels added to the data set's 13 samples
    for seed in (0, 1):
        (record,) = json.loads((out / "centralized_dagger" / f"seed-{seed}" / "summary.json").read_text())["iterations"]
        assert record["expert_samples"] > 0 and record["training_samples"] == 13 + record["expert_samples"]
    for results in bench.values():
        assert set(results["town02"]["straight"]) >= {"episodes", "success_rate", "route_completion",
                                                      "driving_score", "infractions_per_km"}
        assert results["town02"]["straight"]["episodes"] == 1
    assert bench["reference"]["town02"]["straight"]["success_rate"] == 1.0
    assert "## Closed-loop benchmark" in (out / "report.md").read_text()
    # balanced accuracy beside accuracy, and the always-straight baseline on the same test set
    assert set(summary["baselines"]["always_straight"]) >= {"accuracy", "balanced_accuracy"}
    for stats in (*summary["schemes"].values(), summary["centralized"]):
        assert stats["balanced_accuracy"]["n"] == 2 and 0.0 <= stats["balanced_accuracy"]["mean"] <= 1.0

    # finished parts are not redone; the report is rebuilt the same
    with pytest.raises(CrchflError, match="--resume"):
        reproduce_command(out_dir=out, config_path=path)
    report = (out / "report.md").read_text()
    _, again = reproduce_command(out_dir=out, config_path=path, resume=True)
    assert json.loads((out / "timings.json").read_text()) == timings
    assert again == summary and (out / "report.md").read_text() == report
    # resuming with other settings is refused
    with pytest.raises(CrchflError, match=r"other settings \(its 'config' differs in seeds:"):
        reproduce_command(out_dir=out, config_path=path, seeds=3, resume=True)
    # so is a folder started before a data set setting had its present default (its config lacks the key)
    started = json.loads((out / "reproduce.json").read_text())
    red_share = started["config"]["generate"]["dataset"].pop("recovery_red_share")
    (out / "reproduce.json").write_text(json.dumps(started))
    with pytest.raises(CrchflError, match=r"differs in generate\.dataset\.recovery_red_share:"):
        reproduce_command(out_dir=out, config_path=path, resume=True)
    started["config"]["generate"]["dataset"]["recovery_red_share"] = red_share
    (out / "reproduce.json").write_text(json.dumps(started))
    # a run killed midway is not recorded as finished: it resumes from its checkpoint, to the same files
    metrics = (out / "runs" / "hfl" / "seed-0" / "metrics.jsonl").read_text()
    del timings["runs/hfl/seed-0"]
    (out / "timings.json").write_text(json.dumps(timings))
    reproduce(load_reproduce_config(path), out, resume=True)
    assert (out / "runs" / "hfl" / "seed-0" / "metrics.jsonl").read_text() == metrics
    assert "runs/hfl/seed-0" in json.loads((out / "timings.json").read_text())


def _training_parts_only(folder):
    """The tiny preset with one seed, no ablation, no DAgger and no drives, written to folder/tiny.toml."""
    text = TINY.replace("seeds = 2", "seeds = 1").replace("ablation_edge_intervals = [2, 3]", "ablation_edge_intervals = []")
    text = text.replace('drive_routes = ["town01_right_left"]', "drive_routes = []").replace("bench_episodes = 1", "bench_episodes = 0")
    text = text.replace("dagger_iterations = 1", "dagger_iterations = 0")
    path = folder / "tiny.toml"
    path.write_text(text)
    return path


@pytest.mark.slow
def test_parts_run_side_by_side_give_the_same_results(tmp_path):
    # one seed, no ablation, no drives: the data set, then 4 parts that --jobs 2 runs two at a time
    path = _training_parts_only(tmp_path)
    seen = []
    _, alone = reproduce_command(out_dir=tmp_path / "one", config_path=path)
    _, paired = reproduce_command(
        out_dir=tmp_path / "two", config_path=path, jobs=2, progress=lambda u: seen.append((u.done, u.detail["part"]))
    )
    for scheme in ("crchfl", "hfl", "sfl"):
        a, b = alone["schemes"][scheme], paired["schemes"][scheme]
        assert a["cloud_rounds"] == b["cloud_rounds"] and a["consumed_bytes"] == b["consumed_bytes"]
        assert a["best_accuracy"]["values"] == b["best_accuracy"]["values"]
        # equal on a 2-core machine (one thread either way); elsewhere the thread count may differ
        assert b["final_loss"]["values"] == pytest.approx(a["final_loss"]["values"], rel=1e-3)
    assert paired["centralized"]["best_accuracy"] == alone["centralized"]["best_accuracy"]
    # progress: the data set starts, then each of the 4 parts is reported as it finishes
    assert seen[0] == (0, "data") and [i for i, _ in seen[2:-1]] == [2, 3, 4, 5] and seen[-1] == (5, "report")
    timings = json.loads((tmp_path / "two" / "timings.json").read_text())
    assert [t["jobs"] for t in timings.values()] == [1, 2, 2, 2, 2]
    total = paired["running_time_s"]["total"]
    assert total["elapsed_s"] <= total["wall_s"] + 1e-9  # side by side: elapsed time below the sum of the parts
    with pytest.raises(CrchflError, match="--jobs"):
        reproduce(load_reproduce_config(path), tmp_path / "three", jobs=0)


@pytest.mark.slow
def test_ray_tasks_give_the_local_backends_summary(tmp_path):
    # the data set, then the centralized and the three schemes' parts
    path = _training_parts_only(tmp_path)
    _, local = reproduce_command(out_dir=tmp_path / "local", config_path=path)
    _, on_ray = reproduce_command(out_dir=tmp_path / "ray", config_path=path, backend="ray")
    # the same parts, the same folders, the same figures (one torch thread a part either way)
    for key in ("schemes", "differences", "gains", "baselines", "centralized", "ablation", "closed_loop"):
        assert on_ray[key] == local[key], key
    timings = json.loads((tmp_path / "ray" / "timings.json").read_text())
    assert sorted(timings) == sorted(json.loads((tmp_path / "local" / "timings.json").read_text()))
    assert {t["jobs"] for t in timings.values()} == {RAY_PART}
    with pytest.raises(CrchflError, match="--address"):
        reproduce_command(out_dir=tmp_path / "x", config_path=path, address="auto")


def _budget_curve_preset(folder):
    """Two seeds of the three schemes at 5 GB, the curve at 2.5 and 5 GB, every seed's model benchmarked once."""
    text = _training_parts_only(folder).read_text().replace("seeds = 1", "seeds = 2")
    text = text.replace("centralized_epochs = 1", "centralized_epochs = 0").replace("bench_episodes = 0", "bench_episodes = 1")
    text = text.replace('name = "tiny"', 'name = "tiny"\nbudgets_gb = [2.5, 5.0]\naccuracy_targets = [0.01, 1.0]\n'
                        "bench_all_seeds = true")
    path = folder / "curve.toml"
    path.write_text(text)
    return path


def test_the_budget_curve_plans_crchfl_again_and_reads_hfl_and_sfl_from_their_runs(tmp_path):
    from crchfl_sumo.studies.reproduce import budget_model_for
    from crchfl_sumo.studies.reproduce_plan import bench_parts

    config = load_reproduce_config(_budget_curve_preset(tmp_path))
    keys = [p.key for p in plan_parts(config)]
    assert keys[:7] == ["data", "runs/crchfl/seed-0", "runs/hfl/seed-0", "runs/sfl/seed-0", "runs/crchfl/seed-1",
                        "runs/hfl/seed-1", "runs/sfl/seed-1"]
    assert keys[7:] == ["budget_curve/runs/crchfl/gb-2.5/seed-0", "budget_curve/runs/crchfl/gb-2.5/seed-1"]
    runs = {scheme: run_config(run_mapping(config, scheme, 0, Path("d")), "t") for scheme in ("crchfl", "hfl", "sfl")}
    assert runs["crchfl"].ledger.marks_gb == () and runs["hfl"].ledger.marks_gb == runs["sfl"].ledger.marks_gb == (2.5,)
    assert run_config(run_mapping(config, "crchfl", 1, Path("d"), budget_gb=2.5), "t").ledger.budget_gb == 2.5
    budget_benches = [p.key for p in bench_parts(config) if p.budget_gb is not None]
    assert budget_benches == [f"budget_curve/drive_bench/{s}/gb-2.5/seed-{seed}"
                              for s in ("crchfl", "hfl", "sfl") for seed in (0, 1)]
    assert budget_model_for(config, Path("r"), "crchfl", 2.5, 1) == Path("r/budget_curve/runs/crchfl/gb-2.5/seed-1/best_model.pt")
    assert budget_model_for(config, Path("r"), "sfl", 2.5, 0) == Path("r/runs/sfl/seed-0/best_model_within_2.5gb.pt")
    # the budgets lie within the runs' budget, and every seed's model drives
    with pytest.raises(CrchflError, match="reproduce.budgets_gb: 10 exceeds the crchfl runs' budget_gb = 5"):
        ReproduceConfig(budgets_gb=(2.5, 10.0), run={"ledger": {"budget_gb": 5.0}}, bench_all_seeds=True)
    with pytest.raises(CrchflError, match="set bench_all_seeds = true"):
        ReproduceConfig(budgets_gb=(2.5,), bench_episodes=1)
    with pytest.raises(CrchflError, match="increasing, each once"):
        ReproduceConfig(budgets_gb=(5.0, 2.5), bench_all_seeds=True)


@pytest.mark.slow
def test_tiny_budget_curve_end_to_end(tmp_path):
    _, summary = reproduce_command(out_dir=tmp_path / "out", config_path=_budget_curve_preset(tmp_path))
    out = tmp_path / "out"
    curve = summary["budget_curve"]
    assert list(curve) == ["crchfl", "hfl", "sfl"] and all(list(points) == ["2.5", "5"] for points in curve.values())
    for scheme in ("crchfl", "hfl", "sfl"):
        top = curve[scheme]["5"]
        # the top of the curve is experiment B itself
        assert top["balanced_accuracy"]["values"] == summary["schemes"][scheme]["balanced_accuracy"]["values"]
        assert top["driving_score"]["n"] == 2 and top["balanced_accuracy"]["ci95"] is not None
        for key in ("balanced_accuracy", "driving_score"):
            assert set(curve[scheme]["2.5"][key]) >= {"mean", "ci95", "n"}
    for scheme in ("hfl", "sfl"):  # read from the 5 GB run's mark
        for seed in (0, 1):
            run = json.loads((out / "runs" / scheme / f"seed-{seed}" / "summary.json").read_text())
            mark = run["budget_marks"]["2.5"]
            index = curve[scheme]["2.5"]["balanced_accuracy"]["seeds"].index(seed)
            assert curve[scheme]["2.5"]["balanced_accuracy"]["values"][index] == mark["balanced_accuracy"]
            assert mark["consumed_bytes"] <= 2.5 * 1024**3
    crchfl_small = json.loads((out / "budget_curve/runs/crchfl/gb-2.5/seed-0/summary.json").read_text())
    assert crchfl_small["budget_bytes"] == 2.5 * 1024**3 and crchfl_small["consumed_bytes"] <= 2.5 * 1024**3
    assert set(summary["budget_differences"]) == {"crchfl-hfl", "crchfl-sfl"}
    assert summary["budget_differences"]["crchfl-hfl"]["2.5"]["balanced_accuracy"]["n"] == 2
    # bytes to accuracy, by hand from each seed's metrics: the GB of its first evaluation at the target,
    # the mean over seeds only where both seeds reached it
    for scheme, targets in summary["bytes_to_accuracy"].items():
        for target in ("0.01", "1.0"):
            by_seed = []
            for seed in (0, 1):
                lines = (out / "runs" / scheme / f"seed-{seed}" / "metrics.jsonl").read_text().splitlines()
                reached = [json.loads(line) for line in lines if (json.loads(line).get("balanced_accuracy") or 0) >= float(target)]
                by_seed.append(reached[0]["consumed_bytes"] / 1024**3 if reached else None)
            assert list(summary["bytes_to_accuracy_seeds"][scheme][target].values()) == by_seed
            assert targets[target] == (None if None in by_seed else pytest.approx(sum(by_seed) / 2))
    report = (out / "report.md").read_text()
    assert "## Experiment E" in report and "CRCHFL against the other schemes, paired by seed: balanced accuracy over HFL" in report
    assert (out / summary["figures"]["budget"]).is_file()


def test_a_reproduction_in_another_scenario_shares_the_samples_among_its_vehicles(grid_dir):
    from crchfl_sumo.studies.reproduce_plan import for_scenario

    quick = load_reproduce_config("quick")
    path = str(grid_dir / "grid.sumocfg")
    config = for_scenario(quick, path)  # a plain .sumocfg: one town, 5 data and 1 test vehicle added
    assert config.scenario == str(Path(path).resolve())
    (town,) = config.generate.dataset.towns
    # the quick preset's 315 training and 208 test samples, shared: 315 // 5 and 208 // 1
    assert (town.town, town.train_samples, town.test_samples) == ("grid", (63,) * 5, (208,))
    assert config.drive_routes == () and config.bench_towns == (str(Path(path).resolve()),)
    assert run_config(run_mapping(config, "hfl", 0, Path("d")), "t").scenario == str(Path(path).resolve())
    # a scenario with the preset's towns keeps its split, routes and benchmark
    linked = for_scenario(quick, "paper_linked")
    assert linked.scenario == "paper_linked" and linked.generate == quick.generate
    assert linked.drive_routes == quick.drive_routes and linked.bench_towns == quick.bench_towns
