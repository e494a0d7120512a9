"""Asynchronous edges (``[federation] aggregation = "async"``): FedBuff on SUMO's clock.

A synchronous edge waits for all its vehicles (or its deadline). Here every vehicle works on its own:
it trains on the model it holds (at its own speed, paused while off: links/fleet.py) and uploads it
over its link; an edge aggregates as soon as ``async_buffer`` updates have arrived (at most as many
as it has vehicles), sends the new model back to the vehicles whose updates it used, and those start
again. The others go on with the model they hold. A vehicle that leaves coverage simply arrives later
(its upload stalls), or its upload fails; then it trains again from the model it holds.

The edge's update (learning.aggregate.buffered_update, Nguyen et al., "Federated Learning with
Buffered Asynchronous Aggregation", AISTATS 2022):

    w_e <- w_e + sum_i n_i s(tau_i) (w_i - b_i) / sum_i n_i,    s(tau) = (1 + tau) ** -staleness_exponent

with b_i the model vehicle i trained from, n_i its samples, and tau_i the staleness: how often the
edge's model changed (its aggregations and the cloud's releases) between the release of b_i to the
vehicle and the update's arrival. Fresh updates from every vehicle give FedAvg.

The cloud aggregates after every ``cloud_interval`` x (edges with vehicles) edge aggregations: every
such edge sends its model up over the wireline, the cloud averages them by the samples of their
vehicles and sends the result back to the edges. The vehicles get it with their edge's next model.

One step of the loop is one event, the earliest of: an edge's buffer filling (an edge aggregation,
perhaps with a cloud aggregation after it) or a failed upload (its bytes charged, the vehicle a
straggler). Each vehicle's next upload is worked out from when it holds its model, so the events
depend on the clock only; the vehicles train last, as in the synchronous loop. Transfers that are
under way when the budget runs out are never charged.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from crchfl_sumo.accounting.ledger import Ledger
from crchfl_sumo.accounting.schedules import CLOUD, Transfer
from crchfl_sumo.federation.services import (
    RelayedTransfer,
    StepServices,
    charge_transfers,
    count_transfer,
    wireless_event,
    wireline_event,
)
from crchfl_sumo.federation.state import FederationState
from crchfl_sumo.learning.aggregate import buffered_update, fedavg, staleness_factor
from crchfl_sumo.links.clock import WirelessOutcome


@dataclass(frozen=True)
class Attempt:
    """A vehicle's next update: trained from ``state.ready_s`` on, uploaded; where and when it arrives."""

    vehicle: str
    out: WirelessOutcome
    arrival_s: float  # at ``receiver`` (after forwarding); the failure time if the upload failed
    receiver: str  # the edge the update reaches
    relays: tuple[RelayedTransfer, ...]


class AsyncEdgeStep:
    """One event of asynchronous edges: the training step of CRCHFL and HFL with ``aggregation = "async"``
    (federation/scheme_steps.py: the step protocol; stage I as with synchronous edges)."""

    def __init__(self) -> None:
        # vehicle -> (what its next attempt depends on, the attempt): most vehicles have not moved on since the
        # last step, and their attempt (a transfer integrated over the clock) is the same
        self._attempts: dict[str, tuple[tuple, Attempt]] = {}

    def run(self, services: StepServices, state: FederationState, ledger: Ledger) -> None:
        samples = services.training_data(state, ledger)
        attempts = [self._attempt(services, state, v, len(samples[v])) for v in services.setup.vehicles]
        failure = min((a for a in attempts if not a.out.ok), key=lambda a: a.arrival_s, default=None)
        edge, buffer = self._first_full_buffer(services, state, attempts)
        if failure is not None and (edge is None or failure.arrival_s <= buffer[-1].arrival_s):
            self._failed_upload(services, state, ledger, failure)
        elif edge is not None:
            self._aggregate(services, state, ledger, edge, buffer, samples)
        else:  # no upload can arrive and none failed: nothing will ever happen
            state.stop_reason = "no_progress"

    # -- events

    def _attempt(self, services: StepServices, state: FederationState, vehicle: str, samples: int) -> Attempt:
        key = (state.ready_s[vehicle], state.member[vehicle], samples)
        known = self._attempts.get(vehicle)
        if known is None or known[0] != key:
            self._attempts[vehicle] = key, self._new_attempt(services, state, vehicle, samples)
        return self._attempts[vehicle][1]

    def _new_attempt(self, services: StepServices, state: FederationState, vehicle: str, samples: int) -> Attempt:
        edge = state.member[vehicle]
        size = services.setup.sizes.upload_bytes
        trained_s = services.trained_s(vehicle, state.ready_s[vehicle], samples, services.setup.hyper.edge_interval)
        out = services.upload(vehicle, edge, trained_s, size, math.inf)
        relays: list[RelayedTransfer] = []
        if not out.ok:
            return Attempt(vehicle, out, out.end_s, edge, ())
        receiver = services.setup.edges[out.site] if services.config.handover_policy == "new_edge" else edge
        arrival_s = services.forward(out, receiver, size, "model", "II", relays)
        return Attempt(vehicle, out, arrival_s, receiver, tuple(relays))

    def _first_full_buffer(self, services: StepServices, state: FederationState, attempts: list[Attempt]):
        """The edge whose buffer fills first and the updates in it (in arrival order); (None, []) if none fills."""
        members = Counter(state.member.values())
        best = None, []
        for e in services.setup.edges:
            arriving = sorted((a for a in attempts if a.out.ok and a.receiver == e), key=lambda a: a.arrival_s)
            size = min(services.config.async_buffer, max(members[e], 1))
            if len(arriving) >= size and (best[0] is None or arriving[size - 1].arrival_s < best[1][-1].arrival_s):
                best = e, arriving[:size]
        return best

    def _failed_upload(self, services: StepServices, state: FederationState, ledger: Ledger, attempt: Attempt) -> None:
        """A failed upload: charged, its vehicle a straggler that trains again from the model it holds (from the
        failure, and a clock step after its last try at the soonest)."""
        v, edge = attempt.vehicle, state.member[attempt.vehicle]
        events = {(v, edge, "uplink"): wireless_event(attempt.out)}
        count_transfer(state, "uploads", False)
        services.straggler(state, v, "II", attempt.out.reason, attempt.out.end_s)
        schedule = (Transfer("wireless", "uplink", "II", v, edge, "model", services.setup.sizes.upload_bytes),)
        if not charge_transfers(ledger, schedule, events, services.setup.rule, state.cloud_rounds + 1, state):
            state.stop_reason = "budget"
            return
        # it tries again at the failure, but at least one clock step on: an upload that fails at once (no
        # coverage under "miss", no compute time) must not fail again at the same moment for ever
        state.ready_s = {**state.ready_s, v: max(attempt.out.end_s, state.ready_s[v] + services.clock.step_s)}

    def _aggregate(
        self, services: StepServices, state: FederationState, ledger: Ledger, edge: str, buffer: list[Attempt], samples
    ) -> None:
        """``edge`` aggregates the updates of ``buffer`` when the last arrives, and sends its model back to them;
        the cloud aggregates when its turn has come."""
        setup, sizes = services.setup, services.setup.sizes
        at_s = buffer[-1].arrival_s
        order = {v: i for i, v in enumerate(setup.vehicles)}
        buffer = sorted(buffer, key=lambda a: order[a.vehicle])  # the sums in the vehicles' order: reproducible
        vehicles = [a.vehicle for a in buffer]
        events, relays = {}, []
        for a in buffer:
            events[(a.vehicle, edge, "uplink")] = wireless_event(a.out)
            count_transfer(state, "uploads", True)
            relays.extend(a.relays)
        ready = dict(state.ready_s)
        delivered = set(services.send_down(state, edge, vehicles, at_s, "II", events, ready, relays))
        history = state.edge_history.get(edge, [])
        staleness = {v: sum(t > state.base_s.get(v, -math.inf) for t in history) for v in vehicles}
        factors = {v: staleness_factor(staleness[v], services.config.staleness_exponent) for v in vehicles}
        counts = {v: len(samples[v]) for v in vehicles}
        seed = int(np.random.SeedSequence([services.config.seed, 1, state.steps]).generate_state(1)[0])
        starts = [state.vehicle_models[v] for v in vehicles]
        trained = list(services.trainer.train(starts, [samples[v] for v in vehicles], setup.hyper.edge_interval, seed))
        edge_model = buffered_update(
            state.edge_models[edge],
            [(start, model, counts[v], factors[v]) for v, start, model in zip(vehicles, starts, trained, strict=True)],
        )
        schedule = tuple(Transfer("wireless", "uplink", "II", v, edge, "model", sizes.upload_bytes) for v in vehicles)
        schedule += tuple(Transfer("wireless", "downlink", "II", edge, v, "model", sizes.model_bytes) for v in vehicles)
        next_round = state.cloud_rounds + 1
        if not charge_transfers(ledger, schedule, events, setup.rule, next_round, state, relays, setup.edges):
            state.stop_reason = "budget"
            return
        models = dict(state.vehicle_models)
        for v, model in zip(vehicles, trained):  # a vehicle whose download failed goes on from its own model
            models[v] = edge_model if v in delivered else model
        state.vehicle_models, state.ready_s = models, ready
        state.member = {**state.member, **dict.fromkeys(vehicles, edge)}
        state.base_s = {**state.base_s, **dict.fromkeys(vehicles, at_s)}
        state.edge_models = {**state.edge_models, edge: edge_model}
        state.edge_history = {**state.edge_history, edge: [*history, at_s]}
        state.edge_weights = {**state.edge_weights, edge: float(sum(counts.values()))}
        state.edge_aggregations += 1
        state.tau += 1
        services.count_training(state, counts, setup.hyper.edge_interval)
        edge_metrics = None
        if services.config.evaluate_every_edge:
            edge_metrics = services.evaluate_edges({edge: edge_model}, {edge: 1.0}, [edge])
        services.line(state, ledger, "II", at_s, edge_metrics, received={edge: len(vehicles)},
                      samples=sum(counts.values()), staleness=staleness)
        active = [e for e in setup.edges if any(m == e for m in state.member.values())]
        if state.tau >= setup.hyper.cloud_interval * len(active):
            self._cloud_round(services, state, ledger, active, at_s)

    def _cloud_round(
        self, services: StepServices, state: FederationState, ledger: Ledger, edges: list[str], at_s: float
    ) -> None:
        """Every edge with vehicles sends its model up; the cloud averages them and sends the result back."""
        setup = services.setup
        weights = {e: float(sum(setup.count(v) for v in setup.vehicles if state.member[v] == e)) for e in edges}
        events = {}
        for e in edges:
            events[(e, CLOUD, "uplink")] = wireline_event(at_s, setup.sizes.model_bytes, setup.wireline)
        cloud_s = max(events[(e, CLOUD, "uplink")].end_s for e in edges)
        for e in edges:
            events[(CLOUD, e, "downlink")] = wireline_event(cloud_s, setup.sizes.model_bytes, setup.wireline)
        size = setup.sizes.model_bytes
        schedule = tuple(Transfer("wireline", "uplink", "III", e, CLOUD, "model", size) for e in edges)
        schedule += tuple(Transfer("wireline", "downlink", "III", CLOUD, e, "model", size) for e in edges)
        if not charge_transfers(ledger, schedule, events, setup.rule, state.cloud_rounds + 1, state):
            state.stop_reason = "budget"
            return
        cloud_model = fedavg([(state.edge_models[e], weights[e]) for e in edges])
        state.edge_models = {**state.edge_models, **dict.fromkeys(edges, cloud_model)}
        state.edge_weights = {**state.edge_weights, **weights}
        released = {e: [*state.edge_history.get(e, []), events[(CLOUD, e, "downlink")].end_s] for e in edges}
        state.edge_history = {**state.edge_history, **released}
        state.cloud_model = cloud_model
        state.cloud_rounds += 1
        state.tau = 0
        services.evaluate_cloud(state, ledger, "III", cloud_s)
