"""Test-set metrics of a driving model, and the always-straight baseline they are read against.

``evaluate_model(model, samples)`` (``training.evaluate`` with a TrainConfig) gives, over a set of N samples:

- loss: MSE of branch I (mean over throttle and brake, or on the scaled target
  speed: model.longitudinal_target) + cross-entropy of branch II (over the
  steer head's classes: model.steer_targets);
  loss_throttle_brake and loss_steer are the two parts (plain, unweighted means);
- accuracy: top-1 steer-class accuracy, the paper's Accuracy (a head of finer
  steer bins is read on the paper's 7 classes: model.paper_class_of_bin);
- confusion: the 7 x 7 matrix of counts, row = true class, column = predicted class;
- recall: per class c, confusion[c, c] / (samples of true class c); NaN for a
  class absent from the set;
- balanced_accuracy: the mean of recall over the classes PRESENT in the set
  (a class with no samples has no recall and is left out of the mean;
  predictions of an absent class count as errors of the true class). This is
  sklearn's ``balanced_accuracy_score``. A model that always predicts one
  class present in the set scores 1 / (number of classes present): 1/7 with
  all seven;
- steer_error: mean |value of the predicted class - true analogue steer|,
  the error of the steer the vehicle would get after the DAC;
- throttle_error, brake_error: mean absolute error of the two pedals (a
  target-speed model's pedals are model.longitudinal_pedals' at the sample's
  speed, for SUMO's passenger car);
- target_speed_error: mean absolute error of the target speed [m/s] (NaN for a
  model that predicts pedals).

``always_straight(samples)`` gives the accuracy, balanced accuracy and steer
error (mean |true steer|) of the constant prediction "class 0" (straight) on
the same set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from crchfl_sumo.data.labels import NUM_STEER_CLASSES
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.model import (
    DrivingModel,
    longitudinal_pedals,
    longitudinal_target,
    paper_class_of_bin,
    steer_targets,
    steer_values,
)
from crchfl_sumo.learning.settings import SPEED_SCALE_MPS

STRAIGHT_CLASS = 0  # labels.STEER_CLASS_VALUES[0] == 0.0


@dataclass(frozen=True)
class Evaluation:
    """A model's metrics on one set (module docstring). An empty set gives NaN values and zero counts."""

    loss: float
    accuracy: float
    loss_throttle_brake: float
    loss_steer: float
    num_samples: int
    balanced_accuracy: float
    recall: tuple[float, ...]  # per steer class; NaN where the class is absent
    confusion: tuple[tuple[int, ...], ...]  # [true class][predicted class] counts
    steer_error: float
    throttle_error: float
    brake_error: float
    target_speed_error: float

    def record(self) -> dict:
        """The metrics as plain JSON values (NaN recall as None), num_samples as ``samples``."""
        return {
            "loss": self.loss,
            "accuracy": self.accuracy,
            "balanced_accuracy": self.balanced_accuracy,
            "loss_throttle_brake": self.loss_throttle_brake,
            "loss_steer": self.loss_steer,
            "steer_error": self.steer_error,
            "throttle_error": self.throttle_error,
            "brake_error": self.brake_error,
            "target_speed_error": None if math.isnan(self.target_speed_error) else self.target_speed_error,
            "recall": [None if math.isnan(r) else r for r in self.recall],
            "confusion": [list(row) for row in self.confusion],
            "samples": self.num_samples,
        }


def confusion_matrix(true_class: np.ndarray, predicted_class: np.ndarray) -> np.ndarray:
    """int64 [7, 7] counts: row = true class, column = predicted class."""
    true_class, predicted_class = np.asarray(true_class, np.int64), np.asarray(predicted_class, np.int64)
    flat = true_class * NUM_STEER_CLASSES + predicted_class
    return np.bincount(flat, minlength=NUM_STEER_CLASSES**2).reshape(NUM_STEER_CLASSES, NUM_STEER_CLASSES)


def recall_per_class(confusion: np.ndarray) -> np.ndarray:
    """float64 [7]: diagonal / row sum, NaN for a class with no true samples."""
    support = confusion.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(support > 0, np.diag(confusion) / np.maximum(support, 1), np.nan)


def balanced_accuracy(confusion: np.ndarray) -> float:
    """Mean recall over the classes present (NaN when no class is)."""
    recall = recall_per_class(confusion)
    present = ~np.isnan(recall)
    return float(recall[present].mean()) if present.any() else math.nan


def always_straight(samples: Samples) -> dict[str, float]:
    """Accuracy, balanced accuracy and DAC steer error of predicting class 0 (straight) for every sample."""
    true_class = samples.steer_class.cpu().numpy()
    confusion = confusion_matrix(true_class, np.full_like(true_class, STRAIGHT_CLASS))
    n = len(true_class)
    return {
        "accuracy": float(confusion[STRAIGHT_CLASS, STRAIGHT_CLASS] / n) if n else math.nan,
        "balanced_accuracy": balanced_accuracy(confusion),
        "steer_error": float(samples.actions[:, 1].abs().double().mean()) if n else math.nan,
    }


@torch.no_grad()
def evaluate_model(model: DrivingModel, samples: Samples, eval_batch_size: int = 256) -> Evaluation:
    """``model``'s metrics on ``samples`` (on the model's device, in eval mode; the mode is restored)."""
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    sums = np.zeros(6)  # MSE, CE, |throttle|, |brake|, |steer|, |target speed| sums
    predicted = []
    values = torch.as_tensor(steer_values(model.config), device=device)
    paper_class = torch.as_tensor(paper_class_of_bin(model.config), device=device)
    try:
        for start in range(0, len(samples), eval_batch_size):
            batch = samples.subset(slice(start, start + eval_batch_size)).to(device)
            longitudinal, steer_logits = model(batch.images, batch.command, batch.speed_mps)
            guess = steer_logits.argmax(dim=1)  # the steer head's class
            target = longitudinal_target(model.config, batch)
            output = longitudinal.double().cpu().numpy()
            throttle, brake = longitudinal_pedals(model.config, output, batch.speed_mps.cpu().numpy())
            actions = batch.actions.double().cpu().numpy()
            speed_error = np.abs(output[:, 0] * SPEED_SCALE_MPS - batch.target_speed_mps.cpu().numpy()).sum()
            sums += [
                float((longitudinal - target).double().square().mean(dim=1).sum()),
                float(F.cross_entropy(steer_logits.double(), steer_targets(model.config, batch.steer_class,
                                                                           batch.actions[:, 1]), reduction="sum")),
                np.abs(throttle - actions[:, 0]).sum(),
                np.abs(brake - actions[:, 2]).sum(),
                float((values[guess] - batch.actions[:, 1]).abs().double().sum()),
                speed_error if model.config.longitudinal == "target_speed" else math.nan,
            ]
            predicted.append(paper_class[guess].cpu())
    finally:
        model.train(was_training)
    n = len(samples)
    guesses = torch.cat(predicted).numpy() if predicted else np.zeros(0, np.int64)
    confusion = confusion_matrix(samples.steer_class.cpu().numpy(), guesses)
    mse, ce, throttle, brake, steer, speed = (v / n if n else math.nan for v in sums.tolist())
    return Evaluation(
        loss=mse + ce,
        accuracy=float(np.trace(confusion) / n) if n else math.nan,
        loss_throttle_brake=mse,
        loss_steer=ce,
        num_samples=n,
        balanced_accuracy=balanced_accuracy(confusion),
        recall=tuple(float(r) for r in recall_per_class(confusion)),
        confusion=tuple(tuple(int(c) for c in row) for row in confusion),
        steer_error=steer,
        throttle_error=throttle,
        brake_error=brake,
        target_speed_error=speed,
    )
