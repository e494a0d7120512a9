"""`crchfl-sumo run`: results folder, checkpoints, kill-and-resume equality, SUMO clock."""

from __future__ import annotations

import contextlib
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from crchfl_sumo.core.config import from_mapping, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import LINEAR_RACK, ExpertConfig
from crchfl_sumo.federation.run import run_command, run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig, builtin_experiments, load_run_config
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.learning.checkpoint import load_checkpoint
from crchfl_sumo.links.clock import ScriptedClock, Segment

from helpers import PAPER_VEHICLES, Killed, SumTrainer, kill_after, result_files, run_config, write_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data"), PAPER_VEHICLES)


def test_run_command_writes_the_results_folder(tmp_path, dataset):
    path = tmp_path / "run.toml"
    path.write_text(
        f'dataset = "{dataset}"\n[federation]\nscheme = "crchfl"\npretrain_batch = 3\npretrain_epochs = 1\n'
        'edge_interval = 1\ncloud_rounds = 1\n[ledger]\nnominal_model_mb = 10.0\n'
        '[model]\nimage_height = 48\nimage_width = 64\n[train]\ndevice = "cpu"\n[clock]\nkind = "constant"\n'
    )
    seen = []
    summary = run_command(path, tmp_path / "out", progress=seen.append)
    out = tmp_path / "out"
    for name in ("config.toml", "config.json", "federation_state.pt", "best_model.pt", "final_model.pt"):
        assert (out / name).is_file(), name
    assert json.loads((out / "summary.json").read_text()) == summary
    for key in ("scheme", "cloud_rounds", "edge_aggregations", "consumed_bytes", "budget_bytes", "best_accuracy",
                "final_accuracy", "best_loss", "sim_time_s", "balanced_accuracy", "final_balanced_accuracy"):
        assert key in summary
    assert 0.0 <= summary["balanced_accuracy"] <= 1.0
    # the always-straight baseline on the 4 test samples of write_dataset (random classes 0..6)
    assert set(summary["baselines"]["always_straight"]) >= {"accuracy", "balanced_accuracy"}
    assert (summary["scheme"], summary["cloud_rounds"], summary["edge_aggregations"]) == ("crchfl", 1, 1)
    lines = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [m["stage"] for m in lines] == ["I", "II", "III"]
    assert lines[-1]["consumed_bytes"] == summary["consumed_bytes"]
    assert lines[-1]["wireless_bytes"] + lines[-1]["wireline_bytes"] == summary["consumed_bytes"]
    assert 0.0 <= lines[-1]["accuracy"] <= 1.0
    assert len(lines[-1]["confusion"]) == 7 and sum(map(sum, lines[-1]["confusion"])) == 4  # every test sample
    # one update a loop step, counting the steps; the last shows the finished round and the budget
    assert [u.stage for u in seen] == ["step"] * len(seen) and [u.done for u in seen] == list(range(1, len(seen) + 1))
    postfix = seen[-1].detail
    assert postfix["round"] == "1/1" and postfix["GB"].endswith("/20.00") and postfix["loss"] != "-"
    model = load_checkpoint(out / "best_model.pt")
    assert model.model_config.image_height == 48
    # the data set's camera settings travel with the model, for the drives
    manifest = json.loads((Path(dataset) / "manifest.json").read_text())
    assert model.extra["camera"] == manifest["camera"]
    # and the expert's settings, whose steering rack the drive's dynamics steer through
    stored = manifest["labels"].get("expert", {})  # this hand-made data set names none: the defaults, linear rack
    assert model.extra["expert"] == {**to_mapping(ExpertConfig()), **LINEAR_RACK, **stored}
    with pytest.raises(CrchflError, match="--resume"):
        run_command(path, out)
    # resuming a finished run changes nothing
    before = result_files(out)
    run_command(path, out, resume=True)
    assert result_files(out) == before


def test_a_run_on_lane_change_data_gives_its_network_the_lane_change_heads(tmp_path):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(8, 8, 8, 8, 8), commands=6, seed=3)
    config = from_mapping(RunConfig, run_config(data, cloud_rounds=1))
    assert config.model.commands is None
    summary = run_federation_dir(config, read_inputs(config), tmp_path / "run")
    assert summary["model"]["commands"] == 6
    checkpoint = load_checkpoint(tmp_path / "run" / "final_model.pt")
    assert checkpoint.model_config.num_commands == 6
    assert sum(k.startswith("branch_steer.heads.") and k.endswith(".0.weight") for k in checkpoint.state_dict) == 6
    # a setting given stays: 4 heads, which read the lane changes as follow
    four = from_mapping(RunConfig, {**run_config(data, cloud_rounds=1), "model": {
        "image_height": 48, "image_width": 64, "commands": 4}})
    assert run_federation_dir(four, read_inputs(four), tmp_path / "four")["model"]["commands"] == 4


def test_torch_run_killed_and_resumed_ends_like_an_uninterrupted_one(tmp_path, dataset):
    config = from_mapping(
        RunConfig, run_config(dataset, scheme="crchfl", pretrain_batch=4, pretrain_epochs=1, cloud_interval=2, cloud_rounds=1)
    )
    inputs = read_inputs(config)
    whole = run_federation_dir(config, inputs, tmp_path / "whole")
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", after_checkpoint=kill_after(2))
    resumed = run_federation_dir(config, inputs, tmp_path / "killed", resume=True)
    assert resumed == whole
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")
    a = load_checkpoint(tmp_path / "whole" / "final_model.pt").state_dict
    b = load_checkpoint(tmp_path / "killed" / "final_model.pt").state_dict
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("kill_at", [1, 2, 4, 5])  # 5: after the final checkpoint
def test_kill_at_any_step_and_resume_gives_the_same_files(tmp_path, dataset, kill_at):
    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2))
    inputs = read_inputs(config)
    run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), after_checkpoint=kill_after(kill_at))
    run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")


def test_a_folder_whose_state_was_checkpoint_pt_resumes_under_todays_name(tmp_path, dataset):
    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2))
    inputs = read_inputs(config)
    run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    old = tmp_path / "old"
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, old, trainer=SumTrainer(), after_checkpoint=kill_after(3))
    # the folder as runs wrote it before the state had a name of its own
    (old / "federation_state.pt").rename(old / "checkpoint.pt")
    (old / "federation_state.prev.pt").rename(old / "checkpoint.prev.pt")
    with pytest.raises(CrchflError, match="--resume"):
        run_federation_dir(config, inputs, old, trainer=SumTrainer())
    run_federation_dir(config, inputs, old, trainer=SumTrainer(), resume=True)
    assert result_files(old) == result_files(tmp_path / "whole")
    assert not (old / "checkpoint.pt").exists() and not (old / "checkpoint.prev.pt").exists()


def test_resume_with_other_settings_is_refused(tmp_path, dataset):
    config = from_mapping(RunConfig, run_config(dataset))
    inputs = read_inputs(config)
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "out", trainer=SumTrainer(), after_checkpoint=kill_after(1))
    other = from_mapping(RunConfig, run_config(dataset, edge_interval=3))
    with pytest.raises(CrchflError, match=r"other settings or data \(they differ in "
                       r"config\.federation\.edge_interval, hyper\.edge_interval\)"):
        run_federation_dir(other, inputs, tmp_path / "out", trainer=SumTrainer(), resume=True)


def test_a_run_is_not_continued_in_another_precision(tmp_path, dataset):
    # config.json records the precision the run trains in ("auto" decided), so a run started in one
    # precision is not continued in the other, e.g. on a machine where "auto" means the other.
    mapping = run_config(dataset)
    trained = from_mapping(RunConfig, {**mapping, "train": {**mapping["train"], "precision": "fp32"}})
    inputs = read_inputs(trained)
    with pytest.raises(Killed):
        run_federation_dir(trained, inputs, tmp_path / "out", trainer=SumTrainer(), after_checkpoint=kill_after(1))
    assert json.loads((tmp_path / "out" / "config.json").read_text())["config"]["train"]["precision"] == "fp32"
    other = from_mapping(RunConfig, {**mapping, "train": {**mapping["train"], "precision": "bf16"}})
    with pytest.raises(CrchflError, match=r'trained in fp32; .* continue it in bf16\. Set \[train\] precision = "fp32"'):
        run_federation_dir(other, inputs, tmp_path / "out", trainer=SumTrainer(), resume=True)
    both = from_mapping(RunConfig, {**mapping, "train": {**mapping["train"], "precision": "bf16"},
                                    "federation": {**mapping["federation"], "edge_interval": 3}})
    with pytest.raises(CrchflError, match="written by a run with other settings or data"):  # not only the precision
        run_federation_dir(both, inputs, tmp_path / "out", trainer=SumTrainer(), resume=True)
    run_federation_dir(trained, inputs, tmp_path / "out", trainer=SumTrainer(), resume=True)  # the same: it goes on
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["stop_reason"]


def test_config_errors_name_the_key(tmp_path, dataset):
    with pytest.raises(CrchflError, match="data_mode"):
        from_mapping(RunConfig, {**run_config(dataset), "data_mode": "online"})  # needs the SUMO clock
    with pytest.raises(CrchflError, match="data_mode"):
        from_mapping(RunConfig, {**run_config(dataset), "data_mode": "streaming"})
    with pytest.raises(CrchflError, match="federation: unknown key"):
        from_mapping(RunConfig, {**run_config(dataset), "federation": {"edge_intervall": 2}})
    bad = from_mapping(RunConfig, {**run_config(dataset), "model": {"image_height": 64, "image_width": 128}})
    with pytest.raises(CrchflError, match="image_height"):
        read_inputs(bad)
    other = write_dataset(tmp_path / "other", [("v0", "town01", "edge01")], samples=(1,))
    with pytest.raises(CrchflError, match="not data vehicles of scenario 'town02'"):
        read_inputs(from_mapping(RunConfig, {**run_config(other), "scenario": "town02", "clock": {"kind": "sumo"}}))


def test_use_plan_asks_the_optimizer_for_this_runs_topology(tmp_path, dataset):
    config = from_mapping(RunConfig, {**run_config(dataset, scheme="crchfl", use_plan=True, edge_interval=2, cloud_rounds=0),
                                      "ledger": {"nominal_model_mb": 150.0, "budget_gb": 5.0}})
    summary = run_federation_dir(config, read_inputs(config), tmp_path / "out", trainer=SumTrainer())
    plan = json.loads((tmp_path / "out" / "config.json").read_text())["plan"]
    assert plan is not None and summary["hyper"]["edge_interval"] == plan["edge_interval"]
    assert summary["hyper"]["pretrain_batch"] <= 10  # the run's vehicles hold 10 samples
    assert summary["cloud_rounds"] == plan["cloud_rounds"]
    # the plan's timing is the run's: the constant clock's rate, the loop's compute model on the largest shard
    assert plan["wireless_rate_bps"] == config.clock.constant_rate_bps
    assert plan["epoch_time_s"] == pytest.approx(3 * config.federation.compute_s_per_sample)
    # a planned run resumes too: the plan is the same when made again
    with pytest.raises(Killed):
        run_federation_dir(config, read_inputs(config), tmp_path / "killed", trainer=SumTrainer(),
                           after_checkpoint=kill_after(2))
    run_federation_dir(config, read_inputs(config), tmp_path / "killed", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "out")


def test_builtin_experiments_are_the_three_schemes():
    configs = {name: load_run_config(path) for name, path in builtin_experiments().items()}
    assert {name: c.federation.scheme for name, c in configs.items()} == {"crchfl": "crchfl", "hfl": "hfl", "sfl": "sfl"}
    assert configs["crchfl"].federation.use_plan
    assert all(c.ledger.budget_gb == 20.0 and c.ledger.rule == "paper" for c in configs.values())


# ------------------------------------------------------------------ SUMO clock


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["hfl", "sfl"])
def test_sumo_clock_run_is_deterministic_and_resumes_exactly(tmp_path, dataset, scheme):
    mapping = run_config(dataset, scheme=scheme, cloud_rounds=2, compute_s_per_sample=5.0, deadline_s=120.0)
    mapping["clock"] = {"kind": "sumo"}
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)
    summary = run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    assert summary["cloud_rounds"] == 2
    ledger = [json.loads(line) for line in (tmp_path / "whole" / "ledger.jsonl").read_text().splitlines()[1:]]
    wireless = [r for r in ledger if r["link"] == "wireless"]
    assert wireless and all(r["end_s"] > r["start_s"] for r in wireless)
    # moving vehicles see different rates: the uploads of one round do not all take the same time
    first = [r["end_s"] - r["start_s"] for r in wireless if r["direction"] == "uplink" and r["cloud_round"] == 1]
    assert len(set(np.round(first, 6))) > 1
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), after_checkpoint=kill_after(1))
    run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")


# ------------------------------------------------------------------ online data mode


def _straight_frames(seconds: float, step_s: float = 0.25):
    from crchfl_sumo.sumo.frame import make_frame

    frames = []
    for k in range(1, int(seconds / step_s) + 1):
        t = k * step_s
        frames.append(make_frame(t, ids=["a"], x_m=[10.0 + 8.0 * t], y_m=[0.0], speed_mps=[8.0]))
    return frames


def test_online_collector_labels_after_the_look_ahead_and_keeps_the_newest(grid_dir):
    from crchfl_sumo.data.expert import ExpertConfig, expert_labels, tracks_from_frames
    from crchfl_sumo.data.online import OnlineCollector
    from crchfl_sumo.data.recording import FUTURE_S
    from crchfl_sumo.data.settings import OnlineConfig
    from crchfl_sumo.vision.camera import CameraConfig
    from crchfl_sumo.vision.raster import RasterConfig

    raster = RasterConfig(camera=CameraConfig(height_px=48, width_px=64))
    collector = OnlineCollector(
        grid_dir / "grid.net.xml", ["a"], {"a": 2.0}, 0.5, 0.25, raster=raster, config=OnlineConfig(max_samples=6)
    )
    frames = _straight_frames(20.0)
    for frame in frames:
        collector.observe(frame)
    assert collector.collected("a", 2.0 + FUTURE_S) is None  # nothing after 2 s is labelled yet
    early = collector.collected("a", 4.0 + FUTURE_S)
    assert len(early) == 4  # 2.5, 3.0, 3.5, 4.0 s
    late = collector.collected("a", 20.0)
    assert len(late) == 6  # the newest six of 2.5 .. 10.0 s
    actions, steer_class = expert_labels(tracks_from_frames(frames)["a"], ExpertConfig())
    rows = [round(t / 0.25) - 1 for t in (7.5, 8.0, 8.5, 9.0, 9.5, 10.0)]
    assert np.array_equal(late.actions.numpy(), actions[rows])
    assert np.array_equal(late.steer_class.numpy(), steer_class[rows])
    assert late.images.shape == (6, 4, 48, 64, 3)


@pytest.mark.slow
def test_online_mode_grows_the_vehicles_data_and_resumes_exactly(tmp_path):
    root = tmp_path / "data"
    write_dataset(root, PAPER_VEHICLES[:1] + PAPER_VEHICLES[2:3], samples=(2, 2))
    manifest = root / "manifest.json"
    text = json.loads(manifest.read_text())
    text["camera"] = {"raster": {"camera": {"height_px": 48, "width_px": 64}}}
    manifest.write_text(json.dumps(text))
    mapping = run_config(root, scheme="hfl", cloud_rounds=3, compute_s_per_sample=2.0)
    mapping.update(data_mode="online", online={"max_samples": 10}, clock={"kind": "sumo"})
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)
    run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    lines = [json.loads(line) for line in (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()]
    samples = [m["samples"] for m in lines if m["stage"] == "II"]
    assert samples[0] == 4 and samples[-1] > samples[0] and samples[-1] <= 4 + 2 * 10
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), after_checkpoint=kill_after(2))
    run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")


def test_a_planned_run_reads_the_calibration_file(tmp_path, dataset):
    calibration = tmp_path / "calibration.toml"
    calibration.write_text("[allocation]\nalpha = 0.0\ngamma = 0.5\nd = 1.0\n")  # uploaded samples worth nothing
    config = from_mapping(RunConfig, {**run_config(dataset, scheme="crchfl", use_plan=True, edge_interval=2, cloud_rounds=0),
                                      "ledger": {"nominal_model_mb": 150.0, "budget_gb": 5.0},
                                      "allocation": {"calibration_file": str(calibration)}})
    run_federation_dir(config, read_inputs(config), tmp_path / "out", trainer=SumTrainer())
    plan = json.loads((tmp_path / "out" / "config.json").read_text())["plan"]
    # objective = alpha x + gamma s (T - d / (I_e I_c)) with the file's weights and the run's s = 10 samples
    t, ie, ic = plan["cloud_rounds"], plan["edge_interval"], plan["cloud_interval"]
    assert plan["objective"] == pytest.approx(0.5 * 10 * (t - 1.0 / (ie * ic)))


def test_the_bytes_a_step_writes_do_not_grow_with_the_record_count(tmp_path, dataset):
    # 12 edge aggregations (a cloud one every second); at every checkpoint, note what the
    # step wrote: the checkpoint, the derived files (fixed size), what the logs grew by.
    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=6))
    inputs = read_inputs(config)
    out = tmp_path / "run"
    logs = ("ledger.jsonl", "metrics.jsonl", "stragglers.jsonl")
    seen = []

    def note(state):
        texts = {name: (out / name).read_bytes() for name in logs}
        rewritten = sum((out / name).stat().st_size for name in ("federation_state.pt", "summary.json", "final_model.pt")
                        if (out / name).exists())
        seen.append((len(state.records), texts, rewritten))

    run_federation_dir(config, inputs, out, trainer=SumTrainer(), after_checkpoint=note)
    assert len(seen) == 13  # 12 aggregation steps and the one that stops
    for (_, before, _), (_, after, _) in itertools.pairwise(seen):
        for name in logs:  # append-only: every log starts with what it held a step before
            assert after[name].startswith(before[name]), name
    written = [rewritten + sum(len(texts[n]) - len(prev[n]) for n in logs)
               for (_, prev, _), (_, texts, rewritten) in itertools.pairwise(seen)]
    records = [count for count, _, _ in seen]
    assert records[11] >= 5 * records[1]
    # steps 2 .. 12 alternate edge-only and edge + cloud aggregations: compare like with like
    assert max(written[1:11:2]) - min(written[1:11:2]) <= 64
    assert max(written[2:11:2]) - min(written[2:11:2]) <= 64
    assert (out / "ledger.jsonl").read_text().count("\n") == records[-1] + 1  # the header and every record


def test_a_steps_files_are_written_while_the_next_step_runs(tmp_path, dataset, monkeypatch):
    # step 1's save blocks until the loop starts step 2: with the save in the loop, step 2 would never start
    import threading

    from crchfl_sumo.federation.loop import Federation

    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=1))
    inputs = read_inputs(config)
    run_federation_dir(config, inputs, tmp_path / "plain", trainer=SumTrainer())
    second_step_started = threading.Event()
    step = Federation.step

    def noting_step(self, state):
        if state.steps == 1:  # the state after step 1: this call computes step 2
            second_step_started.set()
        return step(self, state)

    waited = []

    def hold(state):
        if state.steps == 1:
            waited.append(second_step_started.wait(30))

    monkeypatch.setattr(Federation, "step", noting_step)
    run_federation_dir(config, inputs, tmp_path / "held", trainer=SumTrainer(), after_checkpoint=hold)
    assert waited == [True]
    assert result_files(tmp_path / "held") == result_files(tmp_path / "plain")


def test_kill_between_the_logs_and_the_checkpoint_and_a_torn_log_line_resume_exactly(tmp_path, dataset, monkeypatch):
    from crchfl_sumo.federation import run as run_module

    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2))
    inputs = read_inputs(config)
    run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    save = run_module._save_state

    def killed_before_checkpoint_3(path, resolved, state, marks):
        if state.steps == 3:  # its log lines are appended, its checkpoint not written
            raise Killed
        save(path, resolved, state, marks)

    monkeypatch.setattr(run_module, "_save_state", killed_before_checkpoint_3)
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer())
    monkeypatch.setattr(run_module, "_save_state", save)
    assert (tmp_path / "killed" / "ledger.jsonl").stat().st_size > 0
    run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")

    # killed while appending: half a line at the end of two logs
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "torn", trainer=SumTrainer(), after_checkpoint=kill_after(2))
    for name in ("ledger.jsonl", "metrics.jsonl"):
        with open(tmp_path / "torn" / name, "a") as handle:
            handle.write('{"link": "wirel')
    run_federation_dir(config, inputs, tmp_path / "torn", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "torn") == result_files(tmp_path / "whole")


def test_a_log_shorter_than_the_checkpoint_is_refused(tmp_path, dataset):
    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2))
    inputs = read_inputs(config)
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "out", trainer=SumTrainer(), after_checkpoint=kill_after(2))
    (tmp_path / "out" / "metrics.jsonl").write_text("")
    with pytest.raises(CrchflError, match="metrics.jsonl: missing or shorter than federation_state.pt"):
        run_federation_dir(config, inputs, tmp_path / "out", trainer=SumTrainer(), resume=True)


def test_a_run_that_relays_killed_anywhere_resumes_exactly(tmp_path, dataset):
    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2))
    inputs = read_inputs(config)

    def clock():  # t01_data_0 swaps between the two edges every 4 s; 10 MB take 10.5 s at 8 Mbit/s
        tracks = {v: [Segment(0.0, inputs.home_site[v], 8e6)] for v in inputs.vehicles}
        tracks["t01_data_0"] = [Segment(4.0 * k, k % 2, 8e6) for k in range(100)]
        return contextlib.nullcontext(ScriptedClock(tracks, step_s=0.5))

    whole = run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer(), clock_factory=clock)
    assert whole["relayed_transfers"] >= 4 and whole["relay_bytes"] > 0
    assert whole["downloads_failed"] == 0 and whole["downloads"] == 4 * len(inputs.vehicles)
    assert whole["bytes_by_link"]["relay"] == whole["relay_bytes"]
    relays = [json.loads(line) for line in (tmp_path / "whole" / "ledger.jsonl").read_text().splitlines()[1:]]
    assert sum(r["size_bytes"] for r in relays if r["link"] == "relay") == whole["relay_bytes"]
    for kill_at in (1, 3, 4):
        out = tmp_path / f"killed{kill_at}"
        with pytest.raises(Killed):
            run_federation_dir(config, inputs, out, trainer=SumTrainer(), clock_factory=clock,
                               after_checkpoint=kill_after(kill_at))
        resumed = run_federation_dir(config, inputs, out, trainer=SumTrainer(), clock_factory=clock, resume=True)
        assert resumed == whole
        assert result_files(out) == result_files(tmp_path / "whole")
    # where leaving the sending edge fails a download, relays save the ones that cross a handover
    for policy, name in (("relay", "strict"), ("drop", "drop")):
        mapping = run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2, download_handover=policy)
        mapping["transfer"] = {"on_outage": "fail"}
        summary = run_federation_dir(from_mapping(RunConfig, mapping), inputs, tmp_path / name, trainer=SumTrainer(),
                                     clock_factory=clock)
        if policy == "relay":
            assert summary["downloads_failed"] == 0 and summary["relayed_transfers"] >= 4
        else:
            assert summary["relayed_transfers"] == 0 and summary["relay_bytes"] == 0
            assert summary["downloads_failed"] >= 1


def test_a_run_keeps_the_best_model_within_each_budget_mark(tmp_path, dataset):
    path = tmp_path / "run.toml"
    path.write_text(
        f'dataset = "{dataset}"\n[federation]\nscheme = "hfl"\nedge_interval = 1\n'
        '[ledger]\nnominal_model_mb = 10.0\nbudget_gb = 0.5\nmarks_gb = [0.01, 0.2, 0.5]\n'
        '[model]\nimage_height = 48\nimage_width = 64\n[train]\ndevice = "cpu"\n[clock]\nkind = "constant"\n'
    )
    summary = run_command(path, tmp_path / "out")
    out = tmp_path / "out"
    lines = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    marks = summary["budget_marks"]
    assert list(marks) == ["0.01", "0.2", "0.5"]
    assert marks["0.01"] is None and not (out / "best_model_within_0.01gb.pt").exists()  # no evaluation within
    evaluated = [m for m in lines if m.get("balanced_accuracy") is not None]
    within = [m for m in evaluated if m["consumed_bytes"] <= 0.2 * 1024**3]
    assert 0 < len(within) < len(evaluated)
    assert marks["0.2"]["step"] in [m["step"] for m in within]
    assert marks["0.2"]["balanced_accuracy"] == max(m["balanced_accuracy"] for m in within)
    assert marks["0.5"]["step"] == load_checkpoint(out / "best_model.pt").extra["metrics"]["step"]  # the whole run
    model = load_checkpoint(out / "best_model_within_0.2gb.pt")
    assert model.extra["metrics"]["step"] == marks["0.2"]["step"]


def test_settings_stored_before_newer_options_read_back_as_today():
    # A folder written before federation.selection and model.steer_speed_input existed holds
    # neither key; read with today's defaults its settings equal a new default run's, so it resumes.
    from crchfl_sumo.federation.run_config import resolved_as_today, resolved_config

    config = from_mapping(RunConfig, {"federation": {"scheme": "hfl"}}, "test")
    today = json.loads(json.dumps(resolved_config(config)))
    stored = json.loads(json.dumps(today))
    del stored["federation"]["selection"], stored["model"]["steer_speed_input"]
    assert resolved_as_today(stored, "test") == today
    stored["federation"]["deadline_s"] = 60.0  # a setting that does differ still differs
    assert resolved_as_today(stored, "test") != today
    assert resolved_as_today({"federation": {"no_such_key": 1}}, "test") == {"federation": {"no_such_key": 1}}


def test_a_run_records_the_multi_vehicle_method_it_trains_with_so_former_folders_resume():
    # "auto" replaced "sequential" as the default; on a CPU it trains the same, so a folder written
    # under the former default compares equal (run --resume, sweep points) and config.json says the method.
    from crchfl_sumo.federation.run_config import resolved_as_today, resolved_config

    on_cpu = lambda **train: from_mapping(RunConfig, {"federation": {"scheme": "hfl"}, "train": {"device": "cpu", **train}})
    today = json.loads(json.dumps(resolved_config(on_cpu())))
    assert today["train"]["multi_vehicle"] == "sequential"
    former = {**today, "train": {**today["train"], "multi_vehicle": "sequential"}}
    assert resolved_as_today(former, "config.json") == today
    assert resolved_config(on_cpu(multi_vehicle="vmap"))["train"]["multi_vehicle"] == "vmap"  # chosen: it stands
    assert resolved_as_today({**today, "train": {**today["train"], "multi_vehicle": "vmap"}}, "config.json") != today
    ray = from_mapping(RunConfig, {"federation": {"scheme": "hfl"}, "backend": {"kind": "ray"}})
    assert resolved_config(ray)["train"]["multi_vehicle"] == "sequential"  # one task a vehicle, on a CPU


def test_a_run_records_the_precision_it_trains_in_so_former_folders_resume():
    # "auto" is stored decided: bf16 where the CPU multiplies bfloat16, else fp32. A folder written
    # before, which holds "auto", reads back as this machine decides it, and a named precision stands.
    from crchfl_sumo.federation.run_config import resolved_as_today, resolved_config
    from crchfl_sumo.learning.devices import native_bfloat16

    on_cpu = lambda **train: from_mapping(RunConfig, {"federation": {"scheme": "hfl"}, "train": {"device": "cpu", **train}})
    today = json.loads(json.dumps(resolved_config(on_cpu())))
    assert today["train"]["precision"] == ("bf16" if native_bfloat16("cpu") else "fp32")
    former = {**today, "train": {**today["train"], "precision": "auto"}}
    assert resolved_as_today(former, "config.json") == today
    for named in ("fp32", "bf16"):
        assert resolved_config(on_cpu(precision=named))["train"]["precision"] == named
    ray = from_mapping(RunConfig, {"federation": {"scheme": "hfl"}, "backend": {"kind": "ray"}})
    assert resolved_config(ray)["train"]["precision"] == today["train"]["precision"]  # Ray tasks train on CPUs


def test_a_former_ray_folder_reads_back_as_decided_on_the_cpus_its_tasks_train_on(monkeypatch):
    # An earlier version stored "auto"; on a GPU machine whose CPU lacks bfloat16, a Ray run trains in
    # fp32 (tasks on CPUs) and a local one in the GPU's bf16. The stored settings leave the backend out,
    # so the backend the run goes on decides how "auto" reads back.
    from crchfl_sumo.core.backend import BackendConfig
    from crchfl_sumo.federation.run_config import resolved_as_today, resolved_config
    from crchfl_sumo.learning import devices

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(devices, "native_bfloat16", lambda device_type: device_type == "cuda")
    ray = from_mapping(RunConfig, {"federation": {"scheme": "hfl"}, "backend": {"kind": "ray"}})
    today = json.loads(json.dumps(resolved_config(ray)))
    assert today["train"]["precision"] == "fp32"
    former = {**today, "train": {**today["train"], "precision": "auto"}}
    assert resolved_as_today(former, "config.json", ray.backend) == today
    assert resolved_as_today(former, "config.json", BackendConfig())["train"]["precision"] == "bf16"


def test_the_trainer_trains_as_config_json_records(dataset):
    # "auto" is decided once, where the run starts, and handed to the trainer (a Ray worker does not decide again).
    from crchfl_sumo.core.backend import BackendConfig, Executor
    from crchfl_sumo.federation.run import make_trainer
    from crchfl_sumo.federation.run_config import resolved_config

    config = from_mapping(RunConfig, run_config(dataset))
    assert config.train.precision == config.train.multi_vehicle == "auto"
    with Executor(BackendConfig()) as executor:
        trainer = make_trainer(config, read_inputs(config), executor)
    recorded = resolved_config(config)["train"]
    assert (trainer.config.precision, trainer.config.multi_vehicle) == (recorded["precision"], recorded["multi_vehicle"])
    assert trainer.config.precision in ("fp32", "bf16") and trainer.config.multi_vehicle == "sequential"


def test_a_run_of_slow_and_intermittent_vehicles_says_why_each_straggled_and_resumes_exactly(tmp_path, dataset):
    trace = tmp_path / "off.csv"
    trace.write_text("vehicle,off_start_s,off_end_s\nt01_data_1,0.5,25\n")  # off through the first round
    mapping = run_config(dataset, scheme="hfl", cloud_rounds=3, compute_s_per_sample=1.0, deadline_s=8.0)
    mapping["clock"] |= {"compute_profile": "tiers", "compute_tiers": [1.0, 3.0], "availability": "trace",
                         "availability_trace": str(trace)}
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)
    summary = run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    stragglers = [json.loads(line) for line in (tmp_path / "whole" / "stragglers.jsonl").read_text().splitlines()]
    assert stragglers and {s["cause"] for s in stragglers} <= {"unavailable", "slow_compute", "deadline",
                                                                 "out_of_coverage"}
    # off until 25 s: it misses rounds 1 and 2 (its round-1 model arrives at 29 s), and only for that
    assert [(s["cloud_round"], s["cause"]) for s in stragglers if s["vehicle"] == "t01_data_1"][:2] == [
        (1, "unavailable"), (2, "unavailable")
    ]
    assert {s["cause"] for s in stragglers if s["vehicle"] != "t01_data_1"} <= {"slow_compute", "deadline"}
    assert sum(summary["straggler_causes"].values()) == summary["stragglers"] == len(stragglers)
    assert set(summary["compute_factors"]) == set(inputs.vehicles)
    assert set(summary["compute_factors"].values()) <= {1.0, 3.0}
    # one of 5 vehicles off from 0.5 s to 25 s of the run's simulated time
    assert summary["off_share"] == pytest.approx(24.5 / (5 * summary["sim_time_s"]))
    energy = summary["energy_j"]
    assert set(energy["vehicles"]) == set(inputs.vehicles) and energy["compute"] > 0 and energy["radio"] > 0
    assert energy["total"] == pytest.approx(sum(e["total"] for e in energy["vehicles"].values()))
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), after_checkpoint=kill_after(2))
    run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")
