"""Compressed model transfers ([federation] update_codec): what a receiver gets, and how many bytes it costs.

A transfer carries a model as its difference from a reference both ends hold, encoded:

* ``none``: the model as it is (the paper).
* ``int8``: every floating tensor of the difference quantized symmetrically to 8 bits with one float32
  scale a tensor (scale = max |x| / 127; each element off by at most scale / 2). Every model transfer,
  up and down, wireless and wireline, carries this: about a quarter of the float32 bytes.
* ``topk``: a vehicle's upload sends only the ``topk_fraction`` largest entries (by magnitude) of each
  floating tensor of its update (its trained model minus the model it started from) plus what it left
  out before (error feedback, Seide et al. 2014; Stich et al. 2018: the residual carries over to its
  next upload). Each kept entry costs its value and a 4-byte index. Downloads and wireline transfers,
  which carry aggregates, are sent whole.

Tensors that are not floating point (counters) always travel whole. Pure functions on state dicts.
"""

from __future__ import annotations

import math
from typing import Mapping

import torch

from crchfl_sumo.learning.model import State

INDEX_BYTES = 4  # a kept entry's position in its tensor (int32)
SCALE_BYTES = 4  # an int8 tensor's float32 scale


def _is_float(t: torch.Tensor) -> bool:
    return t.is_floating_point()


def int8_roundtrip(delta: Mapping[str, torch.Tensor]) -> State:
    """``delta`` as the receiver decodes it after 8-bit symmetric quantization, tensor by tensor."""
    out = {}
    for name, x in delta.items():
        if not _is_float(x):
            out[name] = x.clone()
            continue
        peak = x.abs().max() if x.numel() else torch.zeros((), dtype=x.dtype)
        if float(peak) == 0.0:
            out[name] = torch.zeros_like(x)
            continue
        scale = peak.to(torch.float32) / 127.0
        q = torch.clamp(torch.round(x.to(torch.float32) / scale), -127, 127)
        out[name] = (q * scale).to(x.dtype)
    return out


def kept_count(numel: int, fraction: float) -> int:
    """Entries a top-k upload keeps of a tensor: at least one of a non-empty tensor."""
    return min(numel, max(1, math.ceil(fraction * numel))) if numel else 0


def topk_roundtrip(
    delta: Mapping[str, torch.Tensor], fraction: float, residual: Mapping[str, torch.Tensor] | None = None
) -> tuple[State, State]:
    """(what the receiver decodes, the new residual) of a top-k upload of ``delta`` with error feedback:
    the ``fraction`` largest entries of ``delta + residual`` per floating tensor are sent; the rest is the
    new residual, added to the next upload. ``sent + new residual == delta + residual``, exactly."""
    sent, left = {}, {}
    for name, x in delta.items():
        if not _is_float(x):
            sent[name] = x.clone()
            continue
        acc = x + residual[name] if residual is not None and name in residual else x.clone()
        flat = acc.reshape(-1)
        k = kept_count(flat.numel(), fraction)
        mask = torch.zeros_like(flat, dtype=torch.bool)
        if k:
            mask[torch.topk(flat.abs(), k, sorted=False).indices] = True
        kept = torch.where(mask, flat, torch.zeros_like(flat))
        sent[name] = kept.reshape(acc.shape)
        left[name] = (flat - kept).reshape(acc.shape)
    return sent, left


def encoded_fraction(state: Mapping[str, torch.Tensor], codec: str, fraction: float = 1.0) -> float:
    """Bytes of an encoded transfer of ``state``'s shape over its raw bytes (1.0 for ``none``)."""
    raw = sum(t.numel() * t.element_size() for t in state.values())
    if codec == "none" or raw == 0:
        return 1.0
    encoded = 0
    for t in state.values():
        if not _is_float(t):
            encoded += t.numel() * t.element_size()
        elif codec == "int8":
            encoded += t.numel() + SCALE_BYTES
        elif codec == "topk":
            encoded += kept_count(t.numel(), fraction) * (t.element_size() + INDEX_BYTES)
        else:
            raise ValueError(f"unknown update codec {codec!r}")
    return encoded / raw


def add(reference: Mapping[str, torch.Tensor], delta: Mapping[str, torch.Tensor]) -> State:
    """``reference + delta`` (a non-floating tensor is taken from ``delta``, which carries it whole)."""
    return {name: (reference[name] + d).to(reference[name].dtype) if _is_float(d) else d.clone()
            for name, d in delta.items()}


def subtract(model: Mapping[str, torch.Tensor], reference: Mapping[str, torch.Tensor]) -> State:
    """``model - reference`` (a non-floating tensor: ``model``'s)."""
    return {name: m - reference[name] if _is_float(m) else m.clone() for name, m in model.items()}


def int8_transfer(model: Mapping[str, torch.Tensor], reference: Mapping[str, torch.Tensor]) -> State:
    """What the receiver of ``model`` holds after an int8 transfer against ``reference``."""
    return add(reference, int8_roundtrip(subtract(model, reference)))
