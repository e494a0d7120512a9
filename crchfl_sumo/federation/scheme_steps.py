"""The schemes' steps: each kind of step of the loop as an object, and each scheme as the sequence of them.

CRCHFL, HFL and SFL differ only in the steps they take. The loop (federation/loop.py) asks the run's
sequence of steps which comes next and runs it::

    step = steps.next_step(state)
    step.run(services, state, ledger)

**The step protocol** (``SchemeStep``): ``run(services, state, ledger)`` is one step of the scheme on the
clock. It

1. decides who takes part: which vehicles train (``[federation] selection``, the strategy's ``configure``
   through ``services.taking_part``) and which edges aggregate;
2. works out what each is sent and when it arrives, before anyone trains (the times do not depend on what
   the models learn): ``services.upload``, ``gather_uploads``, ``forward``, ``send_down``, each recorded as
   a ``TransferEvent`` (stragglers through ``services.straggler``);
3. trains and aggregates: ``services.train_and_average`` (FedAvg of what arrived at each aggregator, folded
   in as the models come), then the strategy's ``services.server_update``;
4. charges its transfers (``charge_transfers`` with the schedule of its actual topology); when one does not
   fit it sets ``state.stop_reason = "budget"`` and returns, the models and times left as they were;
5. writes its outcome into ``state`` (models, times, counters) and its metric lines (``services.line``,
   ``services.evaluate_cloud``).

``state`` is the loop's copy for this step; the loop checks the stopping rules first and, after the
step, appends the ledger's records and counts the step. A step keeps nothing of its own that a resume
would need: whatever must outlive a step lives in ``state`` (a cache of what ``state`` determines, as
``AsyncEdgeStep``'s, may live on the step). ``services`` (federation/services.py ``StepServices``) is
shared by every step: the clock's transfers, the vehicles' data, training, evaluation.

**A scheme's sequence** (``SchemeSteps``, built by ``steps_for`` from ``core.schemes.SHAPES`` and
``[federation] aggregation``, never from the scheme's name): the pretraining step while
``state.stage_one_done`` is False (CRCHFL with ``pretrain_batch`` > 0), then its training step every step:

    crchfl: PretrainingStep, then HierarchicalStep (aggregation = "async": AsyncEdgeStep)
    hfl:    HierarchicalStep (aggregation = "async": AsyncEdgeStep)
    sfl:    FlatRoundStep

Any object with ``next_step(state)`` is a sequence (``StepSequence``): ``[federation] scheme_steps =
"package.module:Class"`` names one, ``Class(builtin)`` given the scheme's ``SchemeSteps``.
docs/beyond_paper.md ("Scheme steps") has the protocol for readers; docs/federation.md maps Algorithm 1
onto these steps line by line.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Mapping, Protocol

import numpy as np

from crchfl_sumo.accounting.ledger import Ledger
from crchfl_sumo.accounting.schedules import CLOUD, Topology, stage_one_schedule
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.imports import import_class
from crchfl_sumo.core.schemes import SHAPES
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation import selection
from crchfl_sumo.federation.async_edges import AsyncEdgeStep
from crchfl_sumo.federation.services import (
    EPS_S,
    RelayedTransfer,
    StepServices,
    TransferEvent,
    charge_transfers,
    count_transfer,
    wireless_event,
    wireline_event,
)
from crchfl_sumo.federation.settings import SFL_LINK, FederationConfig
from crchfl_sumo.federation.state import FederationState
from crchfl_sumo.learning.aggregate import fedavg
from crchfl_sumo.links.clock import WirelessOutcome
from crchfl_sumo.planning.problem import split_pretrain_batch

log = logging.getLogger(__name__)


class SchemeStep(Protocol):
    """One kind of step of a scheme (the module's docstring: the protocol)."""

    def run(self, services: StepServices, state: FederationState, ledger: Ledger) -> None:
        """Advance ``state`` (the loop's copy) by one step, charging ``ledger``."""
        ...


class PretrainingStep:
    """Stage I (CRCHFL with ``pretrain_batch`` > 0): each vehicle uploads a fixed, seeded subset of its
    samples to its edge, the edges relay them to the cloud, the cloud pretrains ``pretrain_epochs``
    epochs and releases the model to every edge and vehicle. Its transfers are charged to cloud round 0."""

    def run(self, services: StepServices, state: FederationState, ledger: Ledger) -> None:
        setup, cfg, sizes = services.setup, services.config, services.setup.sizes
        counts = {v: setup.count(v) for v in setup.vehicles}
        shares = split_pretrain_batch(setup.hyper.pretrain_batch, counts)
        member = dict(state.member)
        events: dict[tuple[str, str, str], TransferEvent] = {}
        relays: list[RelayedTransfer] = []
        uploaded: dict[str, Samples] = {}
        arrival_s: dict[str, float] = {}  # at the vehicle's edge (after forwarding)
        for i, v in enumerate(setup.vehicles):
            if not shares[v]:
                continue
            edge = state.member[v]
            window_end = state.open_s[edge] + cfg.deadline_s
            out = services.upload(v, edge, state.ready_s[v], shares[v] * sizes.sample_bytes, window_end)
            if out is None:
                services.straggler(state, v, "I", "no time to upload before the deadline", window_end)
                continue
            if out.ok and cfg.handover_policy == "new_edge":
                member[v] = setup.edges[out.site]
            events[(v, member[v], "uplink")] = wireless_event(out)
            count_transfer(state, "uploads", out.ok)
            arrival_s[v] = services.forward(out, member[v], shares[v] * sizes.sample_bytes, "samples", "I", relays)
            if out.ok and arrival_s[v] > window_end + EPS_S:
                events[(v, member[v], "uplink")] = dataclasses.replace(events[(v, member[v], "uplink")], wasted=True)
                services.straggler(state, v, "I", "deadline", window_end)
            elif out.ok:
                # the fixed uploaded subset: a seeded choice of the vehicle's samples
                rng = np.random.default_rng([cfg.seed, 2, i])
                uploaded[v] = setup.samples[v].subset(np.sort(rng.permutation(counts[v])[: shares[v]]))
            else:
                services.straggler(state, v, "I", out.reason, out.end_s)
        topology = services.topology(member)
        relay_end = {}
        for e, vehicles in topology.active():
            ends = [min(arrival_s[v], state.open_s[e] + cfg.deadline_s) for v in vehicles if v in arrival_s]
            if ends:
                n = sum(len(uploaded[v]) for v in vehicles if v in uploaded)
                events[(e, CLOUD, "uplink")] = wireline_event(max(ends), n * sizes.sample_bytes, setup.wireline)
                relay_end[e] = events[(e, CLOUD, "uplink")].end_s
        start_s = max(relay_end.values(), default=max(state.ready_s.values()))
        n = sum(len(s) for s in uploaded.values())
        model = state.cloud_model
        if uploaded:
            parts = [uploaded[v] for v in setup.vehicles if v in uploaded]
            seed = int(np.random.SeedSequence([cfg.seed, 3]).generate_state(1)[0])
            [model] = services.trainer.train([state.cloud_model], [Samples.concat(parts)], cfg.pretrain_epochs, seed)
            model = services.sent(model, state.cloud_model)  # released to every edge and vehicle
        pretrained_s = start_s + cfg.pretrain_epochs * n * cfg.compute_s_per_sample
        # release: cloud -> every edge (wireline), edge -> its vehicles (wireless)
        ready, models, open_s = dict(state.ready_s), dict(state.vehicle_models), dict(state.open_s)
        for e, vehicles in topology.active():
            ev = wireline_event(pretrained_s, sizes.model_bytes, setup.wireline)
            events[(CLOUD, e, "downlink")] = ev
            open_s[e] = ev.end_s
            delivered = services.send_down(state, e, vehicles, ev.end_s, "I", events, ready, relays)
            models.update(dict.fromkeys(delivered, model))
        received = {v: shares[v] for v in setup.vehicles}
        schedule = stage_one_schedule(setup.rule, cfg.scheme, topology, received, sizes)
        if not charge_transfers(ledger, schedule, events, setup.rule, 0, state, relays, setup.edges):
            state.stop_reason = "budget"
            return
        state.stage_one_done = True
        state.cloud_model = model
        state.edge_models = {e: model for e in setup.edges}
        state.vehicle_models, state.ready_s, state.open_s, state.member = models, ready, open_s, member
        services.evaluate_cloud(state, ledger, "I", pretrained_s, pretrain_samples=n)

class HierarchicalStep:
    """Stages II and III (CRCHFL, HFL): every vehicle (with ``selection = "skip_leaving"``: every vehicle but
    those predicted to leave their cell before it ends, federation/selection.py; of those, whom the
    strategy chooses) trains ``edge_interval`` local epochs and uploads its model; each edge averages what
    it received (FedAvg, weights |T_nk|) and, unless a cloud aggregation follows, sends the result down.
    After ``cloud_interval`` edge aggregations the edges send their models to the cloud, which averages
    them (weights: the samples behind each edge model) and releases the global model to every edge and
    vehicle."""

    def run(self, services: StepServices, state: FederationState, ledger: Ledger) -> None:
        """Stage II: one edge aggregation; when it is the ``cloud_interval``-th, stage III follows.

        The step's times do not depend on what the models learn (training takes
        its simulated compute time), so its transfers are worked out first and
        the vehicles train last, each model folded into its edge's FedAvg as it
        comes (``services.train_and_average``).
        """
        setup, cfg, sizes = services.setup, services.config, services.setup.sizes
        followed = state.tau + 1 == setup.hyper.cloud_interval
        samples = services.training_data(state, ledger)
        picked = services.taking_part(state, self._select(services, state, samples))
        counts = {v: len(samples[v]) for v in picked}  # |T_nk| of the vehicles that train
        skipped = [v for v in setup.vehicles if v not in picked]
        events: dict[tuple[str, str, str], TransferEvent] = {}
        relays: list[RelayedTransfer] = []
        uploads, member = self._vehicle_uploads(services, state, counts)
        topology = services.topology(member)
        agg_s, received_by = self._edge_arrivals(services, state, topology, uploads, events, relays)
        for e in agg_s:
            # the edge -> cloud upload: real when a cloud aggregation follows; the paper rule charges it every time
            events[(e, CLOUD, "uplink")] = wireline_event(agg_s[e], sizes.model_bytes, setup.wireline)
        cloud_s, release_s = None, agg_s
        if followed:
            cloud_s = max(events[(e, CLOUD, "uplink")].end_s for e in agg_s)
            release_s = {}
            for e in agg_s:
                events[(CLOUD, e, "downlink")] = wireline_event(cloud_s, sizes.model_bytes, setup.wireline)
                release_s[e] = events[(CLOUD, e, "downlink")].end_s
        stage = "III" if followed else "II"
        ready, open_s, delivered = self._release(services, state, topology, release_s, events, stage, relays)
        averages, kept = services.train_and_average(
            state, setup.hyper.edge_interval, {v: samples[v] for v in picked}, received_by, set(counts) - delivered
        )
        edge_models, edge_weights = dict(state.edge_models), dict(state.edge_weights)
        for e, average in averages.items():  # an edge that received no model keeps its previous one
            average = services.server_update(state, "edge", e, state.edge_models[e], average)
            edge_models[e] = services.sent(average, state.cloud_model)  # up to the cloud, or down to its vehicles
            edge_weights[e] = float(sum(counts[v] for v in received_by[e]))
        edge_metrics = services.evaluate_edges(edge_models, edge_weights, agg_s) if cfg.evaluate_every_edge else None
        cloud_model = state.cloud_model
        if followed:
            fresh = [(edge_models[e], edge_weights[e]) for e in agg_s if received_by[e]]
            if fresh:
                average = services.server_update(state, "cloud", CLOUD, state.cloud_model, fedavg(fresh))
                cloud_model = services.sent(average, state.cloud_model)
            edge_models.update(dict.fromkeys(agg_s, cloud_model))
        models = {**state.vehicle_models, **kept}  # a skipped vehicle, or one whose download failed, keeps its own
        for e, vehicles in topology.active():
            models.update(dict.fromkeys((v for v in vehicles if v in delivered), edge_models[e]))
        next_round = state.cloud_rounds + 1
        schedule = services.step_schedule(topology, followed)
        if not charge_transfers(ledger, schedule, events, setup.rule, next_round, state, relays, setup.edges):
            state.stop_reason = "budget"
            return
        state.vehicle_models, state.ready_s, state.open_s, state.member = models, ready, open_s, member
        state.edge_models, state.edge_weights = edge_models, edge_weights
        services.count_training(state, counts, setup.hyper.edge_interval)
        state.edge_aggregations += 1
        state.tau += 1
        state.skipped += len(skipped)
        received = {e: len(vs) for e, vs in received_by.items()}
        extra = {"skipped": skipped} if skipped or cfg.selection != "all" else {}
        t_s = max(agg_s.values())
        services.line(state, ledger, "II", t_s, edge_metrics, received=received, samples=sum(counts.values()), **extra)
        if followed:
            state.cloud_model = cloud_model
            state.cloud_rounds = next_round
            state.tau = 0
            services.evaluate_cloud(state, ledger, "III", cloud_s)

    def _vehicle_uploads(
        self, services: StepServices, state: FederationState, counts: Mapping[str, int]
    ) -> tuple[dict[str, WirelessOutcome | None], dict[str, str]]:
        """The upload of each vehicle in ``counts`` (those that trained) after its training, and the
        membership after them (``new_edge`` moves vehicles)."""
        setup, cfg = services.setup, services.config
        member = dict(state.member)
        uploads: dict[str, WirelessOutcome | None] = {}
        for v in counts:
            edge = state.member[v]
            start_s = services.trained_s(v, state.ready_s[v], counts[v], setup.hyper.edge_interval)
            out = services.upload(v, edge, start_s, setup.sizes.upload_bytes, state.open_s[edge] + cfg.deadline_s)
            uploads[v] = out
            if out is not None and out.ok and cfg.handover_policy == "new_edge":
                member[v] = setup.edges[out.site]
        return uploads, member

    def _edge_arrivals(self, services: StepServices, state, topology, uploads, events, relays):
        """When each edge aggregates (once its members' uploads ended; at the latest, its deadline) and
        whose models it holds then.

        Returns (aggregation time, vehicles whose model arrived) per edge; records the uploads in
        ``events`` and the stragglers in ``state``.
        """
        agg_s: dict[str, float] = {}
        received_by: dict[str, list[str]] = {}
        for e, vehicles in topology.active():
            ends, received_by[e] = services.gather_uploads(
                state,
                {v: uploads[v] for v in vehicles if v in uploads},
                e,
                "II",
                lambda v: state.open_s[state.member[v]] + services.config.deadline_s,
                events,
                relays,
            )
            agg_s[e] = max(ends, default=state.open_s[e])  # no member trained: nothing to wait for
        return agg_s, received_by

    def _release(self, services: StepServices, state, topology, release_s, events, stage, relays):
        """Each edge sends its model to its vehicles from ``release_s[edge]`` on.

        Returns the times the vehicles hold their models, the edges' new window openings, and the
        vehicles whose download arrived (the others keep their own model).
        """
        ready, open_s, delivered = dict(state.ready_s), dict(state.open_s), set()
        for e, vehicles in topology.active():
            open_s[e] = release_s[e]
            delivered.update(services.send_down(state, e, vehicles, release_s[e], stage, events, ready, relays))
        return ready, open_s, delivered

    def _select(
        self, services: StepServices, state: FederationState, samples: Mapping[str, Samples]
    ) -> tuple[str, ...]:
        """The vehicles that train in this edge aggregation (``federation.selection``; federation/selection.py)."""
        cfg, setup = services.config, services.setup
        if cfg.selection == "all":
            return tuple(samples)
        epochs = setup.hyper.edge_interval
        own = cfg.handover_policy in ("wait", "miss")  # their uploads run only over the vehicle's own edge
        needed, residence = {}, {}
        for v in samples:
            t_s = state.ready_s[v]
            rate_bps = selection.recent_rate_bps(services.clock, v, t_s)
            train_s = services.trained_s(v, t_s, len(samples[v]), epochs) - t_s
            needed[v] = selection.needed_s(train_s, setup.sizes.upload_bytes, rate_bps)
            site = setup.edges.index(state.member[v]) if own else None
            residence[v] = selection.residence_on_clock(services.clock, v, t_s, setup.coverage, site)
        picked = selection.chosen(needed, residence)
        for v in samples:
            if v not in picked:
                log.info("step %d: %s skipped: %.1f s left in its cell, %.1f s needed", state.steps, v,
                         residence[v], needed[v])
        return picked

class FlatRoundStep:
    """One round of SFL: no edge tier. Vehicles train ``edge_interval`` local epochs and upload straight to
    the cloud over the macro link; one cloud aggregation per round, released to every vehicle."""

    def run(self, services: StepServices, state: FederationState, ledger: Ledger) -> None:
        setup, cfg, sizes = services.setup, services.config, services.setup.sizes
        epochs = setup.hyper.edge_interval
        samples = services.training_data(state, ledger)
        picked = services.taking_part(state, tuple(samples))
        counts = {v: len(samples[v]) for v in picked}
        skipped = [v for v in setup.vehicles if v not in picked]
        window_end = state.open_s[CLOUD] + cfg.deadline_s
        events: dict[tuple[str, str, str], TransferEvent] = {}
        relays: list[RelayedTransfer] = []
        uploads = {
            v: services.upload(
                v, None, services.trained_s(v, state.ready_s[v], counts[v], epochs), sizes.upload_bytes, window_end
            )
            for v in picked
        }
        ends, received = services.gather_uploads(state, uploads, CLOUD, "III", lambda v: window_end, events, relays)
        cloud_s = max(ends)
        ready = dict(state.ready_s)
        delivered = set(services.send_down(state, CLOUD, setup.vehicles, cloud_s, "III", events, ready, relays))
        # the times first, the training last (as in HierarchicalStep)
        averages, kept = services.train_and_average(
            state, epochs, {v: samples[v] for v in picked}, {CLOUD: received}, set(picked) - delivered
        )
        cloud_model = state.cloud_model
        if CLOUD in averages:
            average = services.server_update(state, "cloud", CLOUD, state.cloud_model, averages[CLOUD])
            cloud_model = services.sent(average, state.cloud_model)
        # a vehicle whose download failed keeps what it trained, or, if it sat the round out, what it held
        models = {v: cloud_model if v in delivered else kept.get(v, state.vehicle_models[v]) for v in setup.vehicles}
        topology = Topology((SFL_LINK,), (setup.vehicles,))
        next_round = state.cloud_rounds + 1
        schedule = services.step_schedule(topology, followed=True)
        if not charge_transfers(ledger, schedule, events, setup.rule, next_round, state):
            state.stop_reason = "budget"
            return
        state.vehicle_models, state.ready_s = models, ready
        state.open_s = {CLOUD: cloud_s}
        services.count_training(state, counts, epochs)
        state.skipped += len(skipped)
        state.cloud_model = cloud_model
        state.cloud_rounds = next_round
        extra = {"skipped": skipped} if skipped else {}
        services.evaluate_cloud(state, ledger, "III", cloud_s, received=len(received), samples=sum(counts.values()),
                                **extra)


class StepSequence(Protocol):
    """A scheme as its steps: which step comes next (``SchemeSteps``, or yours: ``[federation] scheme_steps``)."""

    def next_step(self, state: FederationState) -> SchemeStep: ...


@dataclass(frozen=True)
class SchemeSteps:
    """A built-in scheme as its steps: ``pretraining`` (None: the scheme has no stage I) until
    ``state.stage_one_done``, then ``training`` every step."""

    pretraining: SchemeStep | None
    training: SchemeStep

    def next_step(self, state: FederationState) -> SchemeStep:
        if state.stage_one_done or self.pretraining is None:
            return self.training
        return self.pretraining


def steps_for(config: FederationConfig) -> StepSequence:
    """The steps of ``config``'s scheme, from its shape (core/schemes.py) and ``aggregation``, new objects each
    call (``AsyncEdgeStep`` caches per run); with ``scheme_steps``, that class given those."""
    shape = SHAPES[config.scheme]
    if not shape.edge_tier:
        training: SchemeStep = FlatRoundStep()
    elif config.aggregation == "async":
        training = AsyncEdgeStep()
    else:
        training = HierarchicalStep()
    builtin = SchemeSteps(PretrainingStep() if shape.pretraining else None, training)
    if not config.scheme_steps:
        return builtin
    cls = import_class(config.scheme_steps, "federation.scheme_steps")
    try:
        steps = cls(builtin)
    except TypeError as exc:
        raise CrchflError(f"federation.scheme_steps: {exc}; {config.scheme_steps!r} must take the built-in "
                          "SchemeSteps") from None
    if not callable(getattr(steps, "next_step", None)):
        raise CrchflError(f"federation.scheme_steps: {config.scheme_steps!r} has no next_step(state); give it one "
                          "(federation/scheme_steps.py)")
    return steps
