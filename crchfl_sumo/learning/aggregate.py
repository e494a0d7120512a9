"""Weighted FedAvg on PyTorch state dicts, as pure functions.

The paper (Algorithm 1, eqs. for stages II and III) weights every model by the
number of training samples behind it: an edge averages its vehicles with
weights |T_nk|, the cloud averages the edges with weights sum_k |T_nk|. Both
are the same operation, ``weighted_average``. ``RunningAverage`` is that
operation folded in one model at a time, for a caller that receives models one
by one and should not hold them all (a thousand vehicles' models are gigabytes).

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
    if not states:
        raise CrchflError("weighted_average: no states to average; pass at least one state dict")
    if len(weights) != len(states):
        raise CrchflError(f"weighted_average: {len(states)} states but {len(weights)} weights; pass one weight per state")
    running = RunningAverage(weights)
    for state in states:
        running.add(state)
    return running.result()


class RunningAverage:
    """``weighted_average`` folded in one state at a time: ``add`` the states in the order of ``weights``,
    then take ``result()`` (once).

    It keeps one float64 sum per tensor (twice a float32 model), never the
    states, so a caller may drop each state as soon as it is added: averaging N
    models holds one sum, not N models. The operations and their order are
    those of ``weighted_average`` (which is this class applied to a list), so
    streaming and batch give the same bits.
    """

    def __init__(self, weights: Sequence[float]) -> None:
        _check_weights(weights)
        total = float(sum(float(w) for w in weights))
        self._fractions = [float(w) / total for w in weights]
        self._sums: dict[str, torch.Tensor] = {}  # float64, in the first state's key order
        self._layout: dict[str, tuple[torch.Size, torch.dtype]] = {}  # the first state's shapes and dtypes
        self._added = 0
        self._taken = False

    def add(self, state: StateDict) -> None:
        """Fold in the next state (the one of ``weights[i]``, i = the states added so far)."""
        i = self._added
        if self._taken:
            raise CrchflError("weighted_average: the average was taken already; start a new RunningAverage")
        if i == len(self._fractions):
            raise CrchflError(f"weighted_average: more than {i} states for {i} weights; pass one weight per state")
        if i == 0:
            _check_first(state)
            self._layout = {key: (tensor.shape, tensor.dtype) for key, tensor in state.items()}
            self._sums = {
                key: torch.zeros(tensor.shape, dtype=torch.float64, device=tensor.device)
                for key, tensor in state.items()
            }
        else:
            _check_like_first(i, state, self._layout)
        fraction = self._fractions[i]
        if fraction:
            for key, acc in self._sums.items():
                acc += fraction * state[key].detach().to(torch.float64)
        self._added += 1

    def result(self) -> dict[str, torch.Tensor]:
        """The average of the states added (one per weight), each tensor in its own dtype and new memory."""
        if self._taken:
            raise CrchflError("weighted_average: the average was taken already; start a new RunningAverage")
        if self._added != len(self._fractions):
            raise CrchflError(
                f"weighted_average: {self._added} states but {len(self._fractions)} weights; pass one weight per state"
            )
        averaged: dict[str, torch.Tensor] = {}
        for key, acc in self._sums.items():
            dtype = self._layout[key][1]
            averaged[key] = (acc if dtype.is_floating_point else torch.round(acc)).to(dtype)
        self._sums, self._taken = {}, True  # a float64 model's result is its sum: handed over, not reused
        return averaged


def fedavg(models: Sequence[tuple[StateDict, int]]) -> dict[str, torch.Tensor]:
    """Flower-style convenience: ``[(state, num_samples), ...]`` -> averaged state."""
    if not models:
        raise CrchflError("fedavg: no models to average; at least one (state, num_samples) pair is needed")
    states, counts = zip(*models)
    return weighted_average(list(states), list(counts))


def _check_weights(weights: Sequence[float]) -> None:
    if not len(weights):
        raise CrchflError("weighted_average: no states to average; pass at least one state dict")
    for i, w in enumerate(weights):
        if isinstance(w, bool) or not isinstance(w, numbers.Real) or not math.isfinite(float(w)) or w < 0:
            raise CrchflError(f"weighted_average: weight {i} is {w!r}; weights are sample counts, finite and >= 0")
    if sum(float(w) for w in weights) <= 0:
        raise CrchflError("weighted_average: the weights sum to zero; at least one model must carry samples")


def _check_first(state: StateDict) -> None:
    """The first state: dense tensors of a dtype that has an average."""
    for key, tensor in state.items():
        if not isinstance(tensor, torch.Tensor):
            raise CrchflError(f"weighted_average: state 0 entry {key!r} is not a tensor")
        if tensor.dtype == torch.bool or tensor.is_complex():
            raise CrchflError(f"weighted_average: entry {key!r} has dtype {tensor.dtype}, which has no average")


def _check_like_first(i: int, state: StateDict, layout: Mapping[str, tuple[torch.Size, torch.dtype]]) -> None:
    """State ``i`` has the first state's keys, shapes and dtypes (``layout``)."""
    if set(state) != set(layout):
        missing = sorted(set(layout) - set(state))
        extra = sorted(set(state) - set(layout))
        raise CrchflError(
            f"weighted_average: state {i} keys differ from state 0 (missing {missing}, extra {extra}); "
            "all models must share one architecture"
        )
    for key, (shape, dtype) in layout.items():
        other = state[key]
        if not isinstance(other, torch.Tensor):
            raise CrchflError(f"weighted_average: state {i} entry {key!r} is not a tensor")
        if other.shape != shape:
            raise CrchflError(
                f"weighted_average: entry {key!r} has shape {tuple(other.shape)} in state {i} "
                f"but {tuple(shape)} in state 0"
            )
        if other.dtype != dtype:
            raise CrchflError(
                f"weighted_average: entry {key!r} has dtype {other.dtype} in state {i} but {dtype} in state 0"
            )


def staleness_factor(staleness: int, exponent: float) -> float:
    """The polynomial staleness weight (1 + staleness) ** -exponent (Xie et al., "Asynchronous Federated
    Optimization", 2019; exponent 0.5 is FedBuff's 1 / sqrt(1 + staleness), Nguyen et al., AISTATS 2022)."""
    if staleness < 0 or exponent < 0:
        raise CrchflError(f"staleness_factor: staleness {staleness} and exponent {exponent} must be >= 0")
    return (1.0 + staleness) ** -exponent


def buffered_update(
    current: StateDict, updates: Sequence[tuple[StateDict, StateDict, float, float]]
) -> dict[str, torch.Tensor]:
    """An asynchronous aggregator's step over its buffer (FedBuff):
    current + sum_i n_i f_i (trained_i - base_i) / sum_i n_i, for ``updates`` = [(base_i, trained_i, n_i, f_i)].

    n_i are sample counts, f_i staleness factors in [0, 1]. With every f_i = 1 and every base the current
    model this is the FedAvg of the trained models. Float64 sums, each tensor back in its dtype (integer
    tensors rounded), as ``weighted_average`` does.
    """
    if not updates:
        raise CrchflError("buffered_update: an empty buffer; pass at least one update")
    _check_weights([n for _, _, n, _ in updates])
    total = float(sum(n for _, _, n, _ in updates))
    sums = {key: tensor.detach().to(torch.float64).clone() for key, tensor in current.items()}
    for i, (base, trained, n, factor) in enumerate(updates):
        _check_like_first(i, base, {k: (t.shape, t.dtype) for k, t in current.items()})
        _check_like_first(i, trained, {k: (t.shape, t.dtype) for k, t in current.items()})
        scale = float(n) * float(factor) / total
        if scale:
            for key, acc in sums.items():
                acc += scale * (trained[key].detach().to(torch.float64) - base[key].detach().to(torch.float64))
    return {key: (acc if current[key].dtype.is_floating_point else torch.round(acc)).to(current[key].dtype)
            for key, acc in sums.items()}
