import math

import numpy as np
import pytest
import torch

from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.evaluation import (
    always_straight,
    balanced_accuracy,
    confusion_matrix,
    evaluate_model,
    recall_per_class,
)
from crchfl_sumo.learning.settings import ModelConfig


class FixedModel(torch.nn.Module):
    """Predicts given pedals and steer classes for samples 0..N-1, whatever the input."""

    def __init__(self, pedals, classes, config=ModelConfig(longitudinal="pedals", steer_bins=7)):
        super().__init__()
        self.config = config
        self.weight = torch.nn.Parameter(torch.zeros(1))  # evaluate reads the device from a parameter
        self.pedals = torch.tensor(pedals, dtype=torch.float32)
        self.classes = torch.tensor(classes)
        self.calls = []

    def forward(self, images, command, speed_mps):
        self.calls.append((command.clone(), speed_mps.clone()))
        index = images[:, 0, 0, 0, 0].long()  # each sample's image carries its own index
        logits = torch.nn.functional.one_hot(self.classes[index], self.config.steer_bins).float() * 10.0
        return self.pedals[index], logits


def _samples(actions, classes, commands=None):
    n = len(classes)
    images = np.zeros((n, 4, 48, 64, 3), np.uint8)
    images[:, 0, 0, 0, 0] = np.arange(n)
    commands = np.zeros(n, np.int64) if commands is None else commands
    return Samples.from_numpy(images, np.array(actions, np.float32), np.array(classes), commands, np.arange(n) * 1.5,
                              np.arange(n) * 2.0)


def test_confusion_recall_and_balanced_accuracy_by_hand():
    true = np.array([0, 0, 0, 0, 1, 1, 5])
    predicted = np.array([0, 0, 0, 1, 1, 0, 3])
    confusion = confusion_matrix(true, predicted)
    assert confusion[0, 0] == 3 and confusion[0, 1] == 1 and confusion[1, 1] == 1 and confusion[1, 0] == 1
    assert confusion[5, 3] == 1 and confusion.sum() == 7
    recall = recall_per_class(confusion)
    assert recall[0] == 0.75 and recall[1] == 0.5 and recall[5] == 0.0
    assert all(math.isnan(recall[c]) for c in (2, 3, 4, 6))  # absent classes have no recall
    # mean over the three classes present: (3/4 + 1/2 + 0) / 3; the prediction of absent class 3 is an error
    assert balanced_accuracy(confusion) == pytest.approx(1.25 / 3)
    assert math.isnan(balanced_accuracy(np.zeros((7, 7), np.int64)))


def test_always_straight_baseline():
    actions = np.zeros((5, 3))
    actions[3:, 1] = [0.3, -0.4]  # the two turning samples' analogue steer
    samples = _samples(actions, [0, 0, 0, 2, 6])
    assert always_straight(samples) == {
        "accuracy": 0.6, "balanced_accuracy": pytest.approx(1 / 3), "steer_error": pytest.approx(0.7 / 5)
    }
    every_class = _samples(np.zeros((7, 3)), list(range(7)))
    assert always_straight(every_class)["balanced_accuracy"] == pytest.approx(1 / 7)
    no_straight = _samples(np.zeros((2, 3)), [1, 4])
    assert always_straight(no_straight) == {"accuracy": 0.0, "balanced_accuracy": 0.0, "steer_error": 0.0}


def test_evaluate_model_by_hand():
    # true (throttle, steer, brake) and class; predicted (throttle, brake) and class
    actions = [[0.5, 0.0, 0.0], [0.0, 0.125, 1.0], [0.2, -0.275, 0.0], [1.0, 0.0, 0.0]]
    classes = [0, 1, 5, 0]
    pedals = [[0.5, 0.0], [0.5, 0.5], [0.2, 0.1], [0.6, 0.2]]
    predicted = [0, 0, 5, 2]  # right, wrong (0 for 1), right, wrong (2 for 0)
    model = FixedModel(pedals, predicted)
    samples = _samples(actions, classes, commands=np.array([0, 1, 2, 3]))
    result = evaluate_model(model, samples, eval_batch_size=3)  # two batches: 3 + 1
    assert result.num_samples == 4
    assert result.accuracy == 0.5
    assert result.recall[0] == 0.5 and result.recall[1] == 0.0 and result.recall[5] == 1.0
    assert result.balanced_accuracy == pytest.approx(0.5)  # (1/2 + 0 + 1) / 3
    assert result.confusion[0][0] == 1 and result.confusion[0][2] == 1 and result.confusion[1][0] == 1
    # DAC steer errors: |0 - 0|, |0 - 0.125|, |-0.275 + 0.275|, |0.275 - 0|
    assert result.steer_error == pytest.approx((0.125 + 0.275) / 4)
    assert result.throttle_error == pytest.approx((0 + 0.5 + 0 + 0.4) / 4)
    assert result.brake_error == pytest.approx((0 + 0.5 + 0.1 + 0.2) / 4)
    mse = np.mean([0, (0.25 + 0.25) / 2, 0.01 / 2, (0.16 + 0.04) / 2])
    assert result.loss_throttle_brake == pytest.approx(mse)
    assert result.loss == pytest.approx(result.loss_throttle_brake + result.loss_steer)
    # the model saw each sample's command and speed
    assert torch.cat([c for c, _ in model.calls]).tolist() == [0, 1, 2, 3]
    assert torch.cat([s for _, s in model.calls]).tolist() == [0.0, 1.5, 3.0, 4.5]
    record = result.record()
    assert record["recall"][2] is None and record["recall"][5] == 1.0
    assert record["confusion"][0] == [1, 0, 1, 0, 0, 0, 0] and record["samples"] == 4


def test_a_finer_steer_head_is_scored_on_the_paper_classes():
    # 21 bins, 0.1 apart over [-1, 1]: bin k is -1 + 0.1 k
    actions = [[0.0, 0.0, 0.0], [0.0, 0.12, 0.0], [0.0, -0.6, 0.0], [0.0, 0.3, 0.0]]
    classes = [0, 1, 6, 2]  # the paper's digitizer of those steers
    predicted = [10, 11, 4, 17]  # values 0.0, 0.1, -0.6, 0.7
    model = FixedModel([[0.0, 0.0]] * 4, predicted, ModelConfig(longitudinal="pedals", steer_bins=21))
    result = evaluate_model(model, _samples(actions, classes))
    # read on the paper's classes: 0.0 -> 0, 0.1 -> 1 (0.125), -0.6 -> 6 (-0.425), 0.7 -> 3 (0.425)
    assert result.confusion[0][0] == result.confusion[1][1] == result.confusion[6][6] == result.confusion[2][3] == 1
    assert result.accuracy == 0.75 and result.balanced_accuracy == pytest.approx(0.75)
    # the steer the vehicle gets is the bin's value: |0 - 0|, |0.1 - 0.12|, |-0.6 + 0.6|, |0.7 - 0.3|
    assert result.steer_error == pytest.approx((0.02 + 0.4) / 4, abs=1e-6)
    # the cross-entropy is over the head's bins, each sample's target the bin nearest its steer (10, 11, 4, 13):
    # the fourth predicts bin 17, so its loss is about 10 (logits 10 apart), the others' about 0
    assert result.loss_steer == pytest.approx(10.0 / 4, rel=0.01)


def test_evaluate_target_speed_model_by_hand():
    # sample speeds 0, 1.5, 3, 4.5 m/s, true target speeds 0, 2, 4, 6; predicted 0, 5, 1, 10 (scaled by 1/10)
    actions = [[0.5, 0.0, 0.0], [0.0, 0.125, 1.0], [0.2, -0.275, 0.0], [1.0, 0.0, 0.0]]
    model = FixedModel([[0.0], [0.5], [0.1], [1.0]], [0, 1, 5, 0], ModelConfig(longitudinal="target_speed", speed_horizon_s=2.0))
    result = evaluate_model(model, _samples(actions, [0, 1, 5, 0]))
    assert result.target_speed_error == pytest.approx((0 + 3 + 3 + 4) / 4)
    assert result.loss_throttle_brake == pytest.approx((0 + 0.09 + 0.09 + 0.16) / 4)
    # pedals through (target - v) / 2 s plus rolling resistance and drag, for 2.6 / 4.5 m/s^2:
    # standing and told to stop -> hold brake 0.9; 1.5 -> 5 m/s: 1.75 m/s^2; 3 -> 1: -1; 4.5 -> 10: full throttle
    resistance = [0.015 * 9.81 + 2.64e-4 * v * v for v in (1.5, 3.0)]
    throttle = [0.0, (1.75 + resistance[0]) / 2.6, 0.0, 1.0]
    brake = [0.9, 0.0, (1.0 - resistance[1]) / 4.5, 0.0]
    assert result.throttle_error == pytest.approx(np.mean(np.abs(np.array(throttle) - [0.5, 0.0, 0.2, 1.0])))
    assert result.brake_error == pytest.approx(np.mean(np.abs(np.array(brake) - [0.0, 1.0, 0.0, 0.0])))
    assert result.record()["target_speed_error"] == pytest.approx(2.5)


def test_a_pedal_model_has_no_target_speed_error():
    model = FixedModel([[0.5, 0.0]] * 2, [0, 0])
    result = evaluate_model(model, _samples([[0.5, 0.0, 0.0]] * 2, [0, 0]))
    assert math.isnan(result.target_speed_error) and result.record()["target_speed_error"] is None


def test_evaluate_model_on_no_samples():
    result = evaluate_model(FixedModel([[0.0, 0.0]], [0]), Samples.empty(48, 64))
    assert result.num_samples == 0 and math.isnan(result.loss) and math.isnan(result.balanced_accuracy)
    assert sum(map(sum, result.confusion)) == 0
