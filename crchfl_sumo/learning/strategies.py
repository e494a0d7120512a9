"""Aggregation strategies (``[federation] strategy``): which vehicles take part in an aggregation, what a
vehicle's local training adds to its loss, and how an aggregator turns the FedAvg of what it received
into its new model. The three steps of Flower's configure/aggregate protocol, on our two tiers:

1. **Who takes part.** Before an aggregation the loop asks, per aggregator:

       chosen = strategy.configure(tier, node, candidates, seed)

   ``candidates`` are the vehicles that could train for ``node`` now, in the run's order (an edge's
   members that ``[federation] selection`` kept; in SFL every vehicle), ``seed`` this step's seed
   for any draw. The chosen train and upload; the others sit the aggregation out (counted as
   skipped) and still receive the new model. A strategy without ``configure`` takes every candidate.
2. **What each is sent, and trains on:** the aggregator's model (through ``[federation]
   update_codec``), trained locally with ``proximal_mu``/2 ||w - w_start||^2 added to the loss.
3. **How results are aggregated.** The loop's steps (federation/scheme_steps.py) fold the models that
   reach an edge or the cloud into their sample-weighted FedAvg as they come (so a thousand vehicles'
   models are never held at once) and then ask the strategy for the aggregator's new model:

    new, memory = strategy.server_update(tier, node, current, average, memory)

``tier`` is "edge" or "cloud", ``node`` the edge's name or "cloud", ``current`` the model the node
sent out last, ``average`` the FedAvg of what came back, ``memory`` what the strategy kept at that
node from its previous update ({} at first; tensors only, so a run's checkpoint holds it and a
resume goes on with it). This is the server-optimizer form of Reddi et al., "Adaptive Federated
Optimization" (ICLR 2021): ``current - average`` is the pseudo-gradient.

Built in (each takes ``fraction``, 1.0 by default: the share of each aggregator's candidates that
take part, drawn with the step's seed, at least one, half rounded up; FedAvg's client fraction C of
McMahan et al., AISTATS 2017):

* ``fedavg`` (the paper): every candidate, and the average itself, bit for bit.
* ``fedavgm``: server momentum at the cloud (Hsu et al., "Measuring the Effects of Non-Identical
  Data Distribution for Federated Visual Classification", 2019): v <- momentum v + (current -
  average), new = current - server_lr v; the edges average. Options ``momentum`` (0.9) and
  ``server_lr`` (1.0); momentum 0 and server_lr 1 is FedAvg.
* ``fedprox`` (Li et al., "Federated Optimization in Heterogeneous Networks", MLSys 2020): FedAvg's
  aggregation, and each local training adds ``proximal_mu``/2 ||w - w_start||^2 to its loss, w_start
  being the model it started from. Option ``proximal_mu`` (0.01).

Your own: ``strategy = "package.module:Class"``; ``Class(**options)`` must have ``proximal_mu``
(a float, 0 for none) and ``server_update`` as above, and may have ``configure``. ``[federation] strategy_options`` gives the
options of any strategy (docs/beyond_paper.md).
"""

from __future__ import annotations

from typing import Mapping, Protocol, Sequence

import numpy as np
import torch

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.imports import import_class

State = Mapping[str, torch.Tensor]
BUILTIN = ("fedavg", "fedavgm", "fedprox")


class Strategy(Protocol):
    proximal_mu: float  # the local loss's proximal weight (FedProx); 0: plain local training

    def configure(self, tier: str, node: str, candidates: tuple[str, ...], seed: int) -> Sequence[str]:
        """Which of ``candidates`` take part in ``node``'s aggregation (optional: without it, all)."""
        ...

    def server_update(
        self, tier: str, node: str, current: State, average: State, memory: Mapping[str, torch.Tensor]
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """The node's new model from its last one and the FedAvg of what it received; and what to keep."""
        ...


class FedAvg:
    proximal_mu = 0.0

    def __init__(self, fraction: float = 1.0) -> None:
        if not 0 < fraction <= 1:
            raise CrchflError(f"federation.strategy_options: fraction must lie in (0, 1], got {fraction}")
        self.fraction = float(fraction)

    def configure(self, tier, node, candidates, seed):
        if self.fraction == 1.0:
            return candidates
        take = max(1, int(self.fraction * len(candidates) + 0.5))
        picked = np.random.default_rng(seed).choice(len(candidates), size=min(take, len(candidates)), replace=False)
        return tuple(candidates[i] for i in sorted(picked))

    def server_update(self, tier, node, current, average, memory):
        return dict(average), {}


class FedAvgM(FedAvg):
    def __init__(self, momentum: float = 0.9, server_lr: float = 1.0, fraction: float = 1.0) -> None:
        if not 0 <= momentum < 1 or not 0 < server_lr <= 10:
            raise CrchflError(f"federation.strategy_options: fedavgm needs 0 <= momentum < 1 and 0 < server_lr <= 10, "
                              f"got momentum {momentum}, server_lr {server_lr}")
        super().__init__(fraction)
        self.momentum, self.server_lr, self.proximal_mu = float(momentum), float(server_lr), 0.0

    def server_update(self, tier, node, current, average, memory):
        if tier != "cloud":  # the edges average; momentum at both tiers would compound
            return dict(average), {}
        new, velocity = {}, {}
        for key, now in current.items():
            if not now.is_floating_point():  # counters (BatchNorm's) are averaged, not moved
                new[key] = average[key]
                continue
            step = now.double() - average[key].double()
            if key in memory:
                step = step + self.momentum * memory[key].double()
            velocity[key] = step.to(now.dtype)
            new[key] = (now.double() - self.server_lr * step).to(now.dtype)
        return new, velocity


class FedProx(FedAvg):
    def __init__(self, proximal_mu: float = 0.01, fraction: float = 1.0) -> None:
        if not 0 <= proximal_mu <= 100:
            raise CrchflError(f"federation.strategy_options: fedprox needs 0 <= proximal_mu <= 100, got {proximal_mu}")
        super().__init__(fraction)
        self.proximal_mu = float(proximal_mu)


def strategy_from(name: str, options: Mapping[str, float]) -> Strategy:
    """The strategy ``name`` names (a built-in, or "package.module:Class") with ``options``; a CrchflError
    naming the key and the fix otherwise."""
    builtin = {"fedavg": FedAvg, "fedavgm": FedAvgM, "fedprox": FedProx}
    if name in builtin:
        cls = builtin[name]
    elif ":" in name:
        cls = import_class(name, "federation.strategy")
    else:
        raise CrchflError(
            f"federation.strategy: {name!r} is neither {', '.join(BUILTIN)} nor \"package.module:Class\""
        )
    try:
        strategy = cls(**options)
    except TypeError as exc:
        raise CrchflError(f"federation.strategy_options: {exc}; give the options {name!r} takes") from None
    mu = getattr(strategy, "proximal_mu", None)
    if not callable(getattr(strategy, "server_update", None)) or not isinstance(mu, (int, float)):
        raise CrchflError(f"federation.strategy: {name!r} needs a server_update method and a proximal_mu number "
                          "(learning/strategies.py)")
    if hasattr(strategy, "configure") and not callable(strategy.configure):
        raise CrchflError(f"federation.strategy: {name!r} has a configure that is not a method (learning/strategies.py)")
    return strategy


def taking_part(strategy: Strategy, tier: str, node: str, candidates: tuple[str, ...], seed: int) -> tuple[str, ...]:
    """The candidates ``strategy`` chooses for ``node``'s aggregation, in the candidates' order (all of them
    for a strategy without ``configure``); a CrchflError if it chose a vehicle that is no candidate."""
    configure = getattr(strategy, "configure", None)
    if configure is None or not candidates:
        return candidates
    chosen = set(configure(tier, node, candidates, seed))
    strangers = chosen - set(candidates)
    if strangers:
        raise CrchflError(f"federation.strategy: configure chose {sorted(map(str, strangers))} for {node}, which are "
                          f"not among its candidates {list(candidates)}")
    return tuple(v for v in candidates if v in chosen)
