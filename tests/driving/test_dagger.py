"""DAgger iterations (driving.dagger.dagger_iterations, `crchfl-sumo dagger`): the learner drives, the route
expert labels its states, the model is fine-tuned on the data set plus every iteration's labels, and a rerun
goes on where the last one stopped."""

from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from crchfl_sumo.cli import main
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.data.manifest import read_manifest
from crchfl_sumo.data.labels import SIGNAL_RED, digitize_steer
from crchfl_sumo.data.samples import FIELDS, Samples
from crchfl_sumo.driving.dagger import EXPERT_SAMPLES_FILE, ExpertLabelled, collect, dagger_iterations
from crchfl_sumo.driving.dagger_settings import DaggerConfig
from crchfl_sumo.driving.drive import DriveConfig
from crchfl_sumo.driving.policies import Observation
from crchfl_sumo.learning.checkpoint import load_checkpoint, save_checkpoint
from crchfl_sumo.learning.model import build_model
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.centralized import train_centralized

from helpers import PAPER_VEHICLES, random_samples, write_dataset

SMALL = ModelConfig("compact", 48, 64)  # random_samples' image size
# One short drive a round on the ladder's straight road; every second step labelled, corrections or not
# (the untrained model brakes where the expert drives on: the expert would never step in).
ROUND = DaggerConfig(tasks=("straight",), episodes=1, every=2, max_s=2.0, corrections_only=False,
                     drive=DriveConfig(stuck_s=60.0))


@pytest.fixture(scope="module")
def start(tmp_path_factory):
    """A model trained one epoch (its checkpoint carries the training settings a fine-tune reuses)."""
    out = tmp_path_factory.mktemp("start")
    train, test = random_samples(12, seed=1), random_samples(6, seed=2)
    train_centralized(train, test, 1, out, SMALL, TrainConfig(device="cpu", deterministic=True, batch_size=4), seed=0)
    return out / "checkpoint.pt", train, test


def _states_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_an_iteration_fine_tunes_on_the_data_and_the_experts_labels_and_a_rerun_goes_on(start, ladder, tmp_path):
    checkpoint, train, test = start
    towns = (str(ladder / "ladder.sumocfg"),)
    out = tmp_path / "dagger"
    (first,) = dagger_iterations(checkpoint, train, test, out, towns, ROUND, iterations=1, epochs=1, seed=7)

    with np.load(out / "iteration-1" / EXPERT_SAMPLES_FILE) as stored:
        actions, steer_class = stored["actions"], stored["steer_class"]
        assert stored["images"].shape[1:] == (4, 48, 64, 3)  # drawn as the model's data: its camera size
    # 2 s of driving at 0.25 s steps, every second step labelled (fewer only if the learner left the route)
    assert 1 <= len(actions) <= 4 and first["expert_samples"] == len(actions)
    assert steer_class.tolist() == digitize_steer(actions[:, 1]).tolist()  # the data set's steer classes
    assert first["route_seed"] == ROUND.seed + 1 and first["training_samples"] == 12 + len(actions)
    (record,) = [json.loads(line) for line in (out / "iteration-1" / "metrics.jsonl").read_text().splitlines()]
    assert record["train_samples"] == 12 + len(actions)  # the data set and the labels, together
    assert record["balanced_accuracy"] == first["balanced_accuracy"]
    # Fine-tuned from the start model with its own training settings; out/checkpoint.pt is the last iteration's.
    before, after = load_checkpoint(checkpoint), load_checkpoint(out / "iteration-1" / "checkpoint.pt")
    # the start model's recipe, fine-tuned a tenth as fast and with the steer classes unweighted
    assert after.extra["train_config"] == {**before.extra["train_config"], "learning_rate": 1e-4,
                                           "class_weighting": "none"}
    assert after.extra["train_config"]["batch_size"] == 4
    assert not _states_equal(before.state_dict, after.state_dict)
    assert (out / "checkpoint.pt").read_bytes() == (out / "iteration-1" / "checkpoint.pt").read_bytes()
    assert json.loads((out / "summary.json").read_text())["iterations"] == [first]

    # A second run with one more iteration keeps the first (not driven nor trained again) and adds the second,
    # which starts from the first's model.
    kept = (out / "iteration-1" / "checkpoint.pt").read_bytes()
    records = dagger_iterations(checkpoint, train, test, out, towns, ROUND, iterations=2, epochs=1, seed=7)
    assert records[0] == first and (out / "iteration-1" / "checkpoint.pt").read_bytes() == kept
    assert records[1]["route_seed"] == ROUND.seed + 2
    second = np.load(out / "iteration-2" / EXPERT_SAMPLES_FILE)["actions"]
    assert records[1]["training_samples"] == 12 + len(actions) + len(second)
    assert (out / "checkpoint.pt").read_bytes() == (out / "iteration-2" / "checkpoint.pt").read_bytes()


def test_class_weighting_changes_only_the_fine_tunings_loss(start, ladder, tmp_path):
    checkpoint, train, test = start
    towns = (str(ladder / "ladder.sumocfg"),)
    assert load_checkpoint(checkpoint).extra["train_config"]["class_weighting"] == "sqrt_inverse"
    dagger_iterations(checkpoint, train, test, tmp_path / "kept", towns, ROUND, iterations=1, epochs=1, seed=7,
                      class_weighting="start")
    dagger_iterations(checkpoint, train, test, tmp_path / "none", towns, ROUND, iterations=1, epochs=1, seed=7)
    with pytest.raises(CrchflError, match="class_weighting 'equal' is unknown"):
        dagger_iterations(checkpoint, train, test, tmp_path / "bad", towns, ROUND, class_weighting="equal")
    kept, unweighted = (load_checkpoint(tmp_path / name / "checkpoint.pt") for name in ("kept", "none"))
    assert kept.extra["train_config"]["class_weighting"] == "sqrt_inverse"
    assert unweighted.extra["train_config"] == {**kept.extra["train_config"], "class_weighting": "none"}
    assert [json.loads((tmp_path / name / "summary.json").read_text())["class_weighting"]
            for name in ("kept", "none")] == ["sqrt_inverse", "none"]
    # the start model drove both: the same labels; only the loss's weights differ, and with them the weights
    labels = [(tmp_path / name / "iteration-1" / EXPERT_SAMPLES_FILE).read_bytes() for name in ("kept", "none")]
    assert labels[0] == labels[1]
    assert not _states_equal(kept.state_dict, unweighted.state_dict)


def test_the_fine_tune_keeps_its_last_step_though_the_start_model_averaged_its_weights(start, ladder, tmp_path):
    _, train, test = start
    averaged = tmp_path / "averaged"
    train_centralized(train, test, 1, averaged, SMALL,
                      TrainConfig(device="cpu", deterministic=True, batch_size=4, ema_decay=0.9), seed=0)
    assert load_checkpoint(averaged / "checkpoint.pt").extra["train_config"]["ema_decay"] == 0.9
    dagger_iterations(averaged / "checkpoint.pt", train, test, tmp_path / "dagger", (str(ladder / "ladder.sumocfg"),),
                      ROUND, iterations=1, epochs=1, seed=7)
    tuned = load_checkpoint(tmp_path / "dagger" / "checkpoint.pt")
    assert "ema_decay" not in tuned.extra["train_config"] and set(tuned.extra["resume"]) == {
        "optimizers", "generator", "records", "samples"}


def test_the_samples_do_not_depend_on_how_many_processes_drive(start, ladder):
    checkpoint, _, _ = start
    towns = (str(ladder / "ladder.sumocfg"),)
    config = dataclasses.replace(ROUND, tasks=("straight", "one_turn"))  # 2 episodes: two groups with 2 jobs
    one, two = collect(checkpoint, towns, config, jobs=1), collect(checkpoint, towns, config, jobs=2)
    assert len(one) > 0
    for name in FIELDS:
        assert torch.equal(getattr(one, name), getattr(two, name)), name
    # With corrections only at most as many states are kept, the same however many processes drive
    corrections = dataclasses.replace(config, corrections_only=True)
    kept = collect(checkpoint, towns, corrections, jobs=1)
    assert len(kept) <= len(one) and torch.equal(kept.actions, collect(checkpoint, towns, corrections, jobs=2).actions)
    # A drive that keeps nothing gives empty arrays of the right shape
    learner = _Learner()
    learner.model = SimpleNamespace(config=SimpleNamespace(speed_horizon_s=1.0, image_height=48, image_width=64))
    none = Samples.from_numpy(**ExpertLabelled(learner, _Expert()).arrays())
    assert len(none) == 0 and tuple(none.images.shape[1:]) == (4, 48, 64, 3)


def test_bad_input_is_refused_with_the_file_or_option_named(start, ladder, tmp_path, capsys):
    checkpoint, train, test = start
    towns = (str(ladder / "ladder.sumocfg"),)
    with pytest.raises(CrchflError, match="dagger: iterations"):
        dagger_iterations(checkpoint, train, test, tmp_path / "a", towns, ROUND, iterations=0)
    with pytest.raises(CrchflError, match="dagger: learning_rate"):
        dagger_iterations(checkpoint, train, test, tmp_path / "a", towns, ROUND, learning_rate=float("nan"))
    damaged = tmp_path / "b" / "iteration-1" / EXPERT_SAMPLES_FILE
    damaged.parent.mkdir(parents=True)
    damaged.write_bytes(b"not an npz file")
    with pytest.raises(CrchflError, match="expert_samples.npz: unreadable.*delete the file"):
        dagger_iterations(checkpoint, train, test, tmp_path / "b", towns, ROUND, iterations=1, epochs=1)
    model = build_model(SMALL, seed=0)
    save_checkpoint(tmp_path / "model.pt", model.config, model.state_dict())
    code = main(["dagger", str(tmp_path / "model.pt"), str(tmp_path / "no-data"), "--out", str(tmp_path / "c")])
    assert code == 2 and "no-data" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()  # a refused input leaves nothing behind


def test_the_command_runs_an_iteration_and_overwrite_starts_afresh(ladder, tmp_path, capsys):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    model = build_model(SMALL, seed=0)
    save_checkpoint(tmp_path / "model.pt", model.config, model.state_dict())
    argv = ["dagger", str(tmp_path / "model.pt"), str(data), "--out", str(tmp_path / "out"), "--towns",
            str(ladder / "ladder.sumocfg"), "--tasks", "straight", "--episodes", "1", "--all-states",
            "--class-weighting", "inverse"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    (record,) = summary["iterations"]
    assert f"+{record['expert_samples']} expert-labelled samples ({10 + record['expert_samples']} in all)" in printed
    assert summary["corrections_only"] is False and summary["learning_rate"] == 1e-4
    assert summary["class_weighting"] == "inverse"  # --class-weighting reached the fine-tuning
    # --overwrite drives and trains again rather than taking up what the folder holds
    (tmp_path / "out" / "iteration-1" / EXPERT_SAMPLES_FILE).write_bytes(b"left from another run")
    assert main([*argv, "--overwrite"]) == 0
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["iterations"] == [record]


def test_the_command_refuses_a_data_set_drawn_otherwise_than_the_models(ladder, tmp_path, capsys):
    data = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["camera"] = {"raster": {"route_signal": True}, "world": {}}  # one-link heads (the default since)
    (data / "manifest.json").write_text(json.dumps(manifest))
    model = build_model(SMALL, seed=0)
    old_camera = {"raster": {"lamp_min_radius_px": 2.5}, "world": {}}  # written before route_signal: every head
    save_checkpoint(tmp_path / "model.pt", model.config, model.state_dict(), {"camera": old_camera})
    argv = ["dagger", str(tmp_path / "model.pt"), str(data), "--out", str(tmp_path / "out"), "--towns",
            str(ladder / "ladder.sumocfg"), "--tasks", "straight", "--episodes", "1"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "raster.route_signal True against False" in err and str(data) in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    # the same settings pass the check: the model's copy is the manifest's block
    save_checkpoint(tmp_path / "model.pt", model.config, model.state_dict(), {"camera": manifest["camera"]})
    read_manifest(data).check_camera(manifest["camera"], str(data), "model.pt")


class _Learner:
    """ModelPolicy's face: steers right, command 3."""

    model = SimpleNamespace(config=SimpleNamespace(speed_horizon_s=1.0))
    action = (0.5, 0.3, 0.0)

    def __call__(self, observation):
        return self.action

    def command(self, observation):
        return 3


class _Expert:
    """RoutePolicy's face: steers hard left back to the lane, on a straight route along +x."""

    expert = ExpertConfig()
    route = SimpleNamespace(s_m=np.array([0.0, 1000.0]), xy_m=np.array([[0.0, 0.0], [1000.0, 0.0]]), crossings=())
    action = (0.2, -0.9, 0.0)

    def decide(self, observation):
        return self.action, 0.5

    def __call__(self, observation):
        return self.decide(observation)[0]


def test_the_expert_takes_the_wheel_off_the_lane_or_its_heading_and_those_states_are_not_labelled():
    policy = ExpertLabelled(_Learner(), _Expert(), every=1)
    images = np.zeros((4, 48, 64, 3), np.uint8)
    # a 3.5 m lane: the expert takes over beyond 1.75 m or 15 degrees off the route's heading, and
    # hands back within 0.875 m and 7.5 degrees
    steps = [(0.0, 0), (-1.0, 10), (1.8, 0), (1.0, 0), (-0.9, 0), (0.8, 0), (0.3, 0),  # off the lane
             (0.2, 16), (0.2, 10), (0.2, -7), (0.0, 0)]  # in the lane, its heading off
    acted = [
        policy(Observation(SimpleNamespace(speed_mps=np.array([5.0]), heading_rad=np.array([math.radians(deg)]),
                                           length_m=np.array([4.5]), tls_states={}, foe_gap_m=np.array([np.inf])),
                           "ego", 0, 10.0 * i, images, offset, 3.5))
        for i, (offset, deg) in enumerate(steps)
    ]
    learner, expert = _Learner.action, _Expert.action
    assert acted == [learner, learner, expert, expert, expert, learner, learner, expert, expert, learner, learner]
    assert policy.takeovers == 2
    arrays = policy.arrays()
    # the learner's six states, each labelled with the expert's action; none of the expert's own
    assert len(arrays["actions"]) == 6 and arrays["command"].tolist() == [3] * 6
    assert np.allclose(arrays["actions"], np.array([expert] * 6, np.float32))


def test_dagger_samples_carry_the_next_signal_and_the_yield_gap_as_the_data_set_does():
    from crchfl_sumo.sumo.route import next_signal
    from crchfl_sumo.sumo.route import Crossing

    crossings = (Crossing(40.0, 55.0, "", -1, "s"), Crossing(120.0, 135.0, "J", 1, "s"), Crossing(300.0, 310.0, "K", 0, "l"))
    # the unsignalised junction is passed over; the distance is from the front bumper to the stop line
    assert next_signal(crossings, 30.0, {"J": "Gr", "K": "G"}) == ("r", 90.0)
    assert next_signal(crossings, 120.0, {"J": "Gy"}) == ("y", 0.0)  # at the line: still ahead
    assert next_signal(crossings, 121.0, {}) == ("", 179.0)  # K's state unknown: no letter
    assert next_signal(crossings, 301.0, {"K": "G"}) == ("", math.inf)
    policy = ExpertLabelled(_Learner(), _Expert(), every=1)
    policy.expert.route = SimpleNamespace(**{**vars(_Expert.route), "crossings": crossings})
    # ... and the gap of the nearest junction foe to yield to (12 m from the conflict point, then already in it;
    # NaN: not looked for)
    for progress_m, gap in ((28.0, 12.0), (110.0, -1.5), (200.0, np.nan)):  # front bumpers at 30, 112 and 202 m
        frame = SimpleNamespace(speed_mps=np.array([5.0]), heading_rad=np.array([0.0]), length_m=np.array([4.0]),
                                tls_states={"J": "Gr"}, foe_gap_m=np.array([gap]))
        policy(Observation(frame, "ego", 0, progress_m, np.zeros((4, 48, 64, 3), np.uint8), 0.0, 3.5))
    arrays = policy.arrays()
    assert arrays["signal_state"].tolist()[:2] == [SIGNAL_RED, SIGNAL_RED]
    assert np.allclose(arrays["signal_distance_m"][:2], [90.0, 8.0])
    assert arrays["yield_gap_m"].tolist() == [12.0, -1.5, math.inf] and arrays["yield_gap_m"].dtype == np.float32


def test_the_labeller_steers_by_the_data_sets_pursuit():
    from crchfl_sumo.driving.dagger import labeller_config
    from crchfl_sumo.driving.policies import RoutePolicyConfig

    data = ExpertConfig(lookahead_min_m=6.0, lookahead_time_s=0.9)
    labeller = labeller_config(RoutePolicyConfig(hold_short_m=10.0), data)
    assert (labeller.lookahead_min_m, labeller.lookahead_time_s) == (6.0, 0.9)
    assert labeller.hold_short_m == 10.0  # the rest is the route expert's
    # the reference driver itself keeps its own, shorter look-ahead
    assert (RoutePolicyConfig().lookahead_min_m, RoutePolicyConfig().lookahead_time_s) == (4.0, 0.5)
