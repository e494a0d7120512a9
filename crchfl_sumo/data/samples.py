"""Samples: the in-memory container of training examples (images, actions, steer classes, commands, speeds).

One sample is one time step of one vehicle: the four camera images (order
``CAMERA_NAMES`` = CamH, CamF, CamL, CamR; HWC RGB, uint8), the action
vector (throttle, steer, brake), the steer class (``labels.digitize_steer``),
the route command (``labels.COMMAND_NAMES``), the vehicle's speed [m/s] and its
target speed [m/s] (its speed ``ExpertConfig.speed_horizon_s`` later, data/expert.py),
and the next signal on its route (labels.SIGNAL_NAMES) with its stop line's distance
[m] (inf: none), which training may weigh (learning/balance.py).
Images stay uint8 in memory (4x smaller than float32); the model normalises them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from crchfl_sumo.data.labels import NUM_COMMANDS, NUM_STEER_CLASSES, SIGNAL_NAMES, SIGNAL_UNKNOWN
from crchfl_sumo.vision.camera import CAMERA_NAMES

NUM_CAMERAS = len(CAMERA_NAMES)
NUM_ACTIONS = 3
# The tensors, in constructor order.
FIELDS = ("images", "actions", "steer_class", "command", "speed_mps", "target_speed_mps", "signal_state",
          "signal_distance_m", "yield_gap_m")


@dataclass(frozen=True)
class Samples:
    """N samples as torch tensors on the CPU (or any one device).

    images: uint8 [N, 4, H, W, 3]; actions: float32 [N, 3]; steer_class: int64 [N];
    command: int64 [N] (0..5, labels.COMMAND_NAMES); speed_mps, target_speed_mps: float32 [N];
    signal_state: int64 [N] (labels.SIGNAL_NAMES; None: all unknown); signal_distance_m: float32 [N]
    (inf: none; None: all inf); yield_gap_m: float32 [N], how far the nearest junction foe the car must
    yield to is from the conflict point (negative: in it; inf: none; None: all inf).
    """

    images: torch.Tensor
    actions: torch.Tensor
    steer_class: torch.Tensor
    command: torch.Tensor
    speed_mps: torch.Tensor
    target_speed_mps: torch.Tensor
    signal_state: torch.Tensor | None = None
    signal_distance_m: torch.Tensor | None = None
    yield_gap_m: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.images.shape[0] if self.images.dim() else -1
        device = self.images.device
        if self.signal_state is None:
            unknown = torch.full((max(n, 0),), SIGNAL_UNKNOWN, dtype=torch.int64, device=device)
            object.__setattr__(self, "signal_state", unknown)
        for name in ("signal_distance_m", "yield_gap_m"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, torch.full((max(n, 0),), float("inf"), device=device))
        if self.images.dtype != torch.uint8 or self.images.dim() != 5:
            raise ValueError(f"images must be uint8 [N, 4, H, W, 3], got {self.images.dtype} {tuple(self.images.shape)}")
        if self.images.shape[1] != NUM_CAMERAS or self.images.shape[4] != 3:
            raise ValueError(f"images must be [N, {NUM_CAMERAS}, H, W, 3], got {tuple(self.images.shape)}")
        if self.actions.dtype != torch.float32 or tuple(self.actions.shape) != (n, NUM_ACTIONS):
            raise ValueError(f"actions must be float32 [{n}, 3], got {self.actions.dtype} {tuple(self.actions.shape)}")
        if n and not bool(torch.isfinite(self.actions).all()):
            raise ValueError("actions values must be finite")
        if self.steer_class.dtype != torch.int64 or tuple(self.steer_class.shape) != (n,):
            raise ValueError(
                f"steer_class must be int64 [{n}], got {self.steer_class.dtype} {tuple(self.steer_class.shape)}"
            )
        if n and (int(self.steer_class.min()) < 0 or int(self.steer_class.max()) >= NUM_STEER_CLASSES):
            raise ValueError(f"steer_class values must lie in 0..{NUM_STEER_CLASSES - 1}")
        if self.command.dtype != torch.int64 or tuple(self.command.shape) != (n,):
            raise ValueError(f"command must be int64 [{n}], got {self.command.dtype} {tuple(self.command.shape)}")
        if n and (int(self.command.min()) < 0 or int(self.command.max()) >= NUM_COMMANDS):
            raise ValueError(f"command values must lie in 0..{NUM_COMMANDS - 1}")
        for name in ("speed_mps", "target_speed_mps"):
            speed = getattr(self, name)
            if speed.dtype != torch.float32 or tuple(speed.shape) != (n,):
                raise ValueError(f"{name} must be float32 [{n}], got {speed.dtype} {tuple(speed.shape)}")
            if n and not bool(torch.isfinite(speed).all() and (speed >= 0).all()):
                raise ValueError(f"{name} values must be finite and >= 0")
        if self.signal_state.dtype != torch.int64 or tuple(self.signal_state.shape) != (n,):
            raise ValueError(
                f"signal_state must be int64 [{n}], got {self.signal_state.dtype} {tuple(self.signal_state.shape)}"
            )
        if n and (int(self.signal_state.min()) < 0 or int(self.signal_state.max()) >= len(SIGNAL_NAMES)):
            raise ValueError(f"signal_state values must lie in 0..{len(SIGNAL_NAMES) - 1}")
        for name in ("signal_distance_m", "yield_gap_m"):
            distance = getattr(self, name)
            if distance.dtype != torch.float32 or tuple(distance.shape) != (n,):
                raise ValueError(f"{name} must be float32 [{n}], got {distance.dtype} {tuple(distance.shape)}")
        if n and not bool((self.signal_distance_m >= 0).all()):  # NaN fails this too
            raise ValueError("signal_distance_m values must be >= 0 (inf: no signal ahead)")
        # a foe already in the conflict area has a negative gap (shards.check_label_values: NaN and -inf refused)
        if n and not bool((self.yield_gap_m > -math.inf).all()):  # NaN fails this too
            raise ValueError("yield_gap_m values must be numbers or inf (inf: no foe to yield to)")

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def image_hw(self) -> tuple[int, int]:
        """(height, width) of the camera images in pixels."""
        return int(self.images.shape[2]), int(self.images.shape[3])

    def subset(self, indices: Sequence[int] | np.ndarray | torch.Tensor | slice) -> Samples:
        """The samples at ``indices`` (a slice gives views, an index list gives copies)."""
        if not isinstance(indices, slice):
            indices = torch.as_tensor(np.asarray(indices, dtype=np.int64))
        return Samples(*(getattr(self, name)[indices] for name in FIELDS))

    def to(self, device: torch.device | str) -> Samples:
        """The same samples on ``device``."""
        return Samples(*(getattr(self, name).to(device) for name in FIELDS))

    @staticmethod
    def concat(parts: Sequence[Samples]) -> Samples:
        """All samples of ``parts``, in order; parts must share the image size."""
        if not parts:
            raise ValueError("Samples.concat needs at least one part")
        sizes = {p.image_hw for p in parts}
        if len(sizes) > 1:
            raise ValueError(f"Samples.concat: parts have different image sizes {sorted(sizes)}")
        return Samples(*(torch.cat([getattr(p, name) for p in parts]) for name in FIELDS))

    @staticmethod
    def from_numpy(
        images: np.ndarray,
        actions: np.ndarray,
        steer_class: np.ndarray,
        command: np.ndarray,
        speed_mps: np.ndarray,
        target_speed_mps: np.ndarray,
        signal_state: np.ndarray | None = None,
        signal_distance_m: np.ndarray | None = None,
        yield_gap_m: np.ndarray | None = None,
    ) -> Samples:
        """Build from numpy arrays (images are not copied when already uint8 and contiguous; no signal
        columns: unknown)."""
        return Samples(
            torch.from_numpy(np.ascontiguousarray(images, dtype=np.uint8)),
            torch.from_numpy(np.ascontiguousarray(actions, dtype=np.float32)),
            torch.from_numpy(np.ascontiguousarray(steer_class, dtype=np.int64)),
            torch.from_numpy(np.ascontiguousarray(command, dtype=np.int64)),
            torch.from_numpy(np.ascontiguousarray(speed_mps, dtype=np.float32)),
            torch.from_numpy(np.ascontiguousarray(target_speed_mps, dtype=np.float32)),
            None if signal_state is None else torch.from_numpy(np.ascontiguousarray(signal_state, dtype=np.int64)),
            None if signal_distance_m is None
            else torch.from_numpy(np.ascontiguousarray(signal_distance_m, dtype=np.float32)),
            None if yield_gap_m is None else torch.from_numpy(np.ascontiguousarray(yield_gap_m, dtype=np.float32)),
        )

    @staticmethod
    def empty(height: int, width: int) -> Samples:
        """Zero samples of the given image size."""
        return Samples(
            torch.zeros((0, NUM_CAMERAS, height, width, 3), dtype=torch.uint8),
            torch.zeros((0, NUM_ACTIONS), dtype=torch.float32),
            torch.zeros((0,), dtype=torch.int64),
            torch.zeros((0,), dtype=torch.int64),
            torch.zeros((0,), dtype=torch.float32),
            torch.zeros((0,), dtype=torch.float32),
        )
