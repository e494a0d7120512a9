"""Model checkpoints: a plain dict of tensors and plain values, loadable with weights_only=True.

Layout of the saved dict: ``format`` (CHECKPOINT_FORMAT), ``model_config``
(plain mapping of ModelConfig), ``state_dict`` (name -> tensor, on the CPU) and
``extra`` (plain JSON-like values: epoch, metrics ...). Written atomically.

Format 2 added ``ModelConfig.arch`` and its options. A format-1 file (written
before them) holds the paper's network, so it loads with arch "paper"; its
config mapping never names the new keys.

Loading is safe: torch.load(weights_only=True) unpickles only tensors and
plain values, so no code from a file ever runs, and a file holding anything
else is refused with one line of our own. What loads is checked before use:
the payload's keys and types, the model config (ModelConfig's own checks,
image size bounded), and every tensor against a freshly built model of that
config (names, shapes, dtypes, dense layout, finite and of a plausible size).
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from crchfl_sumo.core.atomic import atomic_path, atomic_path_keeping_previous
from crchfl_sumo.core.config import from_mapping, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import expert_from_labels
from crchfl_sumo.data.labels import NUM_STEER_CLASSES
from crchfl_sumo.learning.model import model_from_state, network
from crchfl_sumo.learning.settings import ModelConfig
from crchfl_sumo.vision.raster import camera_settings

CHECKPOINT_FORMAT = "crchfl-sumo-model/2"
LEGACY_FORMAT = "crchfl-sumo-model/1"  # before ModelConfig.arch: the paper architecture
# No weight of a trained DrivingModel comes near this (its inputs lie in [-1, 1], GroupNorm after every
# convolution); a larger one is a damaged or foreign file and would overflow a drive's dynamics.
MAX_ABS_WEIGHT = 1e6


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
    keep_previous: bool = False,
) -> None:
    """Write a checkpoint to ``path`` atomically (temporary beside it, fsync, os.replace).

    ``keep_previous``: the file it replaces becomes NAME.prev.pt (core.atomic), what a resume reads
    when the latest is damaged.
    """
    payload = {
        "format": CHECKPOINT_FORMAT,
        "model_config": to_mapping(model_config),
        "state_dict": {name: t.detach().cpu().contiguous() for name, t in state_dict.items()},
        "extra": dict(extra or {}),
    }
    with (atomic_path_keeping_previous if keep_previous else atomic_path)(path) as temp:
        torch.save(payload, temp)


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint written by save_checkpoint (weights_only=True: no code is unpickled), its payload checked."""
    path = Path(path)
    if not path.is_file():
        raise CrchflError(f"{path}: checkpoint not found; check the path")
    payload = load_weights_only(path, "checkpoint", "point to a checkpoint.pt written by crchfl-sumo")
    if not isinstance(payload, dict) or payload.get("format") not in (CHECKPOINT_FORMAT, LEGACY_FORMAT):
        raise CrchflError(f"{path}: not a crchfl-sumo checkpoint (format {CHECKPOINT_FORMAT} expected)")
    for key, kind in (("model_config", "a table of settings"), ("state_dict", "a table of tensors"), ("extra", "a table")):
        if not isinstance(payload.get(key), dict):
            raise CrchflError(
                f"{path}: checkpoint's {key} is {type(payload.get(key)).__name__ if key in payload else 'missing'}, "
                f"not {kind}; point to a checkpoint written by crchfl-sumo"
            )
    mapping = dict(payload["model_config"])
    if payload["format"] == LEGACY_FORMAT:
        if "arch" in mapping:
            raise CrchflError(f"{path}: a format-1 checkpoint names model_config.arch; it was not written by crchfl-sumo")
        mapping["arch"] = "paper"
    # Format-2 files written before command_pedals / longitudinal existed: an unconditioned pedal branch.
    mapping.setdefault("command_pedals", False)
    mapping.setdefault("longitudinal", "pedals")
    mapping.setdefault("steer_bins", NUM_STEER_CLASSES)  # written before finer steer heads: the paper's 7
    model_config = from_mapping(ModelConfig, mapping, f"{path}: model_config")
    if payload["extra"].get("camera"):  # the data set's cameras, which a drive renders with
        camera_settings(payload["extra"]["camera"], f"{path}: extra.camera")
    if "expert" in payload["extra"]:  # the data set's expert, whose steering rack a drive steers through
        expert_from_labels(payload["extra"]["expert"], f"{path}: extra.expert")
    state_dict = payload["state_dict"]
    if not all(isinstance(k, str) and isinstance(t, torch.Tensor) for k, t in state_dict.items()):
        raise CrchflError(f"{path}: checkpoint's state_dict holds something other than named tensors; retrain the model")
    return Checkpoint(model_config, dict(state_dict), dict(payload["extra"]))


def load_weights_only(path: Path, what: str, fix: str) -> Any:
    """torch.load(weights_only=True) of ``path``; a file it refuses or cannot read is a one-line CrchflError.

    torch's own message runs over several lines (with colour codes) and
    suggests weights_only=False, which would run whatever code the file
    holds: it is not passed on.
    """
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise CrchflError(
            f"{path}: holds objects other than tensors and plain values, which crchfl-sumo never loads "
            f"(no code from a file runs); {fix}"
        ) from None
    except Exception as exc:  # torch raises several types for corrupt, truncated or foreign files
        raise CrchflError(f"{path}: not a readable {what} (empty, truncated or damaged: {type(exc).__name__}); {fix}") from None


def check_weights(config: ModelConfig, state: dict[str, torch.Tensor], where: str) -> None:
    """Refuse weights that do not fit a freshly built model of ``config``: names, shapes, dtypes, dense
    layout, finite values within MAX_ABS_WEIGHT."""
    with torch.device("meta"):  # shapes and dtypes only: nothing allocated, no random init
        expected = network(config).state_dict()
    fix = "the file is damaged or not of this model config; retrain or point to another checkpoint"
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        names = ", ".join((["missing " + n for n in missing] + ["unexpected " + n for n in unexpected])[:3])
        raise CrchflError(f"{where}: weights do not fit the stored model config ({names}); {fix}")
    for name, want in expected.items():
        tensor = state[name]
        if tensor.layout != torch.strided:
            raise CrchflError(f"{where}: weight {name} is stored as a {tensor.layout} tensor, not a dense one; {fix}")
        if tuple(tensor.shape) != tuple(want.shape) or tensor.dtype != want.dtype:
            raise CrchflError(
                f"{where}: weight {name} is {tensor.dtype} {list(tensor.shape)}, the model config needs "
                f"{want.dtype} {list(want.shape)}; {fix}"
            )
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CrchflError(f"{where}: weight {name} holds NaN or inf; {fix}")
        if tensor.is_floating_point() and tensor.numel() and float(tensor.abs().max()) > MAX_ABS_WEIGHT:
            raise CrchflError(
                f"{where}: weight {name} holds {float(tensor.abs().max()):.3g}, beyond the {MAX_ABS_WEIGHT:.0e} "
                f"no trained model reaches; {fix}"
            )


def load_model(path: str | Path, device: torch.device | str = "cpu") -> torch.nn.Module:
    """The model stored in a checkpoint, in eval mode, on ``device``."""
    return checkpoint_model(load_checkpoint(path), path, device)


def checkpoint_model(checkpoint: Checkpoint, path: str | Path, device: torch.device | str = "cpu") -> torch.nn.Module:
    """The model of a checkpoint already read from ``path`` (its weights checked first), in eval mode, on ``device``."""
    check_weights(checkpoint.model_config, checkpoint.state_dict, str(path))
    try:
        model = model_from_state(checkpoint.model_config, checkpoint.state_dict, device)
    except RuntimeError as exc:
        raise CrchflError(f"{path}: weights do not fit the stored model config ({exc})") from None
    return model.eval()
