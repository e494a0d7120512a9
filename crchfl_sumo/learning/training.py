"""Local training and evaluation of driving models: one vehicle, many vehicles, or centralized.

Training settings follow the paper's Table II: branch I (throttle, brake) is
trained with MSE, branch II (steer class) with cross-entropy, each branch by its
own Adam (betas 0.9/0.999, weight decay 3e-3), batch 32; the learning rate
and the balancing (balance.py) are the measured recipe of docs/model.md
(the paper's learning rate is 1e-4). The reported Loss is the sum of both
branch losses; Accuracy is branch II's top-1 accuracy; ``evaluate`` gives the
full test-set metrics of evaluation.py.

Many vehicles of one aggregation step are trained by ``train_vehicles``. Two
methods give the same result (tests/learning/test_training.py checks it):

- ``sequential``: one vehicle after the other with torch.optim.Adam. Fastest on
  a CPU, where a batch of 32 already keeps the cores busy (docs/model.md).
- ``vmap``: all vehicles at once, torch.func.functional_call + vmap over
  stacked parameters, with a stacked Adam. Vehicles with fewer batches simply
  drop out of the vmapped step once their batches are used up (ragged data).

Models cross this module's boundary as plain state dicts (name -> tensor).
Each vehicle starts with fresh optimizer state, as a vehicle does after it
receives a new model. Shuffling uses a torch.Generator seeded from the caller's
seed and the vehicle's index, so the result does not depend on the method.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch.func import functional_call, grad, vmap
from torch.nn import functional as F

from crchfl_sumo.core.atomic import atomic_write_text, previous_path, read_latest, remove_stale_temporaries
from crchfl_sumo.core.config import to_mapping
from crchfl_sumo.core.cpus import pinned_threads
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_EPOCHS, check_range, check_seed
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.balance import class_weights, epoch_batches
from crchfl_sumo.learning.checkpoint import Checkpoint, check_weights, load_checkpoint, save_checkpoint
from crchfl_sumo.learning.evaluation import Evaluation, always_straight, evaluate_model
from crchfl_sumo.learning.model import (
    DrivingModel,
    State,
    build_model,
    longitudinal_target,
    model_from_state,
    paper_class_of_bin,
    steer_targets,
)
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig

log = logging.getLogger(__name__)


METRICS_FILE = "metrics.jsonl"
CHECKPOINT_FILE = "checkpoint.pt"


@dataclass(frozen=True)
class Metrics:
    """Training metrics of the batches as trained: Loss (sum of both branch losses, the steer
    part weighted as trained), Accuracy (branch II top-1) and the parts, over num_samples.

    A vehicle without samples gets num_samples 0 and NaN values.
    """

    loss: float
    accuracy: float
    loss_throttle_brake: float
    loss_steer: float
    num_samples: int

    @staticmethod
    def from_sums(loss_tb_sum: float, loss_steer_sum: float, correct: float, count: int) -> Metrics:
        if count == 0:
            return Metrics(math.nan, math.nan, math.nan, math.nan, 0)
        loss_tb, loss_steer = loss_tb_sum / count, loss_steer_sum / count
        return Metrics(loss_tb + loss_steer, correct / count, loss_tb, loss_steer, count)


def resolve_device(name: str) -> torch.device:
    """"auto" -> CUDA when available, else CPU; "cuda" without a GPU is a CrchflError."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise CrchflError("train.device: 'cuda' was asked for but no CUDA device is available; use 'auto' or 'cpu'")
    return torch.device(name)


def configure_determinism(enabled: bool) -> None:
    """Turn on deterministic algorithms (process-wide); does nothing when ``enabled`` is False."""
    if not enabled:
        return
    # cuBLAS needs a fixed workspace to be deterministic; it reads this before its first use.
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.backends.cudnn.benchmark = False
    torch.use_deterministic_algorithms(True)


@functools.cache
def native_bfloat16(device_type: str) -> bool:
    """Whether this machine multiplies bfloat16 in hardware: AVX-512 BF16 or AMX on a CPU, a GPU that does.

    Elsewhere bfloat16 is emulated, slower than float32 (measured by capping oneDNN's instruction set
    here: 0.60x with AVX-512 and 0.12x with AVX2; docs/model.md).
    """
    if device_type == "cuda":
        return torch.cuda.is_bf16_supported(including_emulation=False)
    # torch's own probes of the CPU (private names: a torch without them counts as no bfloat16)
    probes = (getattr(torch.cpu, "_is_avx512_bf16_supported", None), getattr(torch.cpu, "_is_amx_tile_supported", None))
    return any(probe() for probe in probes if probe is not None)


@functools.cache
def _warn_emulated_bfloat16(device_type: str) -> None:
    log.warning(
        "train.precision = 'bf16' on a %s without bfloat16 arithmetic: it is emulated and slower than float32 "
        "(0.12 to 0.60x measured); set train.precision = 'fp32' (train --precision fp32)", device_type.upper()
    )


def resolved_precision(config: TrainConfig, device: torch.device) -> str:
    """"fp32" or "bf16": ``config.precision``, with "auto" decided by the device's bfloat16 arithmetic."""
    if config.precision == "auto":
        return "bf16" if native_bfloat16(device.type) else "fp32"
    if config.precision == "bf16" and not native_bfloat16(device.type):
        _warn_emulated_bfloat16(device.type)
    return config.precision


def resolved_multi_vehicle(config: TrainConfig, model_config: ModelConfig, device_type: str) -> str:
    """"sequential" or "vmap": ``config.multi_vehicle``, with "auto" decided by the device.

    On a GPU one vectorised step for all vehicles launches a step's kernels once instead of once a
    vehicle (a step there is bound by launching, not arithmetic: 1.42x on an H200); on a CPU the
    sequential loop is faster (docs/benchmarks.md). BatchNorm cannot be vmapped, so it stays sequential.
    """
    if config.multi_vehicle != "auto":
        return config.multi_vehicle
    return "vmap" if device_type == "cuda" and vmappable(model_config) else "sequential"


def vmappable(model_config: ModelConfig) -> bool:
    """Whether vmap can train the network: not BatchNorm, whose running statistics update in place."""
    return not (model_config.norm == "batch" and model_config.arch == "cil")


def forward_precision(precision: str, device: torch.device) -> contextlib.AbstractContextManager:
    """The context a training forward pass runs in: bfloat16 autocast for ``precision`` "bf16"
    (resolved_precision's answer, decided once per training), else none.

    Only the forward pass runs inside it; the losses are taken in float32 from its outputs.
    """
    if precision == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def vehicle_seed(seed: int, vehicle_index: int) -> int:
    """Seed of one vehicle's shuffling, derived from the caller's seed."""
    return int(np.random.SeedSequence([seed, vehicle_index]).generate_state(1)[0])


def branch_losses(
    longitudinal: torch.Tensor,
    steer_logits: torch.Tensor,
    longitudinal_target: torch.Tensor,
    steer_class: torch.Tensor,
    class_weight: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(MSE of branch I on its target, model.longitudinal_target; cross-entropy of branch II), batch means.

    ``steer_class``: the steer head's classes (model.steer_targets); ``class_weight`` [steer_bins]
    (balance.class_weights) makes the cross-entropy a weighted mean.
    """
    steer_loss = F.cross_entropy(steer_logits, steer_class, weight=class_weight)
    return F.mse_loss(longitudinal, longitudinal_target), steer_loss


@pinned_threads()  # each torch thread on a CPU of its own (core/cpus.py)
def evaluate(model: DrivingModel, samples: Samples, config: TrainConfig = TrainConfig()) -> Evaluation:
    """``model``'s test metrics on ``samples`` (evaluation.py), in batches of ``config.eval_batch_size``."""
    return evaluate_model(model, samples, config.eval_batch_size)


class Learner:
    """One model with one Adam per branch; trains epoch by epoch on Samples.

    (The federation's Trainer, TorchTrainer and RayTrainer train many
    vehicles' models; a Learner is one model.) The model is owned by the
    learner and updated in place; ``state()`` gives
    a CPU copy of its weights.
    """

    def __init__(self, model: DrivingModel, config: TrainConfig) -> None:
        self.model = model
        self.config = config
        self.precision = resolved_precision(config, self.device)
        adam = dict(
            lr=config.learning_rate,
            betas=(config.beta1, config.beta2),
            eps=config.adam_eps,
            weight_decay=config.weight_decay,
        )
        self.optimizers = (
            torch.optim.Adam(model.branch_throttle_brake.parameters(), **adam),
            torch.optim.Adam(model.branch_steer.parameters(), **adam),
        )

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def state(self) -> State:
        return {name: t.detach().cpu().clone() for name, t in self.model.state_dict().items()}

    @pinned_threads()  # each torch thread on a CPU of its own (core/cpus.py)
    def train_epoch(self, samples: Samples, generator: torch.Generator, progress: Progress | None = None) -> Metrics:
        """One pass over ``samples`` in shuffled batches; metrics are those of the batches as trained.

        ``progress`` hears ("train", samples done this epoch, samples) after every batch.
        """
        self.model.train()
        samples = samples.to(self.device)
        model_config = self.model.config
        classes = steer_targets(model_config, samples.steer_class, samples.actions[:, 1])
        paper_class = torch.as_tensor(paper_class_of_bin(model_config), device=self.device)
        weight = class_weights(classes, self.config.class_weighting, model_config.steer_bins)
        weight = None if weight is None else weight.to(self.device)
        sums = torch.zeros(3, dtype=torch.float64, device=self.device)
        done = 0
        for indices in epoch_batches(samples, self.config.batch_size, self.config.sampling, generator):
            indices = indices.to(self.device)
            images, steer_class = samples.images[indices], classes[indices]
            target = longitudinal_target(model_config, samples.actions[indices], samples.target_speed_mps[indices])
            for optimizer in self.optimizers:
                optimizer.zero_grad(set_to_none=True)
            with forward_precision(self.precision, self.device):
                longitudinal, steer_logits = self.model(images, samples.command[indices], samples.speed_mps[indices])
            longitudinal, steer_logits = longitudinal.float(), steer_logits.float()
            loss_tb, loss_steer = branch_losses(longitudinal, steer_logits, target, steer_class, weight)
            # The branches share no weights, so one backward of the sum gives each branch its own gradient.
            (loss_tb + loss_steer).backward()
            for optimizer in self.optimizers:
                optimizer.step()
            n = len(indices)
            with torch.no_grad():
                # accuracy on the paper's classes, whatever the head's bins
                correct = (paper_class[steer_logits.argmax(dim=1)] == samples.steer_class[indices]).sum().double()
                sums += torch.stack([loss_tb.detach().double() * n, loss_steer.detach().double() * n, correct])
            done += n
            report(progress, "train", done, len(samples))
        loss_tb_sum, loss_steer_sum, correct = sums.tolist()
        return Metrics.from_sums(loss_tb_sum, loss_steer_sum, correct, len(samples))


def train_vehicle(
    state: State,
    samples: Samples,
    epochs: int,
    model_config: ModelConfig,
    config: TrainConfig,
    seed: int,
) -> tuple[State, list[Metrics]]:
    """Train one model for ``epochs`` on ``samples``: (new state on CPU, training metrics per epoch).

    ``seed`` is any integer torch's generator takes: callers derive one per vehicle and step.
    """
    check_range(epochs, "train_vehicle: epochs", 0, MAX_EPOCHS, "a number of epochs")
    configure_determinism(config.deterministic)
    device = resolve_device(config.device)
    trainer = Learner(model_from_state(model_config, state, device), config)
    samples = samples.to(device)  # once, not every epoch
    generator = torch.Generator().manual_seed(seed)
    metrics = [trainer.train_epoch(samples, generator) for _ in range(epochs)]
    return trainer.state(), metrics


def train_vehicles(
    states: Sequence[State],
    vehicle_samples: Sequence[Samples],
    epochs: int,
    model_config: ModelConfig,
    config: TrainConfig,
    seed: int,
) -> tuple[list[State], list[list[Metrics]]]:
    """Train every vehicle's model on its own samples, by ``config.multi_vehicle``.

    states[i] is vehicle i's starting model (pass the same dict several times
    for a shared start). Returns new states (CPU) and per-vehicle, per-epoch
    training metrics. Vehicle i shuffles with ``vehicle_seed(seed, i)``.
    """
    if len(states) != len(vehicle_samples):
        raise ValueError(f"train_vehicles: {len(states)} states for {len(vehicle_samples)} vehicles")
    check_range(epochs, "train_vehicles: epochs", 0, MAX_EPOCHS, "a number of epochs")  # seed: as train_vehicle's
    configure_determinism(config.deterministic)
    if config.multi_vehicle == "vmap" and not vmappable(model_config):
        raise CrchflError(
            "train.multi_vehicle: 'vmap' cannot train BatchNorm (its running statistics are updated in place); "
            "use multi_vehicle = 'sequential' or model.norm = 'group'"
        )
    if states and resolved_multi_vehicle(config, model_config, resolve_device(config.device).type) == "vmap":
        return _train_vehicles_vmap(states, vehicle_samples, epochs, model_config, config, seed)
    results = [
        train_vehicle(state, samples, epochs, model_config, config, vehicle_seed(seed, i))
        for i, (state, samples) in enumerate(zip(states, vehicle_samples))
    ]
    return [state for state, _ in results], [metrics for _, metrics in results]


@pinned_threads()  # each torch thread on a CPU of its own (core/cpus.py)
def _train_vehicles_vmap(
    states: Sequence[State],
    vehicle_samples: Sequence[Samples],
    epochs: int,
    model_config: ModelConfig,
    config: TrainConfig,
    seed: int,
) -> tuple[list[State], list[list[Metrics]]]:
    """All vehicles in one vmapped step; Adam on stacked tensors, identical to torch.optim.Adam's update."""
    device = resolve_device(config.device)
    precision = resolved_precision(config, device)
    num_vehicles, batch_size = len(states), config.batch_size
    # A weightless copy of the network for functional_call: its parameters are replaced on each call.
    with torch.device("meta"):
        template = DrivingModel(model_config)
    names = [name for name, _ in template.named_parameters()]
    params = {name: torch.stack([s[name] for s in states]).to(device, torch.float32) for name in names}
    exp_avg = {name: torch.zeros_like(p) for name, p in params.items()}
    exp_avg_sq = {name: torch.zeros_like(p) for name, p in params.items()}
    samples_on_device = [s.to(device) for s in vehicle_samples]

    # Each vehicle's whole schedule (all epochs) as (epoch, indices); vehicle v takes its t-th step at step t.
    schedules: list[list[tuple[int, torch.Tensor]]] = []
    for v, samples in enumerate(vehicle_samples):
        generator = torch.Generator().manual_seed(vehicle_seed(seed, v))
        schedules.append(
            [(e, idx) for e in range(epochs) for idx in epoch_batches(samples, batch_size, config.sampling, generator)]
        )
    # Each vehicle's steer-head classes (model.steer_targets), and their weights from its own samples
    # (all ones for "none").
    bins = model_config.steer_bins
    vehicle_classes = [steer_targets(model_config, s.steer_class, s.actions[:, 1]) for s in samples_on_device]
    paper_class = torch.as_tensor(paper_class_of_bin(model_config), device=device)
    steer_weights = []
    for classes in vehicle_classes:
        weight = class_weights(classes, config.class_weighting, bins)
        steer_weights.append(torch.ones(bins) if weight is None else weight)
    steer_weights_on_device = torch.stack(steer_weights).to(device)
    # Per vehicle and epoch: summed branch-I loss, branch-II loss, correct count.
    sums = torch.zeros(num_vehicles, max(epochs, 1), 3, dtype=torch.float64, device=device)

    def loss_fn(
        p: State,
        images: torch.Tensor,
        command: torch.Tensor,
        speed_mps: torch.Tensor,
        target: torch.Tensor,
        steer_class: torch.Tensor,
        paper_steer_class: torch.Tensor,
        weight: torch.Tensor,
        class_weight: torch.Tensor,
    ):
        with forward_precision(precision, device):
            longitudinal, steer_logits = functional_call(template, p, (images, command, speed_mps))
        longitudinal, steer_logits = longitudinal.float(), steer_logits.float()
        per_sample_tb = (longitudinal - target).square().mean(dim=1)
        per_sample_steer = F.cross_entropy(steer_logits, steer_class, reduction="none")
        n = weight.sum()
        steer_weight = weight * class_weight[steer_class]  # torch's weighted mean, padding rows at 0
        loss_tb = (per_sample_tb * weight).sum() / n
        loss_steer = (per_sample_steer * steer_weight).sum() / steer_weight.sum()
        correct = ((paper_class[steer_logits.argmax(dim=1)] == paper_steer_class).to(weight.dtype) * weight).sum()
        return loss_tb + loss_steer, torch.stack([loss_tb * n, loss_steer * n, correct]).detach()

    grad_fn = vmap(grad(loss_fn, has_aux=True))
    num_steps = max((len(s) for s in schedules), default=0)
    for step in range(num_steps):
        active = [v for v in range(num_vehicles) if step < len(schedules[v])]
        images, commands, speeds, targets, classes, paper_classes, weights = [], [], [], [], [], [], []
        for v in active:
            indices = schedules[v][step][1].to(device)
            n = len(indices)
            weight = torch.ones(batch_size, device=device)
            if n < batch_size:  # short last batch: pad with sample 0 at weight 0
                indices = torch.cat([indices, indices.new_zeros(batch_size - n)])
                weight[n:] = 0
            samples = samples_on_device[v]
            images.append(samples.images[indices])
            commands.append(samples.command[indices])
            speeds.append(samples.speed_mps[indices])
            target = longitudinal_target(model_config, samples.actions[indices], samples.target_speed_mps[indices])
            targets.append(target)
            classes.append(vehicle_classes[v][indices])
            paper_classes.append(samples.steer_class[indices])
            weights.append(weight)
        every = len(active) == num_vehicles
        rows = torch.tensor(active, device=device)
        current = params if every else {name: p[rows] for name, p in params.items()}
        grads, batch_sums = grad_fn(
            current,
            torch.stack(images),
            torch.stack(commands),
            torch.stack(speeds),
            torch.stack(targets),
            torch.stack(classes),
            torch.stack(paper_classes),
            torch.stack(weights),
            steer_weights_on_device[rows],
        )
        _stacked_adam_step(params, exp_avg, exp_avg_sq, grads, None if every else rows, step + 1, config)
        epoch_of = torch.tensor([schedules[v][step][0] for v in active], device=device)
        sums.index_put_((rows, epoch_of), batch_sums.to(torch.float64), accumulate=True)

    new_states = [{name: params[name][v].detach().cpu().clone() for name in names} for v in range(num_vehicles)]
    sums_cpu = sums.cpu().tolist()
    metrics = [
        [Metrics.from_sums(*sums_cpu[v][e], len(vehicle_samples[v])) for e in range(epochs)]
        for v in range(num_vehicles)
    ]
    return new_states, metrics


@torch.no_grad()
def _stacked_adam_step(
    params: State,
    exp_avg: State,
    exp_avg_sq: State,
    grads: State,
    rows: torch.Tensor | None,
    step: int,
    config: TrainConfig,
) -> None:
    """torch.optim.Adam's update (L2 weight decay added to the gradient) on the given rows of stacked tensors.

    All rows updated together are at the same step count, so bias corrections are scalars.
    """
    beta1, beta2 = config.beta1, config.beta2
    bias_correction1 = 1 - beta1**step
    bias_correction2_sqrt = math.sqrt(1 - beta2**step)
    step_size = config.learning_rate / bias_correction1
    for name, g in grads.items():
        p = params[name] if rows is None else params[name][rows]
        m = exp_avg[name] if rows is None else exp_avg[name][rows]
        v = exp_avg_sq[name] if rows is None else exp_avg_sq[name][rows]
        g = g.add(p, alpha=config.weight_decay)
        m.lerp_(g, 1 - beta1)
        v.mul_(beta2).addcmul_(g, g, value=1 - beta2)
        denom = (v.sqrt() / bias_correction2_sqrt).add_(config.adam_eps)
        p.addcdiv_(m, denom, value=-step_size)
        if rows is not None:  # rows were gathered copies: write them back
            params[name][rows] = p
            exp_avg[name][rows] = m
            exp_avg_sq[name][rows] = v


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
) -> list[dict]:
    """Train one model on all samples (the upper bound of the federated schemes).

    ``drive_settings``: the data set's camera and expert settings (``Manifest.drive_settings``),
    kept in the checkpoint's extra so that a drive renders and steers as the model learned.

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
    configure_determinism(config.deterministic)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out_dir)  # what a killed training's atomic writes left
    device = resolve_device(config.device)
    model = build_model(model_config, seed) if initial_state is None else model_from_state(model_config, initial_state, device)
    trainer = Learner(model.to(device), config)
    generator = torch.Generator().manual_seed(seed)
    checkpoint_path = out_dir / CHECKPOINT_FILE
    records: list[dict] = []
    if resume and (checkpoint_path.exists() or previous_path(checkpoint_path).exists()):
        records = _resume_training(checkpoint_path, trainer, generator, seed, epochs, (len(train), len(test)))
        atomic_write_text(out_dir / METRICS_FILE, "".join(json.dumps(r) + "\n" for r in records))  # as checkpointed
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
        test_metrics = evaluate(trainer.model, test_on_device, config).record()
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
        atomic_write_text(out_dir / METRICS_FILE, "".join(json.dumps(r) + "\n" for r in records))
        resume_state = {
            "optimizers": [optimizer.state_dict() for optimizer in trainer.optimizers],
            "generator": generator.get_state(),
            "records": records,
            "samples": [len(train), len(test)],
        }
        save_checkpoint(
            checkpoint_path,
            model_config,
            trainer.model.state_dict(),
            {
                "epoch": epoch, "seed": seed, "train_config": to_mapping(config), "metrics": record,
                "resume": resume_state, **(drive_settings or {}),
            },
            keep_previous=True,
        )
    return records


RESUME_KEYS = {"optimizers", "generator", "records", "samples"}


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

    Refused: a checkpoint of other settings (model, training, seed) or data (sample counts), or
    of more epochs than ``epochs``.
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
    # Epochs recorded before train.precision existed trained in float32.
    trained_in = records[-1].get("precision", "fp32") if records else trainer.precision
    if trained_in != trainer.precision:  # "auto" decided on another machine, or another precision asked for
        raise CrchflError(
            f"{used}: its epochs trained in {trained_in}; this training would continue in {trainer.precision} "
            f"(train.precision {trainer.config.precision!r} on this machine); resume with --precision {trained_in} "
            "or choose another --out"
        )
    if len(records) > epochs:
        raise CrchflError(f"{used}: holds {len(records)} epochs already; ask for --epochs {len(records)} or more")
    trainer.model.load_state_dict(checkpoint.state_dict)
    try:
        for optimizer, optimizer_state in zip(trainer.optimizers, state["optimizers"]):
            optimizer.load_state_dict(optimizer_state)
        generator.set_state(state["generator"])
    except (KeyError, ValueError, RuntimeError, TypeError) as exc:
        raise CrchflError(f"{used}: its optimizer or generator state does not fit ({exc}); delete the folder") from None
    log.info("resuming %s after epoch %d", path.parent, len(records))
    return records


def _resumable_checkpoint(path: Path) -> Checkpoint:
    """A training checkpoint with its resume state, checked; a CrchflError if missing, damaged or without one."""
    checkpoint = load_checkpoint(path)
    check_weights(checkpoint.model_config, checkpoint.state_dict, str(path))
    state = checkpoint.extra.get("resume")
    if not (
        isinstance(state, dict) and set(state) == RESUME_KEYS
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
