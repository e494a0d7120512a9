"""The stop head (ModelConfig.stop_head) and the red hold (ModelConfig.red_hold): their targets, the
controller's cap, training and checkpoints."""

import math

import numpy as np
import pytest
import torch

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.labels import SIGNAL_GREEN, SIGNAL_NONE, SIGNAL_RED, SIGNAL_UNKNOWN, SIGNAL_YELLOW
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.checkpoint import load_model, save_checkpoint
from crchfl_sumo.learning.model import (
    STOP_RANGE_M,
    build_model,
    holds_signal_states,
    longitudinal_target,
    longitudinal_width,
    predict_actions,
    stop_capped_speed,
)
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig, with_data_signals
from crchfl_sumo.learning.training import train_vehicles

STOP = ModelConfig("compact", 48, 64, stop_head=True)
HOLD = ModelConfig("compact", 48, 64, red_hold=True)


def _labelled(state, distance_m, target_mps):
    n = len(state)
    return Samples.from_numpy(np.zeros((n, 4, 48, 64, 3), np.uint8), np.zeros((n, 3)), np.zeros(n), np.zeros(n),
                              np.zeros(n), target_mps, signal_state=state, signal_distance_m=distance_m)


def test_the_targets_are_the_red_or_yellow_stop_line_distance_within_range():
    samples = _labelled([SIGNAL_RED, SIGNAL_YELLOW, SIGNAL_GREEN, SIGNAL_RED, SIGNAL_NONE, SIGNAL_UNKNOWN],
                        [12.0, 4.0, 5.0, 70.0, math.inf, 3.0], np.full(6, 5.0))
    target = longitudinal_target(STOP, samples)
    assert target.shape == (6, 2)
    assert target[:, 0].tolist() == pytest.approx([0.5] * 6)  # the target speed / 10, as without the head
    # red 12 m, yellow 4 m, green: range, red beyond the range: range, no signal, unknown: range
    assert target[:, 1].tolist() == pytest.approx([12 / 40, 4 / 40, 1.0, 1.0, 1.0, 1.0])
    assert longitudinal_target(STOP, samples, torch.tensor([3, 0]))[:, 1].tolist() == pytest.approx([1.0, 12 / 40])
    # without the head nothing changes
    assert longitudinal_target(ModelConfig("compact", 48, 64), samples).shape == (6, 1)


def test_the_red_hold_caps_the_label_before_a_red_line_only():
    samples = _labelled([SIGNAL_RED, SIGNAL_RED, SIGNAL_RED, SIGNAL_RED, SIGNAL_GREEN, SIGNAL_YELLOW, SIGNAL_UNKNOWN],
                        [1.0, 12.0, 40.0, 2.5, 1.0, 1.0, 1.0], [2.0, 8.0, 8.0, 0.5, 2.0, 2.0, 2.0])
    # red: standing 1 m short (inside the 2 m margin) -> 0; 12 m: sqrt(2 * 2.5 * 10) = 7.07 < 8; 40 m:
    # sqrt(2 * 2.5 * 38) = 13.8 > 8, kept; 2.5 m: sqrt(2.5) = 1.58 > 0.5, kept; green, yellow, unknown: kept
    held = longitudinal_target(HOLD, samples)[:, 0] * 10.0
    assert held.tolist() == pytest.approx([0.0, math.sqrt(50.0), 8.0, 0.5, 2.0, 2.0, 2.0], abs=1e-5)
    plain = longitudinal_target(ModelConfig("compact", 48, 64), samples)[:, 0] * 10.0
    assert plain.tolist() == pytest.approx([2.0, 8.0, 8.0, 0.5, 2.0, 2.0, 2.0])
    both = longitudinal_target(ModelConfig("compact", 48, 64, red_hold=True, stop_head=True), samples)
    assert both.shape == (7, 2) and both[0, 0] == 0 and both[1, 1] == pytest.approx(12 / 40)


def test_the_cap_stops_the_car_before_the_line_unless_it_is_committed():
    target = np.array([8.0, 8.0, 8.0, 8.0, 3.0, 8.0])
    stop = np.array([40.0, 22.0, 2.0, 1.0, 22.0, 3.0])
    speed = np.array([8.0, 8.0, 2.5, 0.0, 3.0, 8.0])
    capped = stop_capped_speed(target, stop, speed, 4.5)
    # 40 m: sqrt(2 * 2.5 * 38) = 13.8 > 8, no cap; 22 m: sqrt(2 * 2.5 * 20) = 10 > 8, no cap; 2 m (the margin): 0;
    # standing 1 m short: 0; a lower target stays; 8 m/s at 3 m cannot stop (64 > 2 * 4.5 * 3 = 27): committed
    assert capped.tolist() == pytest.approx([8.0, 8.0, 0.0, 0.0, 3.0, 8.0])
    assert stop_capped_speed(np.array([8.0]), np.array([7.0]), np.array([6.0]), 4.5)[0] == pytest.approx(5.0)
    # standing (under 1 m/s), a car starts only when no red line is within 10 m: at 9 m it stays (the cap
    # alone would allow sqrt(2 * 2.5 * 7) = 5.9 m/s), at 11 m it goes; rolling at 2 m/s, 9 m caps at 5.9
    held = stop_capped_speed(np.array([3.0, 3.0, 8.0]), np.array([9.0, 11.0, 9.0]), np.array([0.0, 0.5, 2.0]), 4.5)
    assert held.tolist() == pytest.approx([0.0, 3.0, math.sqrt(35.0)])


def test_predict_actions_brakes_for_a_predicted_red_line_and_drives_on_without_one():
    model = build_model(STOP, seed=0)
    head = model.branch_throttle_brake.heads[0][-1]
    images = torch.zeros(3, 4, 48, 64, 3, dtype=torch.uint8)
    with torch.no_grad():
        head.weight.zero_()
        head.bias.copy_(torch.tensor([0.8, 1.0]))  # 8 m/s, no red within range
    go = predict_actions(model, images, torch.tensor([0, 0, 0]), torch.tensor([8.0, 8.0, 8.0]))
    with torch.no_grad():
        head.bias.copy_(torch.tensor([0.8, 6.0 / STOP_RANGE_M]))  # a red line 6 m ahead: cap sqrt(5 * 4) = 4.5 m/s
    stop = predict_actions(model, images, torch.tensor([0, 0, 0]), torch.tensor([4.0, 6.0, 8.0]))
    assert go[:, 2].tolist() == [0.0, 0.0, 0.0] and go[0, 0] > 0
    assert stop[0, 0] > 0 and stop[0, 2] == 0  # 4 m/s under the 4.5 m/s cap: no brake
    assert stop[1, 2] > 0 and stop[1, 0] == 0  # 6 m/s, 6 m: it can stop (36 < 2 * 4.5 * 6), so it brakes
    assert stop[2, 0] > 0 and stop[2, 2] == 0  # 8 m/s, 6 m: it cannot (64 > 54), so it drives on


def _signalled_samples(n, seed):
    rng = np.random.default_rng(seed)
    return Samples.from_numpy(
        rng.integers(0, 256, size=(n, 4, 48, 64, 3), dtype=np.uint8), rng.random((n, 3), dtype=np.float32),
        rng.integers(0, 7, size=n), rng.integers(0, 4, size=n), rng.uniform(0, 14, size=n), rng.uniform(0, 14, size=n),
        signal_state=rng.choice([SIGNAL_RED, SIGNAL_GREEN], size=n), signal_distance_m=rng.uniform(0, 60, size=n),
    )


def test_the_stop_head_trains_alike_in_the_sequential_and_the_vmap_trainer_and_round_trips(tmp_path):
    vehicles = [_signalled_samples(n, seed) for seed, n in enumerate((40, 23))]
    start = [build_model(STOP, seed=s).state_dict() for s in (0, 1)]
    results = {
        method: train_vehicles(start, vehicles, 1, STOP, TrainConfig(device="cpu", multi_vehicle=method,
                                                                     precision="fp32"), seed=3)
        for method in ("sequential", "vmap")
    }
    for v in range(2):
        head = "branch_throttle_brake.heads.0.2.weight"
        assert results["sequential"][0][v][head].shape == (2, 50)
        assert torch.allclose(results["sequential"][0][v][head], results["vmap"][0][v][head], atol=1e-5)
        assert not torch.equal(results["sequential"][0][v][head], start[v][head])
    path = tmp_path / "stop.pt"
    save_checkpoint(path, STOP, results["sequential"][0][0])
    loaded = load_model(path)
    assert loaded.config.stop_head


def test_a_pedal_model_has_no_stop_head_and_no_red_hold():
    for key in ("stop_head", "red_hold"):
        with pytest.raises(CrchflError, match=key):
            ModelConfig("compact", 48, 64, longitudinal="pedals", **{key: True})
        with pytest.raises(CrchflError, match=key):
            ModelConfig("compact", 48, 64, **{key: 1})


def test_a_federated_run_refuses_signal_targets_from_a_data_set_without_signal_states(tmp_path):
    from crchfl_sumo.core.config import from_mapping
    from crchfl_sumo.federation.run_config import RunConfig
    from crchfl_sumo.federation.run_data import read_inputs

    from helpers import PAPER_VEHICLES, run_config, write_dataset

    plain = write_dataset(tmp_path / "plain", PAPER_VEHICLES)
    signalled = write_dataset(tmp_path / "signalled", PAPER_VEHICLES, signals=True)
    for key in ("stop_head", "red_hold"):
        config = run_config(plain)
        config["model"][key] = True
        with pytest.raises(CrchflError, match=f"no signal states.*model.{key}"):
            read_inputs(from_mapping(RunConfig, config))
        config["dataset"] = str(signalled)
        assert read_inputs(from_mapping(RunConfig, config)).vehicles  # with signal states it loads


def test_an_unset_stop_head_is_decided_by_the_training_data():
    unset = ModelConfig("compact", 48, 64)
    assert unset.stop_head is None and longitudinal_width(unset) == 1  # a checkpoint without the key: none
    assert with_data_signals(unset, True).stop_head is True
    assert with_data_signals(unset, False) == unset  # a data set before format 5: unset, which is none
    assert with_data_signals(ModelConfig("compact", 48, 64, stop_head=False), True).stop_head is False
    pedals = ModelConfig("compact", 48, 64, longitudinal="pedals")
    assert with_data_signals(pedals, True) == pedals
    assert with_data_signals(ModelConfig("compact", 48, 64, arch="paper"), True).stop_head is None
    own = ModelConfig("compact", 48, 64, class_path="my.module:Net")
    assert with_data_signals(own, True) == own  # your own network answers as it was written
    assert holds_signal_states(torch.tensor([SIGNAL_UNKNOWN, SIGNAL_RED])) is True
    assert holds_signal_states(torch.tensor([SIGNAL_UNKNOWN, SIGNAL_UNKNOWN])) is False
