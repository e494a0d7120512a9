"""Centralized training: one model on every vehicle's samples (the federated schemes' upper bound),
epoch by epoch into a folder, with ``train --resume`` continuing after the last checkpointed epoch."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from crchfl_sumo.core.atomic import atomic_write_text, previous_path, read_latest, remove_stale_temporaries
from crchfl_sumo.core.config import to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_EPOCHS, check_range, check_seed
from crchfl_sumo.core.progress import Progress
from crchfl_sumo.core.result_files import METRICS_LOG_FILE, MODEL_FILE
from crchfl_sumo.data.dataset import load_samples
from crchfl_sumo.data.manifest import read_manifest
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.checkpoint import Checkpoint, check_weights, load_checkpoint, save_checkpoint
from crchfl_sumo.learning.devices import configure_determinism, resolve_device
from crchfl_sumo.learning.evaluation import always_straight
from crchfl_sumo.learning.model import State, build_model, check_signal_labels, model_from_state, with_training_data
from crchfl_sumo.learning.settings import SPEED_INPUTS, ModelConfig, TrainConfig, auto_ema_decay
from crchfl_sumo.learning.training import Learner, evaluate

log = logging.getLogger(__name__)


def train_centralized(
    train: Samples,
    test: Samples,
    epochs: int,
    out_dir: str | Path,
    model_config: ModelConfig,
    config: TrainConfig,
    seed: int,
    progress: Progress | None = None,
    initial_state: State | None = None,
    drive_settings: dict | None = None,
    resume: bool = False,
    overwrite: bool = False,
) -> list[dict]:
    """Train one model on all samples (the upper bound of the federated schemes).

    ``drive_settings``: the data set's camera and expert settings (``Manifest.drive_settings``),
    kept in the checkpoint's extra so that a drive renders and steers as the model learned.
    A new model takes its unset ``commands`` and ``stop_head`` from ``train`` (model.with_training_data):
    the lane-change heads where it holds a lane change, a stop head where it holds signal states.

    After every epoch: evaluates on ``test``, rewrites ``out_dir/metrics.jsonl``
    (one line per epoch: epoch and the test metrics of evaluation.py: loss,
    accuracy, balanced_accuracy, loss_throttle_brake, loss_steer, steer_error,
    throttle_error, brake_error, recall, confusion; test_samples;
    always_straight (accuracy and balanced_accuracy of the constant straight
    prediction on the test set); train_loss, train_accuracy, train_samples;
    samples_per_s) and ``out_dir/checkpoint.pt``, both atomically. ``progress`` hears ("train",
    samples trained so far, epochs x samples). Returns the metric records.

    The checkpoint also holds what a resume needs (extra "resume": both Adams'
    state, the shuffling generator's, the records), and the one it replaces
    becomes checkpoint.prev.pt (core.atomic). ``resume``: continue from the
    checkpoint in ``out_dir``, or from checkpoint.prev.pt (the epoch before)
    when checkpoint.pt is damaged; the run then ends with the weights and
    records of an uninterrupted one (samples_per_s aside, a wall-clock rate).
    Without ``resume``, a folder that holds a checkpoint is refused unless ``overwrite``
    (then the training starts afresh and replaces it): a finished training is not lost to a rerun.
    """
    check_range(epochs, "train_centralized: epochs", 1, MAX_EPOCHS, "a number of epochs")
    check_seed(seed, "train_centralized: seed")
    if len(train) == 0 or len(test) == 0:
        raise CrchflError("train: the training or test set is empty; check the data set folder")
    if train.image_hw != (model_config.image_height, model_config.image_width):
        raise CrchflError(
            f"model.image_height/image_width: {model_config.image_height} x {model_config.image_width} does not "
            f"match the data's {train.image_hw[0]} x {train.image_hw[1]}; set them to the data's size"
        )
    if initial_state is None:  # a network of its own takes the data's commands and signals; weights keep theirs
        model_config = with_training_data(model_config, [train])
    configure_determinism(config.deterministic)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out_dir)  # what a killed training's atomic writes left
    device = resolve_device(config.device)
    model = build_model(model_config, seed) if initial_state is None else model_from_state(model_config, initial_state, device)
    trainer = Learner(model.to(device), config)
    generator = torch.Generator().manual_seed(seed)
    checkpoint_path = out_dir / MODEL_FILE
    if not (resume or overwrite) and _holds_checkpoint(checkpoint_path):
        raise CrchflError(
            f"{out_dir}: holds a training's checkpoint; pass --resume to continue it, --overwrite to train "
            "afresh over it, or choose another --out"
        )
    records: list[dict] = []
    if resume and _holds_checkpoint(checkpoint_path):
        records = _resume_training(checkpoint_path, trainer, generator, seed, epochs, (len(train), len(test)))
        atomic_write_text(out_dir / METRICS_LOG_FILE, "".join(json.dumps(r) + "\n" for r in records))  # as checkpointed
    train_on_device, test_on_device = train.to(device), test.to(device)
    baseline = always_straight(test)
    for epoch in range(len(records) + 1, epochs + 1):
        start_s = time.perf_counter()
        offset = (epoch - 1) * len(train)
        per_epoch = None if progress is None else (
            lambda u, offset=offset: progress(dataclasses.replace(u, done=offset + u.done, total=epochs * len(train)))
        )
        train_metrics = trainer.train_epoch(train_on_device, generator, per_epoch)
        train_time_s = time.perf_counter() - start_s
        test_metrics = evaluate(trainer.kept_model, test_on_device, config).record()
        record = {
            "epoch": epoch,
            **{k: v for k, v in test_metrics.items() if k != "samples"},
            "test_samples": test_metrics["samples"],
            "always_straight": baseline,
            "train_loss": train_metrics.loss,
            "train_accuracy": train_metrics.accuracy,
            "train_samples": train_metrics.num_samples,
            "samples_per_s": len(train) / train_time_s,
            "precision": trainer.precision,
        }
        records.append(record)
        log.info(
            "epoch %d: test loss %.4f, accuracy %.3f, balanced accuracy %.3f (always straight %.3f)",
            epoch, record["loss"], record["accuracy"], record["balanced_accuracy"], baseline["balanced_accuracy"],
        )
        atomic_write_text(out_dir / METRICS_LOG_FILE, "".join(json.dumps(r) + "\n" for r in records))
        resume_state = {
            "optimizers": [optimizer.state_dict() for optimizer in trainer.optimizers],
            "generator": generator.get_state(),
            "records": records,
            "samples": [len(train), len(test)],
        }
        if trainer.average is not None:  # the checkpoint's weights are the average; a resume needs both
            resume_state["trained_weights"] = trainer.model.state_dict()
            resume_state["average"] = trainer.average.state_dict()
        save_checkpoint(
            checkpoint_path,
            model_config,
            trainer.kept_model.state_dict(),
            {
                "epoch": epoch, "seed": seed, "train_config": to_mapping(config), "metrics": record,
                "resume": resume_state, **(drive_settings or {}),
            },
            keep_previous=True,
        )
    return records


RESUME_KEYS = {"optimizers", "generator", "records", "samples"}
AVERAGE_RESUME_KEYS = {"trained_weights", "average"}  # besides, with train.ema_decay


def _centralized_settings(train_config: Any) -> Any:
    """The train settings a centralized checkpoint must match: all but multi_vehicle, which only says how
    a federated run trains its vehicles (its default changed; checkpoints written before still resume),
    and precision, which is checked as resolved against the precision the epochs trained in."""
    if not isinstance(train_config, dict):
        return train_config
    return {key: value for key, value in train_config.items() if key not in ("multi_vehicle", "precision")}


def _resume_training(
    path: Path, trainer: Learner, generator: torch.Generator, seed: int, epochs: int, samples: tuple[int, int]
) -> list[dict]:
    """Load the checkpoint at ``path`` (or its previous copy) into ``trainer`` and ``generator``; its records.

    Refused: a checkpoint of other settings (model, training, seed) or data (sample counts), one
    whose epochs trained in another precision than this training would, or one of more epochs
    than ``epochs``.
    """
    checkpoint, used = read_latest(path, _resumable_checkpoint, "checkpoint", "delete the folder to train afresh")
    extra, state = checkpoint.extra, checkpoint.extra["resume"]
    if (checkpoint.model_config != trainer.model.config or extra.get("seed") != seed
            or _centralized_settings(extra.get("train_config")) != _centralized_settings(to_mapping(trainer.config))
            or list(state["samples"]) != list(samples)):
        raise CrchflError(
            f"{used}: written by a training with other settings or data; resume with the original command "
            "(model, seed, data set) or choose another --out"
        )
    records = list(state["records"])
    trained_in = _trained_precision(records, extra.get("train_config"))
    if trained_in not in (None, trainer.precision):  # "auto" decided on another machine, or another precision
        raise CrchflError(
            f"{used}: its epochs trained in {trained_in}; this training would continue in {trainer.precision} "
            f"(train.precision {trainer.config.precision!r} on this machine); continue it with train.precision "
            f"= {trained_in!r} (train --precision {trained_in}) or choose another --out"
        )
    if len(records) > epochs:
        raise CrchflError(f"{used}: holds {len(records)} epochs already; ask for --epochs {len(records)} or more")
    try:
        if trainer.average is None:
            trainer.model.load_state_dict(checkpoint.state_dict)
        else:
            trainer.model.load_state_dict(state["trained_weights"])
            trainer.average.load_state_dict(state["average"])
        for optimizer, optimizer_state in zip(trainer.optimizers, state["optimizers"]):
            optimizer.load_state_dict(optimizer_state)
        generator.set_state(state["generator"])
    except (KeyError, ValueError, RuntimeError, TypeError) as exc:
        raise CrchflError(f"{used}: its optimizer or generator state does not fit ({exc}); delete the folder") from None
    log.info("resuming %s after epoch %d", path.parent, len(records))
    return records


def _trained_precision(records: list[dict], train_config: Any) -> str | None:
    """The precision the checkpointed epochs trained in (None: no epoch yet). Records name it since
    "auto" exists; before, the train config named it, and before train.precision existed it was fp32."""
    if not records:
        return None
    if "precision" in records[-1]:
        return records[-1]["precision"]
    return train_config.get("precision", "fp32") if isinstance(train_config, dict) else "fp32"


def _resumable_checkpoint(path: Path) -> Checkpoint:
    """A training checkpoint with its resume state, checked; a CrchflError if missing, damaged or without one."""
    checkpoint = load_checkpoint(path)
    check_weights(checkpoint.model_config, checkpoint.state_dict, str(path))
    state = checkpoint.extra.get("resume")
    if not (
        isinstance(state, dict) and set(state) in (RESUME_KEYS, RESUME_KEYS | AVERAGE_RESUME_KEYS)
        and all(isinstance(state.get(key, {}), dict) for key in AVERAGE_RESUME_KEYS)
        and isinstance(state["optimizers"], list) and len(state["optimizers"]) == 2
        and all(isinstance(o, dict) for o in state["optimizers"])
        and isinstance(state["generator"], torch.Tensor) and state["generator"].dtype == torch.uint8
        and isinstance(state["records"], list) and all(isinstance(r, dict) for r in state["records"])
        and len(state["records"]) == checkpoint.extra.get("epoch")
        and isinstance(state["samples"], list) and len(state["samples"]) == 2
    ):
        raise CrchflError(
            f"{path}: holds no resume state (written before `train --resume` existed, or damaged); "
            "delete the folder to train afresh"
        )
    return checkpoint


def train_command(
    dataset: str | Path, out_dir: str | Path, epochs: int, size: str, arch: str, config: TrainConfig, seed: int,
    resume: bool = False, overwrite: bool = False, progress: Progress | None = None, speed_input: str = "none",
    stop_head: bool | None = None, command_pedals: bool = False, red_hold: bool = False,
    train_towns: Sequence[str] | None = None, auto_ema: bool = False,
) -> dict[str, Any]:
    """What `crchfl-sumo train` does: the model of ``size`` and ``arch`` at the data set's image size and speed
    horizon (and the speed as the input ``speed_input`` names: SPEED_INPUTS; ``stop_head``, ``command_pedals``, ``red_hold``: ModelConfig's),
    trained on its train shards (``train_towns``: those towns' only) and evaluated on its test shards (all of them);
    the last epoch's metrics line. ``auto_ema``: `train`'s default moving average (auto_ema_decay) in place of
    ``config.ema_decay``; a folder resumed keeps the one its checkpoint trained with (0 before the default)."""
    manifest = read_manifest(dataset)
    train = load_samples(dataset, "train", manifest.town_vehicles(train_towns, str(dataset)))
    test = load_samples(dataset, "test")
    model_config = ModelConfig(size, *train.image_hw, arch=arch, speed_horizon_s=manifest.speed_horizon_s,
                               stop_head=stop_head, command_pedals=command_pedals, red_hold=red_hold,
                               **SPEED_INPUTS[speed_input])
    check_signal_labels(model_config, train.signal_state, str(dataset))
    if auto_ema:
        checkpoint_path = Path(out_dir) / MODEL_FILE
        resumed = resume and _holds_checkpoint(checkpoint_path)
        config = dataclasses.replace(config, ema_decay=_checkpointed_ema_decay(checkpoint_path) if resumed
                                     else auto_ema_decay(len(train), config.batch_size))
    records = train_centralized(
        train, test, epochs, out_dir, model_config, config, seed, progress=progress,
        drive_settings=manifest.drive_settings(f"{dataset}/manifest.json"), resume=resume, overwrite=overwrite,
    )
    return records[-1]


def _holds_checkpoint(path: Path) -> bool:
    """Whether a training wrote the checkpoint ``path``, or its previous copy (core.atomic)."""
    return path.exists() or previous_path(path).exists()


def _checkpointed_ema_decay(path: Path) -> float:
    """The ``ema_decay`` the checkpoint at ``path`` (or its previous copy) trained with (absent: 0, as before
    `train` averaged by default)."""
    checkpoint, _ = read_latest(path, _resumable_checkpoint, "checkpoint", "delete the folder to train afresh")
    train_config = checkpoint.extra.get("train_config")
    return float(train_config.get("ema_decay", 0.0)) if isinstance(train_config, dict) else 0.0
