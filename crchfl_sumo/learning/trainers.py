"""The federation loop's Trainer on top of training.py: in this process, or each vehicle as a backend task.

``federation.Trainer`` asks for an initial state, local training of several
vehicles and a test-set evaluation. ``TorchTrainer`` does them here;
``RayTrainer`` sends every vehicle's training and every evaluation to an
``Executor`` (backend.py) and returns bit-identical results. Both yield the
trained models one by one, in order, as they are ready: the loop folds each
into its FedAvg and drops it, so a step never holds every vehicle's model.

Evaluation: ``evaluation(state)`` gives the full test metrics
(evaluation.Evaluation: balanced accuracy, recall, confusion, steer and
pedal errors ...); ``evaluate(state)`` gives the same as the plain values the
loop writes into its metric lines. ``always_straight`` holds the
constant-straight baseline on the same test set.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterator

import torch

from crchfl_sumo.core.backend import Executor
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.evaluation import Evaluation, always_straight
from crchfl_sumo.learning.model import build_model, network
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.devices import configure_determinism, resolve_device, resolved_multi_vehicle
from crchfl_sumo.learning.training import evaluate, train_vehicle, train_vehicles, vehicle_seed


class TorchTrainer:
    """The loop's Trainer on top of training.py: DrivingModel state dicts, local training, test-set metrics."""

    def __init__(
        self, model_config: ModelConfig, config: TrainConfig, test: Samples, seed: int, proximal_mu: float = 0.0
    ) -> None:
        configure_determinism(config.deterministic)
        self.model_config, self.config, self.seed = model_config, config, seed
        self.proximal_mu = proximal_mu  # the strategy's local proximal term (FedProx; learning/strategies.py)
        self.device = resolve_device(config.device)
        self.test = test.to(self.device)
        self.always_straight = always_straight(test)  # {"accuracy", "balanced_accuracy"} on the test set
        self._eval_model = network(model_config).to(self.device)

    def initial_state(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().cpu().clone() for k, v in build_model(self.model_config, self.seed).state_dict().items()}

    def train(self, states, samples, epochs, seed, needed=None) -> Iterator[dict[str, torch.Tensor] | None]:
        """Each vehicle's new state, in order, trained when it is asked for: vehicle i with
        ``vehicle_seed(seed, i)``, as ``train_vehicles`` trains it (vmap: all at once). Sequentially, a
        vehicle not in ``needed`` (None: all) is not trained: None in its place (federation.Trainer)."""
        if resolved_multi_vehicle(self.config, self.model_config, self.device.type) == "vmap":
            if self.proximal_mu:
                raise CrchflError("a proximal term (strategy fedprox) trains vehicle by vehicle; set "
                                  "train.multi_vehicle = \"sequential\"")
            # all at once: one batch of every vehicle, whose numerics a smaller batch need not repeat to the bit
            new, _ = train_vehicles(list(states), list(samples), epochs, self.model_config, self.config, seed)
            return iter(new)
        wanted = wanted_indices(len(states), needed)
        return (
            train_vehicle(state, x, epochs, self.model_config, self.config, vehicle_seed(seed, i), self.proximal_mu)[0]
            if i in wanted else None
            for i, (state, x) in enumerate(zip(states, samples, strict=True))
        )

    def evaluation(self, state) -> Evaluation:
        """The full test-set metrics of ``state``."""
        self._eval_model.load_state_dict(state)
        return evaluate(self._eval_model, self.test, self.config)

    def evaluate(self, state) -> dict[str, Any]:
        """The loop's Trainer protocol: the test metrics as the metric line's values (Evaluation.record)."""
        record = self.evaluation(state).record()
        del record["samples"]  # the same every time; the run's summary states the test set's size
        return record


class RayTrainer(TorchTrainer):
    """TorchTrainer whose vehicles train, and whose models are evaluated, as tasks of ``executor``.

    Vehicle i of a call trains alone with ``vehicle_seed(seed, i)``, exactly as
    ``train_vehicles`` trains it sequentially, and every task uses the driver's
    number of torch threads, so the results are bit-identical to the local
    backend's. Samples, starting models and the test set go to the object
    store once each (a thousand vehicles starting from their edge's model
    share a few dozen copies, not a thousand).
    """

    def __init__(self, model_config, config, test, seed, executor: Executor, proximal_mu: float = 0.0) -> None:
        super().__init__(model_config, dataclasses.replace(config, device="cpu"), test, seed, proximal_mu)
        self.executor = executor
        self.threads = torch.get_num_threads()
        self._test_ref = executor.put(test)
        self._sample_refs: dict[int, tuple[Samples, Any]] = {}  # id -> (the object, kept alive; its handle)

    def _put_once(self, obj: Any, refs: dict, known: dict | None = None) -> Any:
        """``obj``'s handle, put once per distinct object (by identity) into ``refs``; ``known``: handles of an
        earlier call to reuse. ``refs`` keeps the object alive, so its id is not reused meanwhile."""
        key = id(obj)
        if key not in refs:
            refs[key] = (known or {}).get(key) or (obj, self.executor.put(obj))
        return refs[key][1]

    def train(self, states, samples, epochs, seed, needed=None) -> Iterator[dict[str, torch.Tensor] | None]:
        """As TorchTrainer's, sequentially: a task per vehicle in ``needed`` (None: all), None for the others."""
        wanted = wanted_indices(len(states), needed)
        sample_refs: dict[int, tuple[Samples, Any]] = {}
        state_refs: dict[int, tuple[Any, Any]] = {}
        args = []
        for i, (state, x) in enumerate(zip(states, samples, strict=True)):
            state_ref = self._put_once(state, state_refs) if i in wanted else None
            sample_ref = self._put_once(x, sample_refs, self._sample_refs)  # kept for a vehicle skipped now
            if i in wanted:
                args.append((state_ref, sample_ref, epochs, self.model_config, self.config, vehicle_seed(seed, i),
                             self.threads, self.proximal_mu))
        self._sample_refs = sample_refs  # handles of samples no longer trained on are released
        results = self.executor.imap(train_vehicle_task, args)
        return (next(results) if i in wanted else None for i in range(len(states)))

    def evaluation(self, state) -> Evaluation:
        args = (state, self._test_ref, self.model_config, self.config, self.threads)
        return self.executor.map(evaluate_task, [args])[0]


def wanted_indices(count: int, needed) -> frozenset[int]:
    """The vehicle indices a trainer trains: ``needed``, or all ``count`` with None."""
    return frozenset(range(count) if needed is None else needed)


def train_vehicle_task(state, samples, epochs, model_config, config, seed, threads, proximal_mu=0.0):
    """One vehicle's local training (a backend task): its new state."""
    torch.set_num_threads(threads)
    return train_vehicle(state, samples, epochs, model_config, config, seed, proximal_mu)[0]


def evaluate_task(state, test, model_config, config, threads) -> Evaluation:
    """The test-set metrics of ``state`` (a backend task)."""
    torch.set_num_threads(threads)
    configure_determinism(config.deterministic)
    model = network(model_config)
    model.load_state_dict(state)
    return evaluate(model, test, config)
