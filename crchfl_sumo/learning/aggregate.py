"""Weighted FedAvg on PyTorch state dicts, as pure functions.

The paper (Algorithm 1, eqs. for stages II and III) weights every model by the
number of training samples behind it: an edge averages its vehicles with
weights |T_nk|, the cloud averages the edges with weights sum_k |T_nk|. Both
are the same operation, ``weighted_average``.

Numerics: floating tensors are averaged in float64 and cast back to their own
dtype, so float16/32 models do not lose precision in the sum. Integer tensors
(BatchNorm's ``num_batches_tracked`` is the usual one) are averaged the same
way and rounded to the nearest integer: a count that is the same everywhere
stays exactly as it is, and differing counts get their weighted mean. Boolean
and complex tensors are rejected: no model of this project has them and no
average of them is obviously right.

Inputs are never modified; every returned tensor is new memory.
"""

from __future__ import annotations

import math
import numbers
from typing import Mapping, Sequence

import torch

from crchfl_sumo.core.errors import CrchflError

StateDict = Mapping[str, torch.Tensor]


def weighted_average(states: Sequence[StateDict], weights: Sequence[float]) -> dict[str, torch.Tensor]:
    """FedAvg: sum_i w_i * state_i / sum_i w_i, key by key.

    ``weights`` are sample counts (any non-negative finite numbers); at least one
    must be positive. All states must have the same keys, shapes and dtypes.
    Raises CrchflError on mismatched states or unusable weights.
    """
    _check_weights(states, weights)
    _check_states(states)
    total = float(sum(float(w) for w in weights))
    fractions = [float(w) / total for w in weights]
    averaged: dict[str, torch.Tensor] = {}
    for key, first in states[0].items():
        acc = torch.zeros(first.shape, dtype=torch.float64, device=first.device)
        for state, fraction in zip(states, fractions):
            if fraction:
                acc += fraction * state[key].detach().to(torch.float64)
        if not first.is_floating_point():
            acc = torch.round(acc)
        averaged[key] = acc.to(first.dtype)
    return averaged


def fedavg(models: Sequence[tuple[StateDict, int]]) -> dict[str, torch.Tensor]:
    """Flower-style convenience: ``[(state, num_samples), ...]`` -> averaged state."""
    if not models:
        raise CrchflError("fedavg: no models to average; at least one (state, num_samples) pair is needed")
    states, counts = zip(*models)
    return weighted_average(list(states), list(counts))


def _check_weights(states: Sequence[StateDict], weights: Sequence[float]) -> None:
    if not states:
        raise CrchflError("weighted_average: no states to average; pass at least one state dict")
    if len(weights) != len(states):
        raise CrchflError(f"weighted_average: {len(states)} states but {len(weights)} weights; pass one weight per state")
    for i, w in enumerate(weights):
        if isinstance(w, bool) or not isinstance(w, numbers.Real) or not math.isfinite(float(w)) or w < 0:
            raise CrchflError(f"weighted_average: weight {i} is {w!r}; weights are sample counts, finite and >= 0")
    if sum(float(w) for w in weights) <= 0:
        raise CrchflError("weighted_average: the weights sum to zero; at least one model must carry samples")


def _check_states(states: Sequence[StateDict]) -> None:
    reference = states[0]
    for key, tensor in reference.items():
        if not isinstance(tensor, torch.Tensor):
            raise CrchflError(f"weighted_average: state 0 entry {key!r} is not a tensor")
        if tensor.dtype == torch.bool or tensor.is_complex():
            raise CrchflError(f"weighted_average: entry {key!r} has dtype {tensor.dtype}, which has no average")
    keys = set(reference)
    for i, state in enumerate(states[1:], start=1):
        if set(state) != keys:
            missing = sorted(keys - set(state))
            extra = sorted(set(state) - keys)
            raise CrchflError(
                f"weighted_average: state {i} keys differ from state 0 (missing {missing}, extra {extra}); "
                "all models must share one architecture"
            )
        for key, tensor in reference.items():
            other = state[key]
            if not isinstance(other, torch.Tensor):
                raise CrchflError(f"weighted_average: state {i} entry {key!r} is not a tensor")
            if other.shape != tensor.shape:
                raise CrchflError(
                    f"weighted_average: entry {key!r} has shape {tuple(other.shape)} in state {i} "
                    f"but {tuple(tensor.shape)} in state 0"
                )
            if other.dtype != tensor.dtype:
                raise CrchflError(
                    f"weighted_average: entry {key!r} has dtype {other.dtype} in state {i} but {tensor.dtype} in state 0"
                )
