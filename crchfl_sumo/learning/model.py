"""The two-branch driving network of the CRCHFL paper, in one file with its config.

Branch I sees the head camera (CamH) and regresses (throttle, brake), or, with
``ModelConfig.longitudinal = "target_speed"``, the speed to drive at
(data/expert.py: the expert's speed 1 s ahead), which a controller turns into pedals.
Branch II sees the front, left and right cameras stacked into 9 channels and
classifies the steer into the 7 classes of ``labels.STEER_CLASS_VALUES`` (or,
``ModelConfig.steer_bins``, into finer evenly spaced steer values).
Both branches share one topology (a PilotNet-like conv stack, adaptive average
pooling to a fixed grid, a small MLP); the two sizes differ only in widths:

- ``compact`` (default): about 0.5 M parameters, fast enough to train on a CPU.
- ``paper``: about 39.4 M parameters (about 150 MiB of fp32), the size of the
  paper's reference implementation, for runs whose byte counts follow the paper.

Two architectures share that topology (``ModelConfig.arch``):

- ``cil`` (default): a normalisation layer after every convolution
  (GroupNorm by default), He initialisation, no narrow last hidden layer, and
  conditioning in the manner of Conditional Imitation Learning (Codevilla et
  al. 2018): the steer branch has one output head per route command and the
  command picks the head (or, ``command_input = "concat"``, the command is a
  one-hot input); the current speed can be an input of both branches
  (``speed_input``, off by default).
- ``paper``: the paper's network exactly as before (no normalisation, MLP
  widths down to 10 units, PyTorch's default initialisation, no command, no
  speed); checkpoints written before ``arch`` existed load as this one.

Every model is called as ``model(images, command, speed_mps)``; the paper
architecture accepts and ignores the last two.

Because of the adaptive pooling the parameter count does not depend on the
image size, and any image of at least 48 x 64 pixels is accepted.
Images enter as uint8 [B, 4, H, W, 3] (camera order ``labels.CAMERA_NAMES``)
and are normalised inside the network, so uint8 can stay uint8 in memory.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import torch
from torch import nn

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.imports import import_class
from crchfl_sumo.core.numbers import check_seed
from crchfl_sumo.data.expert import (
    PASSENGER_MAX_ACCEL_MPS2,
    PASSENGER_MAX_DECEL_MPS2,
    STAND_TARGET_MPS,
    ExpertConfig,
    pedals_towards,
)
from crchfl_sumo.data.labels import (
    FOLLOW, JUNCTION_COMMANDS, NUM_COMMANDS, NUM_STEER_CLASSES, SIGNAL_RED, SIGNAL_UNKNOWN, SIGNAL_YELLOW,
    digitize_steer,
    steer_bin_values,
)
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.settings import (
    DEFAULT_STEER_DECODING,
    SPEED_SCALE_MPS,
    BranchShape,
    ModelConfig,
    resolved_steer_decoding,
    with_data_commands,
    with_data_signals,
)

State = dict[str, torch.Tensor]  # a model's weights by parameter name, as state_dict() gives them


class GridAveragePool(nn.Module):
    """Average pooling to a fixed grid, the same windows as nn.AdaptiveAvgPool2d.

    Written as two small matrix products because adaptive_avg_pool2d's CUDA
    backward has no deterministic implementation, which would make
    deterministic training fail on a GPU.
    """

    def __init__(self, grid_hw: tuple[int, int]) -> None:
        super().__init__()
        self.grid_hw = grid_hw

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        height, width = x.shape[-2:]
        rows = _pool_matrix(height, self.grid_hw[0], x)
        cols = _pool_matrix(width, self.grid_hw[1], x)
        return rows @ x @ cols.T


def _pool_matrix(size: int, cells: int, like: torch.Tensor) -> torch.Tensor:
    """[cells, size] averaging weights: cell i covers floor(i*size/cells) .. ceil((i+1)*size/cells)."""
    index = torch.arange(cells, device=like.device)
    start = (index * size) // cells
    end = ((index + 1) * size + cells - 1) // cells
    position = torch.arange(size, device=like.device)
    inside = (position >= start[:, None]) & (position < end[:, None])
    return inside.to(like.dtype) / (end - start)[:, None].to(like.dtype)


class Branch(nn.Module):
    """The paper architecture's branch: conv stack -> adaptive average pool -> MLP -> ``num_outputs`` values."""

    def __init__(self, in_channels: int, num_outputs: int, shape: BranchShape) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        channels = in_channels
        for out_channels, kernel, stride in shape.convs:
            # 3x3/1 convs are padded so that small images keep a spatial extent.
            padding = kernel // 2 if stride == 1 else 0
            layers += [nn.Conv2d(channels, out_channels, kernel, stride, padding), nn.ReLU()]
            channels = out_channels
        layers += [GridAveragePool(shape.pool_hw), nn.Flatten()]
        width = channels * shape.pool_hw[0] * shape.pool_hw[1]
        for hidden in shape.hidden:
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        layers.append(nn.Linear(width, num_outputs))
        self.layers = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor, command: torch.Tensor, speed_mps: torch.Tensor) -> torch.Tensor:
        return self.layers(x)  # the paper's network sees neither command nor speed


class GroupNorm(nn.GroupNorm):
    """nn.GroupNorm (the same parameters and state) that stays fast on bfloat16 input.

    Under bfloat16 autocast the convolutions hand it bfloat16 in channels_last
    layout, for which PyTorch's CPU kernel with float32 affine weights is slow
    (its backward took a fifth of a bfloat16 training step); the same input made
    contiguous, with the affine weights cast as autocast casts a convolution's,
    is faster even with the copy back to channels_last (docs/model.md, "Training
    in bfloat16"). Float32 input takes nn.GroupNorm's own path, bit for bit, and so
    does input on a GPU (CUDA's autocast runs group_norm in float32 itself).
    Input is [B, C, H, W].
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dtype == self.weight.dtype or x.device.type != "cpu":  # CUDA's autocast runs group_norm in fp32
            return super().forward(x)
        weight, bias = self.weight.to(x.dtype), self.bias.to(x.dtype)
        y = nn.functional.group_norm(x.contiguous(), self.num_groups, weight, bias, self.eps)
        # Back to channels_last, which the next convolution wants, written with permutes (vmap, which
        # trains many vehicles at once, cannot clone to a memory format).
        return y.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)


def norm_layer(kind: str, channels: int) -> nn.Module:
    """The normalisation after a convolution of ``channels`` outputs."""
    if kind == "group":
        return GroupNorm(math.gcd(channels, 8), channels)
    if kind == "layer":
        return GroupNorm(1, channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    return nn.Identity()


class ConditionedBranch(nn.Module):
    """The cil architecture's branch: normalised conv stack -> pool -> MLP -> one or several heads.

    The MLP is the size's first hidden layer; each head is the second hidden
    layer and the output (the size's last, narrowest hidden layer is dropped).
    The speed (scaled) and, for "concat", the command one-hot join the
    features after the first hidden layer; with several heads, sample b's
    output is that of head ``command[b]``.
    """

    def __init__(
        self, in_channels: int, num_outputs: int, shape: BranchShape, norm: str, num_heads: int, command_one_hot: bool,
        speed_input: bool, num_commands: int = JUNCTION_COMMANDS,
    ) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        channels = in_channels
        for out_channels, kernel, stride in shape.convs:
            padding = kernel // 2 if stride == 1 else 0
            bias = norm == "none"  # a normalisation's own shift makes the conv bias redundant
            layers += [nn.Conv2d(channels, out_channels, kernel, stride, padding, bias=bias), norm_layer(norm, out_channels)]
            layers.append(nn.ReLU())
            channels = out_channels
        layers += [GridAveragePool(shape.pool_hw), nn.Flatten()]
        layers += [nn.Linear(channels * shape.pool_hw[0] * shape.pool_hw[1], shape.hidden[0]), nn.ReLU()]
        self.features = nn.Sequential(*layers)
        self.command_one_hot, self.speed_input, self.num_commands = command_one_hot, speed_input, num_commands
        width = shape.hidden[0] + (num_commands if command_one_hot else 0) + (1 if speed_input else 0)
        self.heads = nn.ModuleList(
            nn.Sequential(nn.Linear(width, shape.hidden[1]), nn.ReLU(), nn.Linear(shape.hidden[1], num_outputs))
            for _ in range(num_heads)
        )

    def forward(self, x: torch.Tensor, command: torch.Tensor, speed_mps: torch.Tensor) -> torch.Tensor:
        parts = [self.features(x)]
        if self.command_one_hot:  # a comparison, not F.one_hot: it works under vmap
            codes = torch.arange(self.num_commands, device=command.device)
            parts.append((command[:, None] == codes).to(parts[0].dtype))
        if self.speed_input:
            parts.append((speed_mps.to(parts[0].dtype) / SPEED_SCALE_MPS)[:, None])
        h = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        if len(self.heads) == 1:
            return self.heads[0](h)
        outputs = torch.stack([head(h) for head in self.heads], dim=1)  # [B, heads, outputs]
        picked = command.long()[:, None, None].expand(-1, 1, outputs.shape[-1])
        return outputs.gather(1, picked).squeeze(1)


def _initialise(module: nn.Module) -> None:
    """He (fan-in, ReLU) weights and zero biases; every head's output layer starts small (std 0.01).

    Small output weights start the steer logits near uniform and the pedals
    near 0.5, so no class is favoured before training.
    """
    for layer in module.modules():
        if isinstance(layer, (nn.Conv2d, nn.Linear)):
            nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
            if layer.bias is not None:
                nn.init.zeros_(layer.bias)
    for branch in module.children():
        for head in getattr(branch, "heads", ()):
            nn.init.normal_(head[-1].weight, std=0.01)


class DrivingModel(nn.Module):
    """(uint8 images [B, 4, H, W, 3], command int64 [B], speed_mps float [B]) ->
    (branch I [B, 2] or [B, 1], steer_logits [B, steer_bins]).

    Branch I gives throttle and brake in [0, 1], or (longitudinal "target_speed")
    the target speed / SPEED_SCALE_MPS, unbounded (longitudinal_target says what
    it learns). Commands are 0..5 (labels.COMMAND_NAMES); a network of
    ``config.num_commands`` = 4 reads 4 and 5 (the lane changes) as follow. The paper
    architecture ignores command and speed.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        shape = config.shape
        if config.arch == "paper":
            self.branch_throttle_brake = Branch(3, 2, shape)  # branch I: CamH
            self.branch_steer = Branch(9, NUM_STEER_CLASSES, shape)  # branch II: CamF|CamL|CamR
            return
        commands = config.num_commands
        heads = commands if config.command_input == "branched" else 1
        one_hot = config.command_input == "concat"
        pedal_heads, pedal_one_hot = (heads, one_hot) if config.command_pedals else (1, False)
        self.branch_throttle_brake = ConditionedBranch(
            3, longitudinal_width(config), shape, config.norm, pedal_heads, pedal_one_hot, config.speed_input, commands
        )
        self.branch_steer = ConditionedBranch(
            9, config.steer_bins, shape, config.norm, heads, one_hot, config.speed_input and config.steer_speed_input,
            commands,
        )
        _initialise(self)

    def forward(
        self, images: torch.Tensor, command: torch.Tensor, speed_mps: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        # Under autocast the images go straight to its dtype (bfloat16 holds 0..255 exactly), so the
        # first convolution is not handed float32 to cast again.
        device = images.device.type
        dtype = torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else torch.float32
        # The side cameras are stacked pixel by pixel while still uint8 (a quarter of the bytes to copy;
        # cat copies rows where a permuted reshape copied 3-byte pixels, measured 2.5x faster); the
        # normalisation is elementwise, so doing it after the stacking does not change a bit.
        sides = torch.cat(images[:, 1:4].unbind(1), dim=-1)  # [B, H, W, 9]: CamF RGB, CamL RGB, CamR RGB
        # [B, H, W, C] -> [B, C, H, W] is a view in channels_last layout: no copy.
        head = _normalised(images[:, 0], dtype).permute(0, 3, 1, 2)
        sides = _normalised(sides, dtype).permute(0, 3, 1, 2)
        # a command the network has no head for (a lane change, to a 4-command network) is follow
        command = torch.where(command < self.config.num_commands, command, FOLLOW)
        longitudinal = self.branch_throttle_brake(head, command, speed_mps)
        if self.config.longitudinal == "pedals":
            longitudinal = torch.sigmoid(longitudinal)
        steer_logits = self.branch_steer(sides, command, speed_mps)
        return longitudinal, steer_logits


def mode_steer(probabilities: np.ndarray, values: np.ndarray) -> np.ndarray:
    """[B] steer: the most likely class and its neighbours in value (at most one either side), their values
    weighted by their probabilities (STEER_DECODINGS "mode")."""
    order = np.argsort(values)  # neighbours in value: the paper's 7 classes are not listed in order
    ranked = probabilities[:, order]
    top = ranked.argmax(axis=1)
    window = np.zeros_like(ranked, dtype=bool)
    for shift in (-1, 0, 1):
        window[np.arange(len(top)), np.clip(top + shift, 0, ranked.shape[1] - 1)] = True
    kept = np.where(window, ranked, 0.0)
    return (kept @ values[order]) / kept.sum(axis=1)


def _normalised(images: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """uint8 pixels -> [-1, 1] in ``dtype``."""
    return images.to(dtype) * (1.0 / 127.5) - 1.0


def steer_values(config: ModelConfig) -> np.ndarray:
    """float32 [steer_bins]: the steer value of each of the steer head's classes (labels.steer_bin_values)."""
    return steer_bin_values(config.steer_bins)


def paper_class_of_bin(config: ModelConfig) -> np.ndarray:
    """int64 [steer_bins]: the paper's steer class (labels.digitize_steer) of each steer head class's value;
    the identity for the paper's 7. The test metrics read a prediction through it."""
    return digitize_steer(steer_values(config))


def steer_targets(config: ModelConfig, steer_class: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
    """int64 [B]: the steer head's class each sample teaches: its paper class for 7 bins, else the bin nearest
    its analogue steer label (ties: the lower bin)."""
    if config.steer_bins == NUM_STEER_CLASSES:
        return steer_class
    values = torch.as_tensor(steer_values(config), device=steer.device)
    return (steer.to(values.dtype)[:, None] - values).abs().argmin(dim=1)


# The stop head (ModelConfig.stop_head): branch I's second output is the distance to the stop line of the
# route's next red or yellow signal, up to STOP_RANGE_M (the range, also with no such signal), scaled by
# 1/STOP_RANGE_M. The controller caps the target speed at the speed from which STOP_DECEL_MPS2 stops the car
# STOP_MARGIN_M before that line, unless the car could not stop there even at its full deceleration (then
# it is committed, as SUMO's drivers are at a yellow light). A car slower than STAND_TARGET_MPS starts only
# when the head sees no red line within STOP_START_M: standing at a red line, the models guessed the green a
# second early from the crossing road's lights turning red, and rolled over the line (docs/measurements.md).
STOP_RANGE_M = 40.0  # the farthest the 64 x 128 head camera shows a lamp (docs/measurements.md)
STOP_MARGIN_M = 2.0
STOP_DECEL_MPS2 = 2.5
STOP_START_M = 10.0


def longitudinal_width(config: ModelConfig) -> int:
    """Branch I's outputs: throttle and brake, or one target speed (and the stop distance, with a stop head)."""
    return 2 if config.longitudinal == "pedals" or config.stop_head else 1


def longitudinal_target(
    config: ModelConfig, samples: Samples, indices: torch.Tensor | slice | None = None,
) -> torch.Tensor:
    """What branch I learns from ``samples`` (the rows ``indices``, else all), [B, longitudinal_width]: (throttle,
    brake), or the scaled target speed (held by ``red_held_speed_mps`` with ModelConfig.red_hold; with a stop
    head also the scaled stop distance). Only these read the samples' signal columns."""
    def column(name: str) -> torch.Tensor:
        values = getattr(samples, name)
        return values if indices is None else values[indices]

    if config.longitudinal == "pedals":
        return column("actions")[:, [0, 2]]
    speed = column("target_speed_mps")
    if not (config.red_hold or config.stop_head):
        return (speed / SPEED_SCALE_MPS)[:, None]
    state, distance = column("signal_state"), column("signal_distance_m")
    if config.red_hold:
        speed = red_held_speed_mps(speed, state, distance)
    speed = (speed / SPEED_SCALE_MPS)[:, None]
    if not config.stop_head:
        return speed
    return torch.cat([speed, (stop_distance_m(state, distance) / STOP_RANGE_M)[:, None]], dim=1)


def holds_signal_states(signal_state: torch.Tensor) -> bool:
    """Whether samples' signal states say anything (a data set of format 5 on), not all unknown."""
    return bool((signal_state != SIGNAL_UNKNOWN).any())


def with_training_data(config: ModelConfig, samples: Iterable[Samples]) -> ModelConfig:
    """``config`` with its unset DATA_DECIDED_KEYS decided by the training ``samples`` (one set, or each
    vehicle's): the lane-change heads (``with_data_commands``) and the stop head (``with_data_signals``)."""
    samples = [s for s in samples if len(s)]
    largest_command = max((int(s.command.max()) for s in samples), default=0)
    signals_known = any(holds_signal_states(s.signal_state) for s in samples)
    return with_data_signals(with_data_commands(config, largest_command), signals_known)


def check_signal_labels(config: ModelConfig, signal_state: torch.Tensor, where: str) -> None:
    """Refuse a stop head or a red hold on samples whose signal states are all unknown (a data set written
    before format 5, ``where``): their targets would carry no signal at all."""
    for key in ("stop_head", "red_hold"):
        if getattr(config, key) and len(signal_state) and not holds_signal_states(signal_state):
            flag = "--" + key.replace("_", "-")
            raise CrchflError(
                f"{where}: its samples hold no signal states (written before data set format 5), which model.{key} "
                f"(train {flag}) learns from; generate the data set again with `crchfl-sumo dataset`, or drop {flag}"
            )


def stop_line_speed_mps(stop_m):
    """The speed from which STOP_DECEL_MPS2 stops the car STOP_MARGIN_M before a stop line ``stop_m`` ahead
    (a numpy array or a tensor; 0 within the margin)."""
    return (2.0 * STOP_DECEL_MPS2 * (stop_m - STOP_MARGIN_M).clip(min=0.0)) ** 0.5


def red_held_speed_mps(
    target_speed_mps: torch.Tensor, signal_state: torch.Tensor, signal_distance_m: torch.Tensor,
) -> torch.Tensor:
    """float32 [B]: the target-speed labels of ModelConfig.red_hold: at most stop_line_speed_mps of the stop line
    while the route's next signal shows red (so 0 for a car standing at its line), else as recorded.

    The recorded label is the expert's speed a horizon ahead, so it rises up to a horizon before the green:
    the models learnt to guess the green from the crossing road's lights and rolled over a red line
    (docs/measurements.md, 2026-12-05, seventh)."""
    held = torch.minimum(target_speed_mps, stop_line_speed_mps(signal_distance_m.float()))
    return torch.where(signal_state == SIGNAL_RED, held, target_speed_mps)


def stop_distance_m(signal_state: torch.Tensor, signal_distance_m: torch.Tensor) -> torch.Tensor:
    """float32 [B]: the distance to the stop line of a red or yellow next signal, at most STOP_RANGE_M (also where
    the next signal shows another state, is unknown, or there is none)."""
    stopping = (signal_state == SIGNAL_RED) | (signal_state == SIGNAL_YELLOW)
    distance = torch.where(stopping, signal_distance_m.float(), torch.full_like(signal_distance_m.float(), STOP_RANGE_M))
    return distance.clamp(0.0, STOP_RANGE_M)


def stop_capped_speed(
    target_mps: np.ndarray, stop_m: np.ndarray, speed_mps: np.ndarray, max_decel_mps2: np.ndarray | float,
) -> np.ndarray:
    """The target speed capped so that STOP_DECEL_MPS2 stops the car STOP_MARGIN_M before a stop line ``stop_m``
    ahead; uncapped where the car could not stop before the line even at ``max_decel_mps2`` (committed); 0 for
    a car slower than STAND_TARGET_MPS with a stop line nearer than STOP_START_M."""
    stop_m = np.asarray(stop_m, dtype=np.float64)
    speed = np.asarray(speed_mps, dtype=np.float64)
    allowed = stop_line_speed_mps(stop_m)
    allowed = np.where((speed < STAND_TARGET_MPS) & (stop_m < STOP_START_M), 0.0, allowed)
    committed = speed**2 > 2.0 * np.asarray(max_decel_mps2, dtype=np.float64) * np.maximum(stop_m, 0.0)
    return np.where(committed, target_mps, np.minimum(target_mps, allowed))


def longitudinal_pedals(
    config: ModelConfig,
    longitudinal: np.ndarray,
    speed_mps: np.ndarray,
    max_accel_mps2: np.ndarray | float = PASSENGER_MAX_ACCEL_MPS2,
    max_decel_mps2: np.ndarray | float = PASSENGER_MAX_DECEL_MPS2,
    brake_gain: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Branch I's output [B, width] -> (throttle [B], brake [B]); a target speed through expert.pedals_towards
    (with a stop head, capped by stop_capped_speed at the predicted stop distance).

    The vehicle's acceleration limits scale a target speed's pedals (SUMO's
    passenger car unless given); predicted pedals pass through. ``brake_gain``
    (pedals_towards) is 1 for evaluation against the labels; a drive brakes harder.
    """
    longitudinal = np.asarray(longitudinal, dtype=np.float64)
    if config.longitudinal == "pedals":
        return longitudinal[:, 0], longitudinal[:, 1]
    target = np.maximum(longitudinal[:, 0] * SPEED_SCALE_MPS, 0.0)
    if config.stop_head:
        target = stop_capped_speed(target, longitudinal[:, 1] * STOP_RANGE_M, speed_mps, max_decel_mps2)
    horizon = ExpertConfig(speed_horizon_s=config.speed_horizon_s)
    return pedals_towards(speed_mps, target, max_accel_mps2, max_decel_mps2, horizon, brake_gain)


def count_parameters(model: nn.Module) -> int:
    """Number of scalar parameters."""
    return sum(p.numel() for p in model.parameters())


def state_size_bytes(state: dict[str, torch.Tensor]) -> int:
    """Bytes of the raw tensor data in a state dict (what one model transfer carries)."""
    return sum(t.numel() * t.element_size() for t in state.values())


def network(config: ModelConfig) -> nn.Module:
    """The network of ``config``: the built-in DrivingModel, or the class ``model.class`` names.

    Your class is built as ``Class(config)`` and must answer like DrivingModel: (images, command,
    speed_mps) -> (branch I [B, longitudinal_width(config)], steer logits [B, config.steer_bins]).
    The network's ``config`` is the ModelConfig it was built from (the rest of the package reads it).
    """
    if not config.class_path:
        return DrivingModel(config)
    net = network_class(config.class_path)(config)
    net.config = config
    return net


def network_class(class_path: str) -> type[nn.Module]:
    """The class of ``"package.module:Class"``, imported (its module's code runs, as when it trained; nothing
    of it comes from a checkpoint); a CrchflError naming ``model.class`` and the fix otherwise."""
    cls = import_class(class_path, "model.class")
    if not issubclass(cls, nn.Module):
        raise CrchflError(f"model.class: {class_path!r} is not a torch.nn.Module class; name one")
    return cls


def build_model(config: ModelConfig, seed: int) -> nn.Module:
    """A freshly initialised model; the same seed gives the same weights."""
    check_seed(seed, "build_model: seed")
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        return network(config)
    finally:
        torch.random.set_rng_state(generator_state)


def model_from_state(
    config: ModelConfig, state: dict[str, torch.Tensor], device: torch.device | str = "cpu"
) -> nn.Module:
    """A model holding a copy of ``state`` on ``device``; the caller's tensors and RNG are untouched."""
    with torch.device("meta"):  # no random init: every weight comes from ``state``
        model = network(config)
    # Weights in float32 (states averaged by FedAvg may arrive in another float type); counters such
    # as BatchNorm's num_batches_tracked keep their integer type, which checkpoints are checked against.
    weights = {
        name: t.detach().to(device=device, dtype=torch.float32 if t.is_floating_point() else t.dtype, copy=True)
        for name, t in state.items()
    }
    model.load_state_dict(weights, assign=True)
    return model


@torch.no_grad()
def predict_actions(
    model: DrivingModel,
    images: torch.Tensor,
    command: torch.Tensor | np.ndarray | int,
    speed_mps: torch.Tensor | np.ndarray | float,
    steer_decoding: str = DEFAULT_STEER_DECODING,
    max_accel_mps2: float = PASSENGER_MAX_ACCEL_MPS2,
    max_decel_mps2: float = PASSENGER_MAX_DECEL_MPS2,
    brake_gain: float = 1.0,
) -> np.ndarray:
    """uint8 images [B, 4, H, W, 3] with command [B] and speed_mps [B] -> float32 [B, 3];
    one sample ([4, H, W, 3], an int command, a float speed) -> float32 [3].

    Columns are (throttle, steer, brake); a target-speed model's pedals are
    longitudinal_pedals' for a vehicle of the given acceleration limits (and
    ``brake_gain``). ``steer_decoding`` (STEER_DECODINGS):
    "argmax" is the paper's DAC, the value of the most likely class; "expected"
    is the classes' values weighted by their softmax probabilities, a steer
    between the classes (0.125 steps are a 33 m radius each: argmax can only
    steer in those steps); "mode" weights only the most likely class and its
    neighbours (``mode_steer``); "auto" is argmax for the paper's 7 classes and
    mode for a finer head (settings.resolved_steer_decoding).
    """
    steer_decoding = resolved_steer_decoding(steer_decoding, model.config.steer_bins)
    single = images.dim() == 4
    batch = images.unsqueeze(0) if single else images
    device = next(model.parameters()).device
    command = torch.as_tensor(command, dtype=torch.int64).reshape(-1).to(device)
    speed_mps = torch.as_tensor(speed_mps, dtype=torch.float32).reshape(-1).to(device)
    if len(command) != len(batch) or len(speed_mps) != len(batch):
        raise ValueError(f"predict_actions: {len(batch)} images, {len(command)} commands, {len(speed_mps)} speeds")
    if len(command) and (int(command.min()) < 0 or int(command.max()) >= NUM_COMMANDS):
        raise ValueError(f"predict_actions: commands must lie in 0..{NUM_COMMANDS - 1}")
    was_training = model.training
    model.eval()
    try:
        longitudinal, steer_logits = model(batch.to(device), command, speed_mps)
    finally:
        model.train(was_training)
    throttle, brake = longitudinal_pedals(
        model.config, longitudinal.cpu().numpy(), speed_mps.cpu().numpy(), max_accel_mps2, max_decel_mps2, brake_gain
    )
    values = steer_values(model.config)
    if steer_decoding == "expected":
        probabilities = torch.softmax(steer_logits.float(), dim=1).cpu().numpy()
        steer = probabilities @ values
    elif steer_decoding == "mode":
        steer = mode_steer(torch.softmax(steer_logits.float(), dim=1).cpu().numpy(), values)
    else:
        steer = values[steer_logits.argmax(dim=1).cpu().numpy()]
    actions = np.stack([throttle, steer, brake], axis=1).astype(np.float32)
    return actions[0] if single else actions
