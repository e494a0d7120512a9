"""Model checkpoints: a plain dict of tensors and plain values, loadable with weights_only=True.

Layout of the saved dict: ``format`` (CHECKPOINT_FORMAT), ``model_config``
(plain mapping of ModelConfig), ``state_dict`` (name -> tensor, on the CPU) and
``extra`` (plain JSON-like values: epoch, metrics ...). Written atomically.

Format 2 added ``ModelConfig.arch`` and its options. A format-1 file (written
before them) holds the paper's network, so it loads with arch "paper"; its
config mapping never names the new keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from crchfl_sumo.core.atomic import atomic_path
from crchfl_sumo.core.config import from_mapping, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.learning.model import DrivingModel, model_from_state
from crchfl_sumo.learning.settings import ModelConfig

CHECKPOINT_FORMAT = "crchfl-sumo-model/2"
LEGACY_FORMAT = "crchfl-sumo-model/1"  # before ModelConfig.arch: the paper architecture


@dataclass(frozen=True)
class Checkpoint:
    """What a checkpoint file holds."""

    model_config: ModelConfig
    state_dict: dict[str, torch.Tensor]
    extra: dict[str, Any]


def save_checkpoint(
    path: str | Path,
    model_config: ModelConfig,
    state_dict: dict[str, torch.Tensor],
    extra: dict[str, Any] | None = None,
) -> None:
    """Write a checkpoint to ``path`` atomically (temporary beside it, fsync, os.replace)."""
    payload = {
        "format": CHECKPOINT_FORMAT,
        "model_config": to_mapping(model_config),
        "state_dict": {name: t.detach().cpu().contiguous() for name, t in state_dict.items()},
        "extra": dict(extra or {}),
    }
    with atomic_path(path) as temp:
        torch.save(payload, temp)


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint written by save_checkpoint (weights_only=True: no code is unpickled)."""
    path = Path(path)
    if not path.is_file():
        raise CrchflError(f"{path}: checkpoint not found; check the path")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt or foreign files
        raise CrchflError(f"{path}: not a readable checkpoint ({exc}); point to a checkpoint.pt written by crchfl-sumo") from None
    if not isinstance(payload, dict) or payload.get("format") not in (CHECKPOINT_FORMAT, LEGACY_FORMAT):
        raise CrchflError(f"{path}: not a crchfl-sumo checkpoint (format {CHECKPOINT_FORMAT} expected)")
    mapping = dict(payload["model_config"])
    if payload["format"] == LEGACY_FORMAT:
        if "arch" in mapping:
            raise CrchflError(f"{path}: a format-1 checkpoint names model_config.arch; it was not written by crchfl-sumo")
        mapping["arch"] = "paper"
    # Format-2 files written before command_pedals / longitudinal existed: an unconditioned pedal branch.
    mapping.setdefault("command_pedals", False)
    mapping.setdefault("longitudinal", "pedals")
    model_config = from_mapping(ModelConfig, mapping, f"{path}: model_config")
    return Checkpoint(model_config, dict(payload["state_dict"]), dict(payload["extra"]))


def load_model(path: str | Path, device: torch.device | str = "cpu") -> DrivingModel:
    """The model stored in a checkpoint, in eval mode, on ``device``."""
    return checkpoint_model(load_checkpoint(path), path, device)


def checkpoint_model(checkpoint: Checkpoint, path: str | Path, device: torch.device | str = "cpu") -> DrivingModel:
    """The model of a checkpoint already read from ``path``, in eval mode, on ``device``."""
    try:
        model = model_from_state(checkpoint.model_config, checkpoint.state_dict, device)
    except RuntimeError as exc:
        raise CrchflError(f"{path}: weights do not fit the stored model config ({exc})") from None
    return model.eval()
