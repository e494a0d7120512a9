"""The two-branch driving network of the CRCHFL paper, in one file with its config.

Branch I sees the head camera (CamH) and regresses (throttle, brake).
Branch II sees the front, left and right cameras stacked into 9 channels and
classifies the steer into the 7 classes of ``labels.STEER_CLASS_VALUES``.
Both branches share one topology (a PilotNet-like conv stack, adaptive average
pooling to a fixed grid, a small MLP); the two sizes differ only in widths:

- ``compact`` (default): about 0.5 M parameters, fast enough to train on a CPU.
- ``paper``: about 39.4 M parameters (about 150 MiB of fp32), the size of the
  paper's reference implementation, for runs whose byte counts follow the paper.

Because of the adaptive pooling the parameter count does not depend on the
image size, and any image of at least 48 x 64 pixels is accepted.
Images enter as uint8 [B, 4, H, W, 3] (camera order ``labels.CAMERA_NAMES``)
and are normalised inside the network, so uint8 can stay uint8 in memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import nn

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.labels import NUM_STEER_CLASSES, steer_from_class

State = dict[str, torch.Tensor]  # a model's weights by parameter name, as state_dict() gives them

MIN_IMAGE_HEIGHT = 48
MIN_IMAGE_WIDTH = 64


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


@dataclass(frozen=True)
class ModelConfig:
    """Settings of the driving network.

    size: "compact" (default, ~0.5 M parameters) or "paper" (~39.4 M, ~150 MiB).
    image_height, image_width: camera image size in pixels (default 64 x 128,
        the default of camera.CameraConfig); at least 48 x 64.
    """

    size: Literal["compact", "paper"] = "compact"
    image_height: int = 64
    image_width: int = 128

    def __post_init__(self) -> None:
        if self.size not in SIZES:
            raise CrchflError(f"model.size: {self.size!r} is unknown; use one of {', '.join(map(repr, SIZES))}")
        if self.image_height < MIN_IMAGE_HEIGHT or self.image_width < MIN_IMAGE_WIDTH:
            raise CrchflError(
                f"model.image_height/image_width: {self.image_height} x {self.image_width} is too small; "
                f"use at least {MIN_IMAGE_HEIGHT} x {MIN_IMAGE_WIDTH} pixels"
            )

    @property
    def shape(self) -> BranchShape:
        """Widths of each branch for this size."""
        return SIZES[self.size]


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
    """Conv stack -> adaptive average pool -> MLP -> ``num_outputs`` values."""

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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)


class DrivingModel(nn.Module):
    """uint8 images [B, 4, H, W, 3] -> (throttle_brake [B, 2] in [0, 1], steer_logits [B, 7])."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.branch_throttle_brake = Branch(3, 2, config.shape)  # branch I: CamH
        self.branch_steer = Branch(9, NUM_STEER_CLASSES, config.shape)  # branch II: CamF|CamL|CamR

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        batch, _, height, width, _ = images.shape
        x = images.to(torch.float32) * (1.0 / 127.5) - 1.0
        # [B, H, W, C] -> [B, C, H, W] is a view in channels_last layout: no copy.
        head = x[:, 0].permute(0, 3, 1, 2)
        sides = x[:, 1:4].permute(0, 2, 3, 1, 4).reshape(batch, height, width, 9).permute(0, 3, 1, 2)
        throttle_brake = torch.sigmoid(self.branch_throttle_brake(head))
        steer_logits = self.branch_steer(sides)
        return throttle_brake, steer_logits


def count_parameters(model: nn.Module) -> int:
    """Number of scalar parameters."""
    return sum(p.numel() for p in model.parameters())


def state_size_bytes(state: dict[str, torch.Tensor]) -> int:
    """Bytes of the raw tensor data in a state dict (what one model transfer carries)."""
    return sum(t.numel() * t.element_size() for t in state.values())


def build_model(config: ModelConfig, seed: int) -> DrivingModel:
    """A freshly initialised model; the same seed gives the same weights."""
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        return DrivingModel(config)
    finally:
        torch.random.set_rng_state(generator_state)


def model_from_state(
    config: ModelConfig, state: dict[str, torch.Tensor], device: torch.device | str = "cpu"
) -> DrivingModel:
    """A model holding a copy of ``state`` on ``device``; the caller's tensors and RNG are untouched."""
    with torch.device("meta"):  # no random init: every weight comes from ``state``
        model = DrivingModel(config)
    weights = {name: t.detach().to(device=device, dtype=torch.float32, copy=True) for name, t in state.items()}
    model.load_state_dict(weights, assign=True)
    return model


@torch.no_grad()
def predict_actions(model: DrivingModel, images: torch.Tensor) -> np.ndarray:
    """uint8 images [B, 4, H, W, 3] (or one sample [4, H, W, 3]) -> float32 [B, 3] or [3].

    Columns are (throttle, steer, brake); the steer is the DAC value of the most
    likely class.
    """
    single = images.dim() == 4
    batch = images.unsqueeze(0) if single else images
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    try:
        throttle_brake, steer_logits = model(batch.to(device))
    finally:
        model.train(was_training)
    throttle_brake = throttle_brake.cpu().numpy()
    steer = steer_from_class(steer_logits.argmax(dim=1).cpu().numpy())
    actions = np.stack([throttle_brake[:, 0], steer, throttle_brake[:, 1]], axis=1).astype(np.float32)
    return actions[0] if single else actions
