"""Local training and evaluation of driving models: one model (Learner), one vehicle, or many vehicles at once.

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

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import nn
from torch.func import functional_call, grad, vmap
from torch.nn import functional as F
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from crchfl_sumo.core.cpus import pinned_threads
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_EPOCHS, check_range
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.balance import class_weights, epoch_batches
from crchfl_sumo.learning.devices import (
    configure_determinism,
    forward_precision,
    resolve_device,
    resolved_multi_vehicle,
    resolved_precision,
    vmappable,
)
from crchfl_sumo.learning.evaluation import Evaluation, evaluate_model
from crchfl_sumo.learning.model import (
    State,
    longitudinal_target,
    model_from_state,
    network,
    paper_class_of_bin,
    steer_targets,
)
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig


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
def evaluate(model: nn.Module, samples: Samples, config: TrainConfig = TrainConfig()) -> Evaluation:
    """``model``'s test metrics on ``samples`` (evaluation.py), in batches of ``config.eval_batch_size``."""
    return evaluate_model(model, samples, config.eval_batch_size)


class Learner:
    """One model with one Adam per branch; trains epoch by epoch on Samples.

    (The federation's Trainer, TorchTrainer and RayTrainer train many
    vehicles' models; a Learner is one model.) The model is owned by the
    learner and updated in place; ``state()`` gives
    a CPU copy of the weights it keeps (``kept_model``: the model, or its
    moving average with ``train.ema_decay``).
    """

    def __init__(self, model: nn.Module, config: TrainConfig, proximal_mu: float = 0.0) -> None:
        self.model = model
        self.config = config
        # FedProx (learning/strategies.py): mu/2 ||w - w_start||^2 joins the loss, w_start the weights now
        self.proximal_mu = proximal_mu
        self._start = [p.detach().clone() for p in model.parameters()] if proximal_mu else None
        self.precision = resolved_precision(config, self.device)
        adam = dict(
            lr=config.learning_rate,
            betas=(config.beta1, config.beta2),
            eps=config.adam_eps,
            weight_decay=config.weight_decay,
        )
        # One Adam per branch (the paper's two networks); a network of the user's (model.class) has one.
        # Adam works element by element, so either way every weight takes the same steps.
        parts = [getattr(model, name, None) for name in ("branch_throttle_brake", "branch_steer")]
        parts = parts if all(isinstance(part, nn.Module) for part in parts) else [model]
        self.optimizers = tuple(torch.optim.Adam(part.parameters(), **adam) for part in parts)
        # train.ema_decay: a moving average of the weights, updated after every step, is what the training keeps
        self.average = (AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(config.ema_decay), use_buffers=True)
                        if config.ema_decay else None)

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    @property
    def kept_model(self) -> nn.Module:
        """The network a training keeps, evaluates and hands on: the average of the weights where
        ``train.ema_decay`` asks for one, else the trained model itself."""
        return self.model if self.average is None else self.average.module

    def state(self) -> State:
        """A CPU copy of the kept model's weights."""
        return {name: t.detach().cpu().clone() for name, t in self.kept_model.state_dict().items()}

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
        for indices in epoch_batches(samples, self.config.batch_size, self.config.sampling, generator,
                                     **emphasis(self.config)):
            indices = indices.to(self.device)
            images, steer_class = samples.images[indices], classes[indices]
            target = longitudinal_target(model_config, samples, indices)
            for optimizer in self.optimizers:
                optimizer.zero_grad(set_to_none=True)
            with forward_precision(self.precision, self.device):
                longitudinal, steer_logits = self.model(images, samples.command[indices], samples.speed_mps[indices])
            longitudinal, steer_logits = longitudinal.float(), steer_logits.float()
            loss_tb, loss_steer = branch_losses(longitudinal, steer_logits, target, steer_class, weight)
            # The branches share no weights, so one backward of the sum gives each branch its own gradient.
            loss = loss_tb + loss_steer
            if self._start is not None:
                loss = loss + 0.5 * self.proximal_mu * sum(
                    ((p - p0) ** 2).sum() for p, p0 in zip(self.model.parameters(), self._start, strict=True))
            loss.backward()
            for optimizer in self.optimizers:
                optimizer.step()
            if self.average is not None:
                self.average.update_parameters(self.model)
            n = len(indices)
            with torch.no_grad():
                # accuracy on the paper's classes, whatever the head's bins
                correct = (paper_class[steer_logits.argmax(dim=1)] == samples.steer_class[indices]).sum().double()
                sums += torch.stack([loss_tb.detach().double() * n, loss_steer.detach().double() * n, correct])
            done += n
            report(progress, "train", done, len(samples))
        loss_tb_sum, loss_steer_sum, correct = sums.tolist()
        return Metrics.from_sums(loss_tb_sum, loss_steer_sum, correct, len(samples))


def emphasis(config: TrainConfig) -> dict[str, float]:
    """epoch_batches' emphasis of red lights and yields, from ``config``."""
    return {"red_weight": config.red_weight, "red_window_m": config.red_window_m,
            "yield_weight": config.yield_weight, "yield_window_m": config.yield_window_m}


def train_vehicle(
    state: State,
    samples: Samples,
    epochs: int,
    model_config: ModelConfig,
    config: TrainConfig,
    seed: int,
    proximal_mu: float = 0.0,
) -> tuple[State, list[Metrics]]:
    """Train one model for ``epochs`` on ``samples``: (new state on CPU, training metrics per epoch);
    ``proximal_mu`` > 0 adds FedProx's proximal term to the loss.

    ``seed`` is any integer torch's generator takes: callers derive one per vehicle and step.
    """
    check_range(epochs, "train_vehicle: epochs", 0, MAX_EPOCHS, "a number of epochs")
    configure_determinism(config.deterministic)
    device = resolve_device(config.device)
    trainer = Learner(model_from_state(model_config, state, device), config, proximal_mu)
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
        template = network(model_config)
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
            [(e, idx) for e in range(epochs)
             for idx in epoch_batches(samples, batch_size, config.sampling, generator, **emphasis(config))]
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
            target = longitudinal_target(model_config, samples, indices)
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
