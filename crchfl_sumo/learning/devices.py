"""Where and in what arithmetic training runs: the device, deterministic algorithms, bfloat16, and how
many vehicles are trained at once. Each "auto" setting is decided here, once, from the machine."""

from __future__ import annotations

import contextlib
import functools
import logging
import os

import torch

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig

log = logging.getLogger(__name__)


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
    sequential loop is faster (docs/benchmarks.md). BatchNorm cannot be vmapped, and the vectorised step
    keeps no moving average of the weights (``train.ema_decay``), so either stays sequential.
    """
    if config.multi_vehicle != "auto":
        return config.multi_vehicle
    return "vmap" if device_type == "cuda" and vmappable(model_config) and not config.ema_decay else "sequential"


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
