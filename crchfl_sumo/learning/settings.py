"""The settings of the network and of its training, apart from the network itself so that a config (RunConfig, ReproduceConfig) reads without torch.

ModelConfig is model.py's config (nanoGPT keeps it beside the network; here it sits one file away for that
reason); TrainConfig is training.py's and centralized.py's.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Literal

from crchfl_sumo.core.config import KEY, OMIT_DEFAULT
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.data.expert import DEFAULT_SPEED_HORIZON_S, MAX_SPEED_HORIZON_S
from crchfl_sumo.data.labels import JUNCTION_COMMANDS, NUM_COMMANDS, NUM_STEER_CLASSES
from crchfl_sumo.sumo.frame import FOE_RANGE_M
from crchfl_sumo.vision.camera import MAX_HEIGHT_PX, MAX_WIDTH_PX

MIN_IMAGE_HEIGHT = 48


MIN_IMAGE_WIDTH = 64


SPEED_SCALE_MPS = 10.0  # speed enters the network as speed_mps / 10: about [0, 1.5] in the towns


ARCHS = ("cil", "paper")
# `train --speed-input`: the ModelConfig fields each choice sets (the ego's speed into branch I, and into the
# steer branch too); "none" leaves the defaults, the paper's network without the speed
SPEED_INPUTS = {
    "none": {},
    "longitudinal": {"speed_input": True, "steer_speed_input": False},
    "both": {"speed_input": True, "steer_speed_input": True},
}


NORMS = ("group", "batch", "layer", "none")


COMMAND_INPUTS = ("branched", "concat", "none")


LONGITUDINALS = ("pedals", "target_speed")  # what branch I predicts (ModelConfig.longitudinal)


@dataclass(frozen=True)
class BranchShape:
    """Widths of one branch: conv layers as (out_channels, kernel, stride), pool grid, MLP widths."""

    convs: tuple[tuple[int, int, int], ...]
    pool_hw: tuple[int, int]
    hidden: tuple[int, ...]


# The two sizes; the stride pattern of PilotNet (three 5x5/2 convs, two 3x3/1 convs) in both.
SIZES: dict[str, BranchShape] = {
    "compact": BranchShape(
        convs=((24, 5, 2), (36, 5, 2), (48, 5, 2), (64, 3, 1), (64, 3, 1)),
        pool_hw=(2, 8),
        hidden=(100, 50, 10),
    ),
    "paper": BranchShape(
        convs=((64, 5, 2), (128, 5, 2), (256, 5, 2), (384, 3, 1), (384, 3, 1)),
        pool_hw=(2, 8),
        hidden=(2256, 1024, 256),
    ),
}


COMMAND_COUNTS = (JUNCTION_COMMANDS, NUM_COMMANDS)  # ModelConfig.commands: without or with the lane changes


@dataclass(frozen=True)
class ModelConfig:
    """Settings of the driving network.

    size: "compact" (default, ~0.5 M parameters) or "paper" (~39.4 M, ~150 MiB).
    image_height, image_width: camera image size in pixels (default 64 x 128,
        the default of camera.CameraConfig); at least 48 x 64, at most 1080 x 1920.
    arch: "cil" (default; normalised, conditioned on command and speed) or
        "paper" (the paper's network exactly; no command, no speed).
    The next three apply to arch "cil" only (arch "paper" needs their defaults):
    norm: after every convolution: "group" (default; GroupNorm, up to 8
        groups), "batch" (BatchNorm; running statistics average poorly under
        FedAvg and it cannot train with multi_vehicle = "vmap"), "layer"
        (GroupNorm with one group) or "none".
    command_input: "branched" (default; one steer head per command, picked by
        the command), "concat" (the command one-hot into the steer MLP) or "none".
    command_pedals: the command conditions the throttle/brake branch too, in the
        same way (command_input) as the steer branch: whether to slow before a
        junction depends on the turn to come, which CamH cannot show.
    speed_input: the current speed (speed_mps / 10) is an input of branch I's
        MLP and, with steer_speed_input (default true), of the steer branch's
        (default off: docs/model.md's measurements).
    steer_speed_input: with speed_input, the steer branch sees the speed too;
        false keeps it to branch I (the steer branch then trains as without).
    longitudinal: what branch I predicts: "target_speed" (the default of arch
        "cil": the expert's speed ExpertConfig.speed_horizon_s ahead, scaled by
        1/10; expert.pedals_towards turns it into pedals) or "pedals" (throttle
        and brake, the paper's; the only choice of arch "paper"). Unset, it is
        the architecture's default (docs/model.md measures both).
    speed_horizon_s: how far ahead the target speed looks (the data set's
        expert.speed_horizon_s, 1 s by default); the controller reaches a
        target over the same time. Training refuses data of another horizon.
    steer_bins: the steer head's classes: 7 is the paper's digitizer and DAC
        (labels.STEER_CLASS_VALUES); an odd count up to MAX_STEER_BINS spaces
        that many steer values evenly over [-1, 1] (labels.steer_bin_values),
        learnt from the analogue steer label. The test metrics stay on the
        paper's 7 classes (the predicted value digitized). Unset, it is the
        architecture's default: 21 for "cil" (the paper's sharpest class, 17
        degrees, cannot take the towns' turns: docs/model.md), 7 for "paper",
        which takes no other.
    commands: the route commands the network tells apart (arch "cil"): 4, the paper's and CIL's
        follow, left, right and straight, or 6, with change_left and change_right for multi-lane
        roads (labels.COMMAND_NAMES). Unset: 6 where the training data hold a lane-change command,
        else 4 (``with_data_commands``). A 4-command network reads a lane-change command as follow.
    stop_head: branch I also learns how far ahead the route's next signal shows red or yellow
        (``stop_distance_m`` of the data set's signal_state and signal_distance_m, up to STOP_RANGE_M),
        and the controller caps the target speed so that the car can stop before that line
        (model.longitudinal_pedals). Target-speed models only. Unset, a new built-in network gets
        one where its training data hold signal states (``with_data_signals``); a checkpoint
        written without the key has none (docs/model.md, "A stop head").
    red_hold: while the route's next signal shows red, the target-speed label never exceeds the
        speed from which the stop head's deceleration stops the car before the line
        (model.red_held_speed_mps): 0 standing at the line, where the recorded label (the speed a
        horizon ahead) rises a horizon before the green. Target-speed models only; default off.
    class (TOML key; ``class_path`` here): "package.module:Class", your own network in place of the
        built-in one (learning/model.py ``network``; docs/own_model.md); "" (default): the built-in.
    """

    size: Literal["compact", "paper"] = "compact"
    image_height: int = 64
    image_width: int = 128
    arch: Literal["cil", "paper"] = "cil"
    norm: Literal["group", "batch", "layer", "none"] = "group"
    command_input: Literal["branched", "concat", "none"] = "branched"
    command_pedals: bool = False
    speed_input: bool = False
    steer_speed_input: bool = True
    longitudinal: Literal["pedals", "target_speed"] | None = None
    speed_horizon_s: float = DEFAULT_SPEED_HORIZON_S
    steer_bins: int | None = None
    commands: int | None = field(default=None, metadata={OMIT_DEFAULT: True})
    stop_head: bool | None = field(default=None, metadata={OMIT_DEFAULT: True})
    red_hold: bool = field(default=False, metadata={OMIT_DEFAULT: True})
    class_path: str = field(default="", metadata={KEY: "class", OMIT_DEFAULT: True})

    def __post_init__(self) -> None:
        if self.class_path and not re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*", self.class_path):
            raise CrchflError(
                f"model.class: {self.class_path!r} is no import path; give \"package.module:Class\" (a torch.nn.Module "
                "built from this ModelConfig; docs/own_model.md)"
            )
        if self.longitudinal is None:  # frozen: the architecture's default is filled in once, here
            object.__setattr__(self, "longitudinal", "pedals" if self.arch == "paper" else "target_speed")
        if self.steer_bins is None:
            object.__setattr__(self, "steer_bins", NUM_STEER_CLASSES if self.arch == "paper" else CIL_STEER_BINS)
        if self.size not in SIZES:
            raise CrchflError(f"model.size: {self.size!r} is unknown; use one of {', '.join(map(repr, SIZES))}")
        choices = (("arch", ARCHS), ("norm", NORMS), ("command_input", COMMAND_INPUTS), ("longitudinal", LONGITUDINALS))
        for key, allowed in choices:
            if getattr(self, key) not in allowed:
                raise CrchflError(
                    f"model.{key}: {getattr(self, key)!r} is unknown; use one of {', '.join(map(repr, allowed))}"
                )
        if not (isinstance(self.speed_horizon_s, (int, float)) and 0 < self.speed_horizon_s <= MAX_SPEED_HORIZON_S):
            raise CrchflError(
                f"model.speed_horizon_s must lie in (0, {MAX_SPEED_HORIZON_S:g}] s, got {self.speed_horizon_s!r}"
            )
        for key in ("command_pedals", "speed_input", "steer_speed_input", "stop_head", "red_hold"):
            if not isinstance(getattr(self, key), bool) and not (key == "stop_head" and self.stop_head is None):
                raise CrchflError(f"model.{key}: {getattr(self, key)!r} must be true or false")
        bins = self.steer_bins
        if not (isinstance(bins, int) and not isinstance(bins, bool) and bins % 2 == 1 and 7 <= bins <= MAX_STEER_BINS):
            raise CrchflError(
                f"model.steer_bins: {bins!r}; use 7 (the paper's classes) or an odd count up to {MAX_STEER_BINS}"
            )
        if self.commands not in (None, *COMMAND_COUNTS):
            raise CrchflError(
                f"model.commands: {self.commands!r}; use 4 (follow, left, right, straight) or 6 (with change_left "
                "and change_right), or leave it out to take the data's"
            )
        for key in ("stop_head", "red_hold"):
            if getattr(self, key) and self.longitudinal != "target_speed":
                raise CrchflError(f"model.{key}: applies to a target-speed branch I only; drop it or set "
                                  "longitudinal = 'target_speed'")
        if self.arch == "paper":
            defaults = ModelConfig.__dataclass_fields__
            paper_values = {k: defaults[k].default for k in ("norm", "command_input", "command_pedals", "speed_input",
                                                             "commands")}
            for key, value in {**paper_values, "longitudinal": "pedals", "steer_bins": NUM_STEER_CLASSES}.items():
                if getattr(self, key) != value:
                    raise CrchflError(
                        f"model.{key}: {getattr(self, key)!r} applies to arch 'cil' only; the 'paper' architecture "
                        "has no normalisation, command or speed input, predicts pedals and the 7 steer classes; drop the key or set "
                        "arch = 'cil'"
                    )
        if self.image_height < MIN_IMAGE_HEIGHT or self.image_width < MIN_IMAGE_WIDTH:
            raise CrchflError(
                f"model.image_height/image_width: {self.image_height} x {self.image_width} is too small; "
                f"use at least {MIN_IMAGE_HEIGHT} x {MIN_IMAGE_WIDTH} pixels"
            )
        if self.image_height > MAX_HEIGHT_PX or self.image_width > MAX_WIDTH_PX:
            raise CrchflError(
                f"model.image_height/image_width: {self.image_height} x {self.image_width} is too large; "
                f"use at most {MAX_HEIGHT_PX} x {MAX_WIDTH_PX} pixels"
            )

    @property
    def shape(self) -> BranchShape:
        """Widths of each branch for this size."""
        return SIZES[self.size]

    @property
    def num_commands(self) -> int:
        """The commands the network has heads (or one-hot places) for."""
        return self.commands or JUNCTION_COMMANDS



# ModelConfig keys that a new model takes from its training data where they are unset (model.with_training_data,
# through with_data_commands and with_data_signals): a run's recorded settings hold the decided value
DATA_DECIDED_KEYS = ("commands", "stop_head")


def with_data_signals(config: ModelConfig, signals_known: bool) -> ModelConfig:
    """``config`` with a stop head where ``stop_head`` is unset and the network is a built-in target-speed one
    whose training data hold signal states (``signals_known``; data sets of format 5 on); else unchanged
    (unset reads as none, so such a model's settings stay as they were). With one-link heads
    (raster.route_signal) it ran 0.17 red lights per km against 1.18 (docs/model.md, "A stop head")."""
    if config.stop_head is None and signals_known and config.longitudinal == "target_speed" and not config.class_path:
        return dataclasses.replace(config, stop_head=True)
    return config


def with_data_commands(config: ModelConfig, largest_command: int) -> ModelConfig:
    """``config`` with ``commands`` taken from the training data where it is unset: 6 where the data's largest
    command code is a lane change, else unchanged (4), so the towns' models stay as they were."""
    if config.commands is None and config.arch != "paper" and largest_command >= JUNCTION_COMMANDS:
        return dataclasses.replace(config, commands=NUM_COMMANDS)
    return config


# How a steer head's class scores become one steer value (learning.model.predict_actions):
# the paper's DAC ("argmax"), the probability-weighted class values ("expected"), "mode" (the
# probability-weighted values of the most likely class and its two neighbours only: argmax's choice
# of a turn or not, with a steer between its classes), or "auto": argmax for the paper's 7 classes,
# mode for a finer head. Measured (docs/model.md): with 7 classes expected drove worse in Town02
# traffic (2/6 against 4/6); with 21 bins argmax turns too tightly where the probability sits on
# several bins and leaves the road in the towns, and expected averages a turn with going straight
# on the two-lane grid (one-turn 2/30) and rounds a lane change's small steer to none; mode drives
# the towns as expected does and makes the grid's lane changes (docs/measurements.md, 2026-12-05, sixth).
STEER_DECODINGS = ("auto", "argmax", "expected", "mode")
DEFAULT_STEER_DECODING = "auto"


def check_steer_decoding(steer_decoding: str, where: str = "--steer-decoding") -> str:
    """``steer_decoding`` if it is one of STEER_DECODINGS; else a CrchflError naming ``where``."""
    if steer_decoding not in STEER_DECODINGS:
        raise CrchflError(f"{where}: use one of {', '.join(STEER_DECODINGS)}, got {steer_decoding!r}")
    return steer_decoding


def resolved_steer_decoding(steer_decoding: str, steer_bins: int) -> str:
    """"argmax", "expected" or "mode": what ``steer_decoding`` means for a head of ``steer_bins`` classes."""
    if check_steer_decoding(steer_decoding) != "auto":
        return steer_decoding
    return "argmax" if steer_bins == NUM_STEER_CLASSES else "mode"
# A driving target-speed model reaches a lower target in half its speed horizon
# (expert.pedals_towards): its targets under-state the expert's braking, as a
# regression between stopping and going does. Town02 traffic suite 0/6 -> 4/6
# (docs/model.md); evaluation against the labels keeps 1.
DEFAULT_BRAKE_GAIN = 2.0


def check_brake_gain(brake_gain: float) -> float:
    """``brake_gain`` if it is > 0 (a CrchflError naming --brake-gain otherwise)."""
    if not brake_gain > 0:
        raise CrchflError(f"--brake-gain must be > 0 (1 = the label horizon), got {brake_gain}")
    return brake_gain
SAMPLINGS = ("uniform", "class_balanced", "command_balanced", "pedal_balanced")


CLASS_WEIGHTINGS = ("none", "inverse", "sqrt_inverse")
# Arithmetic of training's forward pass (TrainConfig.precision): weights and optimiser stay float32 in each;
# "auto" is bf16 where the device multiplies bfloat16 in hardware, else fp32 (devices.resolved_precision).
RESOLVED_PRECISIONS = ("fp32", "bf16")  # what a training runs in, "auto" decided
PRECISIONS = ("auto", *RESOLVED_PRECISIONS)
# How train_vehicles trains many vehicles (TrainConfig.multi_vehicle; devices.resolved_multi_vehicle).
MULTI_VEHICLE_METHODS = ("auto", "sequential", "vmap")


# Steer head classes at most (model.steer_bins): 0.01 steps over [-1, 1].
MAX_STEER_BINS = 201
# The cil architecture's steer classes: 0.1 apart over [-1, 1]. The traffic suite went from
# 2 / 6 and 3 / 6 (the paper's 7) to 5 / 6 and 4 / 6 (docs/model.md).
CIL_STEER_BINS = 21

MAX_BATCH_SIZE = 65_536  # samples a batch: four camera images each
MAX_DRAW_WEIGHT = 1000.0  # beyond this a few emphasised samples (red lights, yields) would make up nearly every batch
MAX_RED_WINDOW_M = 500.0  # farther than any camera draws a signal head
MAX_YIELD_WINDOW_M = FOE_RANGE_M  # the farthest a junction foe is looked for: beyond it no gap is known

# `train`'s default moving average of the weights (not TrainConfig's: the federated schemes' local trainings keep
# none): 0.998 a step, about the last 500 steps, measured in closed loop on the paper data set's 2,360 steps
AUTO_EMA_DECAY = 0.998


def auto_ema_decay(train_samples: int, batch_size: int) -> float:
    """`train`'s default ``ema_decay``: AUTO_EMA_DECAY, but averaging over no more than about the last two
    epochs' steps (1 / (1 - decay) steps), so that a short training does not keep its first steps' weights."""
    steps_per_epoch = math.ceil(train_samples / batch_size)
    return min(AUTO_EMA_DECAY, 1 - 0.5 / steps_per_epoch)


@dataclass(frozen=True)
class TrainConfig:
    """Settings of local training (the paper's Table II, except the measured learning rate and balancing).

    learning_rate, beta1, beta2, weight_decay, adam_eps: Adam of each branch
        (the paper's learning rate is 1e-4; docs/model.md gives the measurements).
    batch_size: training batch (32); eval_batch_size: batch for evaluation only.
    device: "auto" (CUDA when present, else CPU), "cpu" or "cuda".
    deterministic: torch.use_deterministic_algorithms for reproducible runs.
    multi_vehicle: how many vehicles' models train side by side in one process: "sequential" (one
        after the other), "vmap" (all in one vectorised step) or "auto" (default): "vmap" on a GPU
        (1.42x "sequential" on an H200, measured), "sequential" on a CPU (faster there, measured).
    sampling: "uniform", "class_balanced", "command_balanced" or "pedal_balanced" (balance.py).
    class_weighting: steer cross-entropy weights "none", "inverse" or "sqrt_inverse" (balance.py).
    red_weight, red_window_m: a sample whose next signal shows red or yellow within ``red_window_m``
        metres (standing at it included) is drawn ``red_weight`` times as often as otherwise (balance.py;
        1 = off; samples with an unknown signal, a format-4 data set's, never are).
    yield_weight, yield_window_m: the same for a sample whose nearest junction foe to yield to is within
        ``yield_window_m`` metres of the conflict point (the data set's yield_gap_m; format 5).
    precision: "auto" (default: "bf16" where the device has bfloat16 arithmetic, AVX-512 BF16 or AMX
        on a CPU, else "fp32"), "fp32" (float32 throughout) or "bf16" (the forward pass under
        bfloat16 autocast, on CPU or CUDA; weights, gradients and Adam stay float32). docs/model.md
        measures both.
    ema_decay: 0 (default) keeps the trained weights; above 0 a training keeps, evaluates and hands on
        an exponential moving average of the weights over its steps instead (torch.optim.swa_utils;
        0.998 averages about the last 500 steps). Sequential training only: ``multi_vehicle`` "auto"
        then trains sequentially, "vmap" is refused; docs/model.md.
    """

    learning_rate: float = 1e-3
    beta1: float = 0.9
    beta2: float = 0.999
    weight_decay: float = 3e-3
    adam_eps: float = 1e-8
    batch_size: int = 32
    eval_batch_size: int = 256
    device: Literal["auto", "cpu", "cuda"] = "auto"
    deterministic: bool = False
    multi_vehicle: Literal["auto", "sequential", "vmap"] = "auto"
    sampling: Literal["uniform", "class_balanced", "command_balanced", "pedal_balanced"] = "uniform"
    class_weighting: Literal["none", "inverse", "sqrt_inverse"] = "sqrt_inverse"
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    red_weight: float = 1.0
    red_window_m: float = 30.0
    # added later: left out of a checkpoint's train_config at their defaults, so older checkpoints still resume
    yield_weight: float = field(default=1.0, metadata={OMIT_DEFAULT: True})
    yield_window_m: float = field(default=30.0, metadata={OMIT_DEFAULT: True})
    ema_decay: float = field(default=0.0, metadata={OMIT_DEFAULT: True})

    def __post_init__(self) -> None:
        check_range(self.red_weight, "train.red_weight", 1, MAX_DRAW_WEIGHT, "a draw multiplier (1 = off)")
        check_range(self.red_window_m, "train.red_window_m", 0, MAX_RED_WINDOW_M, "metres before a stop line",
                    lo_open=True)
        check_range(self.yield_weight, "train.yield_weight", 1, MAX_DRAW_WEIGHT, "a draw multiplier (1 = off)")
        check_range(self.yield_window_m, "train.yield_window_m", 0, MAX_YIELD_WINDOW_M,
                    "metres of a junction foe from the conflict point", lo_open=True)
        # 1 would never move the average from the first step's weights
        check_range(self.ema_decay, "train.ema_decay", 0, 1, "a decay per step (0 = off)", hi_open=True)
        if not 0 < self.learning_rate <= 10:
            raise CrchflError(f"train.learning_rate: {self.learning_rate} must lie in (0, 10] (paper: 1e-4)")
        for key in ("beta1", "beta2"):
            if not 0 <= getattr(self, key) < 1:
                raise CrchflError(f"train.{key}: {getattr(self, key)} must lie in [0, 1)")
        # above 1 the decay shrinks every weight faster than a gradient step moves it (paper: 3e-3)
        check_range(self.weight_decay, "train.weight_decay", 0, 1, "a decay (paper: 3e-3)")
        # eps only keeps Adam's division finite; above 1 it swamps the second moment (paper: 1e-8)
        check_range(self.adam_eps, "train.adam_eps", 0, 1, "an epsilon (paper: 1e-8)", lo_open=True)
        if not (1 <= self.batch_size <= MAX_BATCH_SIZE and 1 <= self.eval_batch_size <= MAX_BATCH_SIZE):
            raise CrchflError(
                f"train.batch_size and train.eval_batch_size must be in 1 .. {MAX_BATCH_SIZE} (paper: 32), "
                f"got {self.batch_size} and {self.eval_batch_size}"
            )
        if self.device not in ("auto", "cpu", "cuda"):
            raise CrchflError(f"train.device: {self.device!r} is unknown; use 'auto', 'cpu' or 'cuda'")
        if self.multi_vehicle not in MULTI_VEHICLE_METHODS:
            raise CrchflError(
                f"train.multi_vehicle: {self.multi_vehicle!r} is unknown; use one of {', '.join(map(repr, MULTI_VEHICLE_METHODS))}"
            )
        if self.multi_vehicle == "vmap" and self.ema_decay:
            raise CrchflError("train.ema_decay: the vectorised training (multi_vehicle 'vmap') keeps no average of "
                              "the weights; set train.multi_vehicle = 'sequential' or train.ema_decay = 0")
        if self.sampling not in SAMPLINGS:
            raise CrchflError(f"train.sampling: {self.sampling!r} is unknown; use one of {', '.join(map(repr, SAMPLINGS))}")
        if self.precision not in PRECISIONS:
            raise CrchflError(
                f"train.precision: {self.precision!r} is unknown; use one of {', '.join(map(repr, PRECISIONS))}"
            )
        if self.class_weighting not in CLASS_WEIGHTINGS:
            raise CrchflError(
                f"train.class_weighting: {self.class_weighting!r} is unknown; "
                f"use one of {', '.join(map(repr, CLASS_WEIGHTINGS))}"
            )
