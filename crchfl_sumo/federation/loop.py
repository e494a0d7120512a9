"""Algorithm 1 of the paper on SUMO's clock: CRCHFL, HFL and SFL as configurations of one loop.

The loop (docs/federation.md maps it line by line):

* stage I (CRCHFL with ``pretrain_batch`` > 0): each vehicle uploads a fixed,
  seeded subset of its samples to its edge, the edges relay them to the
  cloud, the cloud pretrains and releases the model to every edge and
  vehicle;
* stage II: every vehicle trains ``edge_interval`` local epochs and uploads
  its model (with ``selection = "skip_leaving"``: every vehicle but those
  predicted to leave their cell before that ends, federation/selection.py);
  each edge averages what it received (FedAvg, weights |T_nk|)
  and, unless a cloud aggregation follows, sends the result down;
* stage III: after ``cloud_interval`` edge aggregations the edges send their
  models to the cloud, which averages them (weights: the samples behind each
  edge model) and releases the global model to every edge and vehicle.

SFL has no edge tier: vehicles upload straight to the cloud over the macro
link, one cloud aggregation per round (``cloud_interval`` = 1). HFL is the
hierarchy without stage I and without the optimizer.

Time: local training takes ``compute_s_per_sample`` x samples x epochs of
simulated time; every wireless transfer runs over the vehicle's link on the
clock (links/clock.py), every wireline one takes latency + size / rate. An
aggregation waits for its vehicles' uploads until ``deadline_s`` after its
window opened; a model that has not arrived by then is a straggler's,
recorded and left out of that FedAvg (weights renormalised over the rest).

Bytes: every step's transfers come from the schedule functions
(``schedules.stage_one_schedule``, ``edge_aggregation_schedule``,
``cloud_aggregation_schedule``) for the step's actual topology, and are
charged with their simulated start and end times. Training stops when the
rest of the budget cannot carry one more model transfer; a step whose
transfers do not all fit is not counted and its models are dropped (its
charged bytes stay spent, as ``ledger.replay`` does).

The loop's whole memory is a ``FederationState`` (models, times, counters;
the ledger records and metric lines it appends to are history it never reads
back), so a checkpoint is the state and a resume continues from it. Mobility
and training are injected (a ``Clock`` and a ``Trainer``), so the loop runs
with scripted tracks and tiny models in tests.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, Collection, Mapping, Sequence

import numpy as np

from crchfl_sumo.accounting.ledger import Ledger
from crchfl_sumo.accounting.schedules import (
    CLOUD,
    Topology,
    Transfer,
    cloud_aggregation_schedule,
    edge_aggregation_schedule,
    schedule_bytes,
    stage_one_schedule,
)
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation import selection
from crchfl_sumo.federation.settings import SFL_LINK
from crchfl_sumo.federation.state import FederationState, Labeller, LoopInputs, Trainer
from crchfl_sumo.learning import codecs
from crchfl_sumo.learning.aggregate import RunningAverage, fedavg
from crchfl_sumo.learning.model import State
from crchfl_sumo.learning.strategies import taking_part
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.clock import Clock, Relay, WirelessOutcome, edge_download, wireless_transfer, with_deadline
from crchfl_sumo.links.fleet import AvailableClock
from crchfl_sumo.links.transfer import wireline_transfer_time_s
from crchfl_sumo.planning.problem import split_pretrain_batch

log = logging.getLogger(__name__)

_EPS_S = 1e-9  # float slack when comparing simulated times

# The test metrics that an edge evaluation averages over edges (the rest: per-class counts and rates).
SCALAR_METRICS = ("loss", "accuracy", "balanced_accuracy", "steer_error", "throttle_error", "brake_error")


# ------------------------------------------------------------------ one step


@dataclass(frozen=True)
class TransferEvent:
    """A simulated transfer: who, when, how much arrived; ``wasted``: its payload was not used
    (the transfer failed, or arrived after the deadline)."""

    start_s: float
    end_s: float
    ok: bool
    sent_bytes: float
    wasted: bool = False


def wireline_event(start_s: float, size_bytes: int, cfg: WirelineConfig) -> TransferEvent:
    return TransferEvent(start_s, start_s + wireline_transfer_time_s(size_bytes, cfg), True, float(size_bytes))


def wireless_event(outcome: WirelessOutcome) -> TransferEvent:
    return TransferEvent(outcome.start_s, outcome.end_s, outcome.ok, outcome.sent_bytes, wasted=not outcome.ok)


@dataclass(frozen=True)
class RelayedTransfer:
    """The edge-to-edge relays of one transfer: a download that followed its vehicle, or an upload
    forwarded to the edge that aggregates it; with the stage, direction and payload of that transfer."""

    stage: str
    direction: str
    payload: str
    relays: tuple[Relay, ...]


def charge_transfers(
    ledger: Ledger,
    schedule: Sequence[Transfer],
    events: Mapping[tuple[str, str, str], TransferEvent],
    rule: str,
    cloud_round: int,
    state: FederationState,
    relays: Sequence[RelayedTransfer] = (),
    edges: Sequence[str] = (),
) -> bool:
    """Charge the schedule's transfers that happened, with their times, then the relays;
    False when one does not fit. Counts the relayed transfers in ``state.transfers``, and the
    bytes charged to wasted transfers in ``state.wasted_bytes``.

    ``paper`` charges the schedule's size of every transfer that started,
    ``physical`` the bytes that crossed (fewer than the size for a failed
    transfer, or for a relay that lost some of its vehicles' samples).
    A transfer the schedule lists but that never started is not charged.
    Relays are charged at the bytes they moved under either rule (the paper
    has none).
    """
    for planned in schedule:
        event = events.get((planned.sender, planned.receiver, planned.direction))
        if event is None:
            continue
        size = planned.size_bytes if rule == "paper" else min(planned.size_bytes, math.ceil(event.sent_bytes))
        if not ledger.can_carry(size):
            return False
        charged = dataclasses.replace(planned, size_bytes=size)
        ledger.charge(charged, cloud_round=cloud_round, start_s=event.start_s, end_s=event.end_s)
        state.wasted_bytes += size if event.wasted else 0
    counts = state.transfers
    for relayed in relays:
        counts["relayed_transfers"] = counts.get("relayed_transfers", 0) + 1
        for relay in relayed.relays:
            size = math.ceil(relay.size_bytes)
            if not ledger.can_carry(size):
                return False
            moved = Transfer("relay", relayed.direction, relayed.stage, edges[relay.from_site], edges[relay.to_site],
                             relayed.payload, size)
            ledger.charge(moved, cloud_round=cloud_round, start_s=relay.start_s, end_s=relay.end_s)
    return True


def count_transfer(state: FederationState, kind: str, ok: bool) -> None:
    """One more wireless transfer of ``kind`` (uploads, downloads) that started; ``{kind}_failed`` if it failed."""
    state.transfers[kind] = state.transfers.get(kind, 0) + 1
    state.transfers[f"{kind}_failed"] = state.transfers.get(f"{kind}_failed", 0) + (not ok)


def _bytes_line(ledger: Ledger) -> dict:
    links = ledger.totals("link")
    return {
        "wireless_bytes": links["wireless"],
        "wireline_bytes": links["wireline"],
        "relay_bytes": links["relay"],
        "consumed_bytes": ledger.spent_bytes,
    }


class Federation:
    """Runs the loop of one setup on a clock with a trainer; ``step`` advances one aggregation step.

    ``data(vehicle, t_s)``: the samples a vehicle trains on when it starts
    training at ``t_s`` (default: its fixed shard, ``setup.samples``; the
    online data mode adds what it collected while driving).
    ``labeller``: the vehicles' route experts, which [dagger] (``setup.dagger``) needs: after each
    cloud round it names, every vehicle drives the model it holds and keeps the expert's labels,
    and trains on them from then on (``_data``).
    """

    def __init__(
        self, setup: LoopInputs, clock: Clock, trainer: Trainer, data: Callable[[str, float], Samples] | None = None,
        labeller: Labeller | None = None,
    ) -> None:
        if setup.dagger.enabled and labeller is None:
            raise CrchflError("[dagger] is on, but the run was given no labeller (driving/vehicle_dagger.py)")
        self.setup = setup
        # a vehicle that is off has no link (links/fleet.py)
        self.clock = AvailableClock(clock, setup.fleet) if setup.fleet.intermittent else clock
        self.trainer = trainer
        self.config = setup.config
        self.data = data or (lambda vehicle, t_s: setup.samples[vehicle])
        self.labeller = labeller
        # vehicle -> (its own samples, the labelled rounds, the two joined): one copy per new round, not per step
        self._joined: dict[str, tuple[Samples, tuple[int, ...], Samples]] = {}
        # vehicle -> when its training of this step ended, and how much later than at the nominal speed (a
        # straggler's cause)
        self._trained_at: dict[str, float] = {}
        self._slowed_s: dict[str, float] = {}

    # -- public

    def run(self, state: FederationState, on_step: Callable[[FederationState], None] | None = None) -> FederationState:
        """Step until the stopping rule; ``on_step`` sees the state after every step (checkpoints, progress)."""
        while not state.done:
            state = self.step(state)
            if on_step is not None:
                on_step(state)
        return state

    def step(self, state: FederationState) -> FederationState:
        """One step on a copy of ``state``: stage I, one edge aggregation (+ cloud), or one SFL round."""
        state = dataclasses.replace(
            state,
            vehicle_models=dict(state.vehicle_models),
            edge_models=dict(state.edge_models),
            edge_weights=dict(state.edge_weights),
            member=dict(state.member),
            ready_s=dict(state.ready_s),
            open_s=dict(state.open_s),
            records=list(state.records),
            metrics=list(state.metrics),
            stragglers=list(state.stragglers),
            transfers=dict(state.transfers),
            residuals=dict(state.residuals),
        )
        ledger = Ledger(self.setup.sizes, byte_totals=state.ledger_totals)
        hyper = self.setup.hyper
        self._trained_at, self._slowed_s = {}, {}
        if hyper.cloud_rounds and state.cloud_rounds >= hyper.cloud_rounds:
            state.stop_reason = "cloud_rounds"
        elif not ledger.can_carry_model():
            state.stop_reason = "budget"
        elif not state.stage_one_done:
            self._stage_one(state, ledger)
        elif self.config.hierarchical:
            self._edge_step(state, ledger)
        else:
            self._sfl_round(state, ledger)
        charged = ledger.records  # this step's
        state.records.extend(charged)
        state.ledger_totals = ledger.byte_totals()
        state.transfers_end_s = max([state.transfers_end_s, *(r.end_s for r in charged)])
        state.steps += 1
        return state

    # -- pieces

    def _compute_s(self, samples: int, epochs: int) -> float:
        """Nominal training time: a vehicle of compute factor 1 that stays on."""
        return epochs * samples * self.config.compute_s_per_sample

    def _own_compute_s(self, vehicle: str, samples: int, epochs: int) -> float:
        """``vehicle``'s training time at its own speed (links/fleet.py), not counting time off."""
        return self._compute_s(samples, epochs) * self.setup.fleet.factor(vehicle)

    def _count_training(self, state: FederationState, counts: Mapping[str, int], epochs: int) -> None:
        """A counted step's training time of each vehicle that trained, at its own speed (its energy)."""
        own = {v: self._own_compute_s(v, n, epochs) for v, n in counts.items()}
        state.train_s = {v: state.train_s.get(v, 0.0) + own.get(v, 0.0) for v in self.setup.vehicles
                         if v in state.train_s or v in own}

    def _trained_s(self, vehicle: str, start_s: float, samples: int, epochs: int) -> float:
        """When ``vehicle``, starting at ``start_s``, has trained: at its own speed, paused while it is off."""
        own_s = self._own_compute_s(vehicle, samples, epochs)
        self._slowed_s[vehicle] = own_s - self._compute_s(samples, epochs)
        self._trained_at[vehicle] = self.setup.fleet.work_end_s(vehicle, start_s, own_s)
        return self._trained_at[vehicle]

    def _upload(
        self, vehicle: str, edge: str | None, start_s: float, size: int, window_end_s: float
    ) -> WirelessOutcome | None:
        """``vehicle``'s upload to its ``edge`` under the handover policy (SFL, edge None: to the cloud).

        None if it cannot even start before the deadline ``window_end_s``.
        """
        if start_s >= window_end_s:
            return None
        cfg = with_deadline(self.setup.transfer, window_end_s - start_s)
        if edge is None:
            return wireless_transfer(self.clock, vehicle, "macro", start_s, size, cfg)
        policy = self.config.handover_policy
        home = self.setup.edges.index(edge)
        if policy in ("new_edge", "forward"):
            return wireless_transfer(self.clock, vehicle, "edge", start_s, size, cfg)
        if policy == "wait":
            cfg = dataclasses.replace(cfg, on_outage="stall", max_outage_s=math.inf)
        else:  # miss: any time off its own edge fails the upload
            cfg = dataclasses.replace(cfg, on_outage="fail")
        return wireless_transfer(self.clock, vehicle, "edge", start_s, size, cfg, only_site=home)

    def _download(
        self, vehicle: str, start_s: float, size: int, edge: str | None
    ) -> tuple[WirelessOutcome, tuple[Relay, ...]]:
        """Edge -> vehicle (across handovers as ``download_handover`` says) or, for SFL (edge None), cloud -> vehicle."""
        setup = self.setup
        if edge is None:
            return wireless_transfer(self.clock, vehicle, "macro", start_s, size, setup.transfer), ()
        site = setup.edges.index(edge)
        return edge_download(self.clock, vehicle, site, start_s, size, setup.transfer, setup.wireline,
                             self.config.download_handover)

    def _forward(self, out: WirelessOutcome, receiver: str, size: int, payload: str, stage: str, relays) -> float:
        """When an upload under the ``forward`` policy ended at another edge than ``receiver``, that edge
        forwards it over the wireline (a relay); returns when it reaches ``receiver``."""
        edges = self.setup.edges
        if self.config.handover_policy != "forward" or not out.ok or receiver not in edges:
            return out.end_s
        home = edges.index(receiver)
        if out.site == home:
            return out.end_s
        arrival_s = out.end_s + wireline_transfer_time_s(size, self.setup.wireline)
        relays.append(RelayedTransfer(stage, "uplink", payload, (Relay(out.site, home, out.end_s, arrival_s, size),)))
        return arrival_s

    def _data(self, state: FederationState, ledger: Ledger) -> dict[str, Samples]:
        """Every vehicle's samples for the training it would start now (when it holds its model), with the
        labels of its own drives ([dagger]): at the start of a cloud round that ``setup.dagger`` names, each
        vehicle first drives the model it holds and the expert labels what it visited."""
        if (self.setup.dagger.due(state.cloud_rounds) and state.tau == 0 and state.cloud_rounds not in state.dagger_rounds
                and self._step_may_fit(state, ledger)):
            self.labeller.label(state.cloud_rounds, state.vehicle_models)
            state.dagger_rounds = [*state.dagger_rounds, state.cloud_rounds]
        rounds = tuple(state.dagger_rounds)
        out = {}
        for v in self.setup.vehicles:
            own = self.data(v, state.ready_s[v])
            cached = self._joined.get(v)
            if not rounds:
                out[v] = own
            elif cached is not None and cached[0] is own and cached[1] == rounds:
                out[v] = cached[2]
            else:
                labels = [labelled[v] for labelled in map(self.labeller.labelled, rounds) if len(labelled.get(v, ()))]
                out[v] = Samples.concat([own, *labels]) if labels else own
                self._joined[v] = (own, rounds, out[v])
        return out

    def _uploaded(self, state: FederationState, vehicle: str, model: State, start: State) -> State:
        """What the receiver of ``vehicle``'s upload of ``model`` holds: the update (``model`` - ``start``)
        through [federation] update_codec, added to ``start``. topk keeps what it leaves out in
        ``state.residuals`` for the vehicle's next upload (error feedback)."""
        codec = self.config.update_codec
        if codec == "none":
            return model
        if codec == "int8":
            return codecs.int8_transfer(model, start)
        sent, state.residuals[vehicle] = codecs.topk_roundtrip(codecs.subtract(model, start), self.config.topk_fraction,
                                                                state.residuals.get(vehicle))
        return codecs.add(start, sent)

    def _server_update(self, state: FederationState, tier: str, node: str, current: State, average: State) -> State:
        """The aggregator's new model from the FedAvg of what it received ([federation] strategy); what the
        strategy keeps at the node goes into ``state.strategy_memory``."""
        kept = state.strategy_memory.get(node, {})
        new, memory = self.setup.strategy.server_update(tier, node, current, average, kept)
        if memory or node in state.strategy_memory:
            state.strategy_memory = {**state.strategy_memory, node: memory}
        return new

    def _sent(self, model: State, reference: State) -> State:
        """What the receivers of a whole-model transfer (a release, an edge's upload) hold: under int8, its
        difference from ``reference`` (the last global model, which every node holds) in 8 bits."""
        return codecs.int8_transfer(model, reference) if self.config.update_codec == "int8" else model

    def _step_schedule(self, topology: Topology, followed: bool) -> tuple[Transfer, ...]:
        """What a step charges for ``topology``: an edge aggregation (and the cloud aggregation when
        ``followed``), or SFL's cloud round."""
        setup, cfg = self.setup, self.config
        if not cfg.hierarchical:
            return cloud_aggregation_schedule(setup.rule, cfg.scheme, topology, setup.sizes)
        schedule = edge_aggregation_schedule(setup.rule, cfg.scheme, topology, setup.sizes, followed_by_cloud=followed)
        if followed:
            schedule += cloud_aggregation_schedule(setup.rule, cfg.scheme, topology, setup.sizes)
        return schedule

    def _step_may_fit(self, state: FederationState, ledger: Ledger) -> bool:
        """Could the budget carry this step? Under the paper rule a step charges at least the schedule of its
        vehicles all under one edge (more edges and relays add to it), so one for which even that does not
        fit will not be counted: the vehicles' drives for it would be wasted. Under the physical rule a
        failed transfer charges less: always True."""
        setup = self.setup
        if setup.rule != "paper":
            return True
        cheapest = Topology(((setup.edges[0],) if self.config.hierarchical else (SFL_LINK,)), (setup.vehicles,))
        followed = state.tau + 1 == setup.hyper.cloud_interval
        return ledger.can_carry(schedule_bytes(self._step_schedule(cheapest, followed)))

    def _train_and_average(
        self,
        state: FederationState,
        epochs: int,
        samples: Mapping[str, Samples],
        arrived: Mapping[str, Collection[str]],
        keep: Collection[str],
    ) -> tuple[dict[str, State], dict[str, State]]:
        """Train the vehicles of ``samples`` for ``epochs``; average, per receiver (edge or cloud), the models
        that arrived there (``arrived``; FedAvg weights |T_nk| = the samples trained on).

        Returns the receivers' averages (those that received a model) and the trained models of the vehicles
        in ``keep`` (a vehicle whose download failed keeps its own). Each model is folded into its
        receiver's average as the trainer yields it and then dropped, so the step never holds every
        vehicle's model at once (a thousand of them are gigabytes). The sums run in the vehicles' order, as
        a FedAvg over each receiver's list of arrivals does, so they equal it to the bit.
        """
        vehicles = list(samples)
        seed = int(np.random.SeedSequence([self.config.seed, 1, state.steps]).generate_state(1)[0])
        receiver = {v: r for r, arrivals in arrived.items() for v in arrivals}
        weights: dict[str, list[int]] = {}
        for v in vehicles:
            if v in receiver:
                weights.setdefault(receiver[v], []).append(len(samples[v]))
        running = {r: RunningAverage(w) for r, w in weights.items()}
        kept: dict[str, State] = {}
        starts = [state.vehicle_models[v] for v in vehicles]
        trained = self.trainer.train(starts, [samples[v] for v in vehicles], epochs, seed)
        for v, start, model in zip(vehicles, starts, trained, strict=True):
            if v in receiver:
                running[receiver[v]].add(self._uploaded(state, v, model, start))
            if v in keep:
                kept[v] = model
        return {r: average.result() for r, average in running.items()}, kept

    def _select(self, state: FederationState, samples: Mapping[str, Samples]) -> tuple[str, ...]:
        """The vehicles that train in this edge aggregation (``federation.selection``; federation/selection.py)."""
        cfg, setup = self.config, self.setup
        if cfg.selection == "all":
            return tuple(samples)
        epochs = setup.hyper.edge_interval
        own = cfg.handover_policy in ("wait", "miss")  # their uploads run only over the vehicle's own edge
        needed, residence = {}, {}
        for v in samples:
            t_s = state.ready_s[v]
            rate_bps = selection.recent_rate_bps(self.clock, v, t_s)
            train_s = self._trained_s(v, t_s, len(samples[v]), epochs) - t_s
            needed[v] = selection.needed_s(train_s, setup.sizes.upload_bytes, rate_bps)
            site = setup.edges.index(state.member[v]) if own else None
            residence[v] = selection.residence_on_clock(self.clock, v, t_s, setup.coverage, site)
        picked = selection.chosen(needed, residence)
        for v in samples:
            if v not in picked:
                log.info("step %d: %s skipped: %.1f s left in its cell, %.1f s needed", state.steps, v,
                         residence[v], needed[v])
        return picked

    def _taking_part(self, state: FederationState, candidates: Sequence[str]) -> tuple[str, ...]:
        """The vehicles of ``candidates`` that the strategy's ``configure`` chooses, aggregator by aggregator: each
        edge among its members, or the cloud among all in SFL (learning/strategies.py)."""
        def seed(index: int) -> int:
            return int(np.random.SeedSequence([self.config.seed, 4, state.steps, index]).generate_state(1)[0])

        strategy, candidates = self.setup.strategy, tuple(candidates)
        if not self.config.hierarchical:
            return taking_part(strategy, "cloud", CLOUD, candidates, seed(0))
        members: dict[str, list[str]] = {}
        for v in candidates:
            members.setdefault(state.member[v], []).append(v)
        chosen: set[str] = set()
        for i, e in enumerate(self.setup.edges, start=1):  # the edge's index seeds its draw
            if e in members:
                chosen.update(taking_part(strategy, "edge", e, tuple(members[e]), seed(i)))
        return tuple(v for v in candidates if v in chosen)

    def _line(
        self, state: FederationState, ledger: Ledger, stage: str, t_s: float, metrics: Mapping | None = None, **extra
    ) -> dict:
        line = {
            "step": state.steps + 1,
            "stage": stage,
            "cloud_round": state.cloud_rounds,
            "edge_aggregations": state.edge_aggregations,
            **_bytes_line(ledger),
            "sim_time_s": t_s,
            "loss": None,
            "accuracy": None,
            **(metrics or {}),
            **extra,
        }
        state.metrics.append(line)
        return line

    def _evaluate_cloud(self, state: FederationState, ledger: Ledger, stage: str, t_s: float, **extra) -> None:
        line = self._line(state, ledger, stage, t_s, self.trainer.evaluate(state.cloud_model), **extra)
        for mark in self.setup.budget_marks_bytes:  # first evaluation past a mark: the best within it is known
            if str(mark) not in state.budget_marks and line["consumed_bytes"] > mark:
                state.budget_marks[str(mark)] = None if state.best is None else dict(state.best)
                if state.best_model is not None:
                    state.budget_mark_models[str(mark)] = state.best_model
        if state.best is None or _better(line, state.best):
            state.best, state.best_model = dict(line), state.cloud_model

    # -- stage I

    def _stage_one(self, state: FederationState, ledger: Ledger) -> None:
        setup, cfg, sizes = self.setup, self.config, self.setup.sizes
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
            out = self._upload(v, edge, state.ready_s[v], shares[v] * sizes.sample_bytes, window_end)
            if out is None:
                self._straggler(state, v, "I", "no time to upload before the deadline", window_end)
                continue
            if out.ok and cfg.handover_policy == "new_edge":
                member[v] = setup.edges[out.site]
            events[(v, member[v], "uplink")] = wireless_event(out)
            count_transfer(state, "uploads", out.ok)
            arrival_s[v] = self._forward(out, member[v], shares[v] * sizes.sample_bytes, "samples", "I", relays)
            if out.ok and arrival_s[v] > window_end + _EPS_S:
                events[(v, member[v], "uplink")] = dataclasses.replace(events[(v, member[v], "uplink")], wasted=True)
                self._straggler(state, v, "I", "deadline", window_end)
            elif out.ok:
                # the fixed uploaded subset: a seeded choice of the vehicle's samples
                rng = np.random.default_rng([cfg.seed, 2, i])
                uploaded[v] = setup.samples[v].subset(np.sort(rng.permutation(counts[v])[: shares[v]]))
            else:
                self._straggler(state, v, "I", out.reason, out.end_s)
        topology = self._topology(member)
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
            [model] = self.trainer.train([state.cloud_model], [Samples.concat(parts)], cfg.pretrain_epochs, seed)
            model = self._sent(model, state.cloud_model)  # released to every edge and vehicle
        pretrained_s = start_s + cfg.pretrain_epochs * n * cfg.compute_s_per_sample
        # release: cloud -> every edge (wireline), edge -> its vehicles (wireless)
        ready, models, open_s = dict(state.ready_s), dict(state.vehicle_models), dict(state.open_s)
        for e, vehicles in topology.active():
            ev = wireline_event(pretrained_s, sizes.model_bytes, setup.wireline)
            events[(CLOUD, e, "downlink")] = ev
            open_s[e] = ev.end_s
            delivered = self._send_down(state, e, vehicles, ev.end_s, "I", events, ready, relays)
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
        self._evaluate_cloud(state, ledger, "I", pretrained_s, pretrain_samples=n)

    # -- stages II and III

    def _topology(self, member: Mapping[str, str]) -> Topology:
        edges = tuple(e for e in self.setup.edges if any(member[v] == e for v in self.setup.vehicles))
        groups = tuple(tuple(v for v in self.setup.vehicles if member[v] == e) for e in edges)
        return Topology(edges, groups)

    def _edge_step(self, state: FederationState, ledger: Ledger) -> None:
        """Stage II: one edge aggregation; when it is the ``cloud_interval``-th, stage III follows.

        The step's times do not depend on what the models learn (training takes
        its simulated compute time), so its transfers are worked out first and
        the vehicles train last, each model folded into its edge's FedAvg as it
        comes (``_train_and_average``).
        """
        setup, cfg, sizes = self.setup, self.config, self.setup.sizes
        followed = state.tau + 1 == setup.hyper.cloud_interval
        samples = self._data(state, ledger)
        picked = self._taking_part(state, self._select(state, samples))
        counts = {v: len(samples[v]) for v in picked}  # |T_nk| of the vehicles that train
        skipped = [v for v in setup.vehicles if v not in picked]
        events: dict[tuple[str, str, str], TransferEvent] = {}
        relays: list[RelayedTransfer] = []
        uploads, member = self._vehicle_uploads(state, counts)
        topology = self._topology(member)
        agg_s, received_by = self._edge_arrivals(state, topology, uploads, events, relays)
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
        ready, open_s, delivered = self._release(state, topology, release_s, events, stage, relays)
        averages, kept = self._train_and_average(
            state, setup.hyper.edge_interval, {v: samples[v] for v in picked}, received_by, set(counts) - delivered
        )
        edge_models, edge_weights = dict(state.edge_models), dict(state.edge_weights)
        for e, average in averages.items():  # an edge that received no model keeps its previous one
            average = self._server_update(state, "edge", e, state.edge_models[e], average)
            edge_models[e] = self._sent(average, state.cloud_model)  # up to the cloud, or down to its vehicles
            edge_weights[e] = float(sum(counts[v] for v in received_by[e]))
        edge_metrics = self._evaluate_edges(edge_models, edge_weights, agg_s) if cfg.evaluate_every_edge else None
        cloud_model = state.cloud_model
        if followed:
            fresh = [(edge_models[e], edge_weights[e]) for e in agg_s if received_by[e]]
            if fresh:
                average = self._server_update(state, "cloud", CLOUD, state.cloud_model, fedavg(fresh))
                cloud_model = self._sent(average, state.cloud_model)
            edge_models.update(dict.fromkeys(agg_s, cloud_model))
        models = {**state.vehicle_models, **kept}  # a skipped vehicle, or one whose download failed, keeps its own
        for e, vehicles in topology.active():
            models.update(dict.fromkeys((v for v in vehicles if v in delivered), edge_models[e]))
        next_round = state.cloud_rounds + 1
        schedule = self._step_schedule(topology, followed)
        if not charge_transfers(ledger, schedule, events, setup.rule, next_round, state, relays, setup.edges):
            state.stop_reason = "budget"
            return
        state.vehicle_models, state.ready_s, state.open_s, state.member = models, ready, open_s, member
        state.edge_models, state.edge_weights = edge_models, edge_weights
        self._count_training(state, counts, setup.hyper.edge_interval)
        state.edge_aggregations += 1
        state.tau += 1
        state.skipped += len(skipped)
        received = {e: len(vs) for e, vs in received_by.items()}
        extra = {"skipped": skipped} if skipped or cfg.selection != "all" else {}
        t_s = max(agg_s.values())
        self._line(state, ledger, "II", t_s, edge_metrics, received=received, samples=sum(counts.values()), **extra)
        if followed:
            state.cloud_model = cloud_model
            state.cloud_rounds = next_round
            state.tau = 0
            self._evaluate_cloud(state, ledger, "III", cloud_s)

    def _vehicle_uploads(
        self, state: FederationState, counts: Mapping[str, int]
    ) -> tuple[dict[str, WirelessOutcome | None], dict[str, str]]:
        """The upload of each vehicle in ``counts`` (those that trained) after its training, and the
        membership after them (``new_edge`` moves vehicles)."""
        setup, cfg = self.setup, self.config
        member = dict(state.member)
        uploads: dict[str, WirelessOutcome | None] = {}
        for v in counts:
            edge = state.member[v]
            start_s = self._trained_s(v, state.ready_s[v], counts[v], setup.hyper.edge_interval)
            out = self._upload(v, edge, start_s, setup.sizes.upload_bytes, state.open_s[edge] + cfg.deadline_s)
            uploads[v] = out
            if out is not None and out.ok and cfg.handover_policy == "new_edge":
                member[v] = setup.edges[out.site]
        return uploads, member

    def _edge_arrivals(self, state, topology, uploads, events, relays):
        """When each edge aggregates (once its members' uploads ended; at the latest, its deadline) and
        whose models it holds then.

        Returns (aggregation time, vehicles whose model arrived) per edge; records the uploads in
        ``events`` and the stragglers in ``state``.
        """
        agg_s: dict[str, float] = {}
        received_by: dict[str, list[str]] = {}
        for e, vehicles in topology.active():
            ends, received_by[e] = self._gather_uploads(
                state,
                {v: uploads[v] for v in vehicles if v in uploads},
                e,
                "II",
                lambda v: state.open_s[state.member[v]] + self.config.deadline_s,
                events,
                relays,
            )
            agg_s[e] = max(ends, default=state.open_s[e])  # no member trained: nothing to wait for
        return agg_s, received_by

    def _release(self, state, topology, release_s, events, stage, relays):
        """Each edge sends its model to its vehicles from ``release_s[edge]`` on.

        Returns the times the vehicles hold their models, the edges' new window openings, and the
        vehicles whose download arrived (the others keep their own model).
        """
        ready, open_s, delivered = dict(state.ready_s), dict(state.open_s), set()
        for e, vehicles in topology.active():
            open_s[e] = release_s[e]
            delivered.update(self._send_down(state, e, vehicles, release_s[e], stage, events, ready, relays))
        return ready, open_s, delivered

    def _send_down(self, state, sender: str, vehicles, start_s: float, stage: str, events, ready, relays) -> list[str]:
        """``sender`` (an edge, or the cloud in SFL) sends its model to each of ``vehicles`` from ``start_s`` on.

        Returns the vehicles whose download arrived. Records each download in ``events``, its relays in
        ``relays`` and its arrival in ``ready``; a vehicle whose download fails is recorded as a straggler.
        """
        edge = None if sender == CLOUD else sender
        delivered = []
        for v in vehicles:
            out, moved = self._download(v, start_s, self.setup.sizes.model_bytes, edge)
            events[(sender, v, "downlink")] = wireless_event(out)
            count_transfer(state, "downloads", out.ok)
            if moved:
                relays.append(RelayedTransfer(stage, "downlink", "model", moved))
            ready[v] = out.end_s
            if out.ok:
                delivered.append(v)
            else:
                self._straggler(state, v, stage, f"download {out.reason}", out.end_s)
        return delivered

    def _evaluate_edges(self, models, weights, edges) -> dict[str, float]:
        """Sample-weighted means of the edge models' scalar test metrics."""
        results = [(self.trainer.evaluate(models[e]), weights[e]) for e in edges]
        total = sum(w for _, w in results) or 1.0
        keys = [k for k in SCALAR_METRICS if all(k in m for m, _ in results)]
        return {k: sum(m[k] * w for m, w in results) / total for k in keys}

    def _gather_uploads(self, state, uploads, receiver: str, stage: str, missed_at, events, relays):
        """Arrival time of each vehicle's upload to ``receiver`` and the vehicles whose model arrived.

        An upload that could not start before the deadline (None) ends at
        ``missed_at(vehicle)``; it and every failed upload are recorded as
        stragglers. Started uploads are recorded in ``events``.
        """
        ends, received = [], []
        for v, out in uploads.items():
            late = dict(window_end_s=missed_at(v), edge=None if receiver == CLOUD else state.member[v])
            if out is None:
                ends.append(missed_at(v))
                self._straggler(state, v, stage, "no time to upload before the deadline", ends[-1], **late)
                continue
            events[(v, receiver, "uplink")] = wireless_event(out)
            count_transfer(state, "uploads", out.ok)
            arrival_s = self._forward(out, receiver, self.setup.sizes.upload_bytes, "model", stage, relays)
            if out.ok and arrival_s > missed_at(v) + _EPS_S:  # forwarded past the deadline
                events[(v, receiver, "uplink")] = dataclasses.replace(events[(v, receiver, "uplink")], wasted=True)
                ends.append(missed_at(v))
                self._straggler(state, v, stage, "deadline", ends[-1], **late)
            elif out.ok:
                ends.append(arrival_s)
                received.append(v)
            else:
                ends.append(out.end_s)
                self._straggler(state, v, stage, out.reason, out.end_s, **late)
        return ends, received

    def _straggler(
        self, state: FederationState, vehicle: str, stage: str, reason: str, t_s: float,
        window_end_s: float | None = None, edge: str | None = None,
    ) -> None:
        """Record that ``vehicle`` missed this step's aggregation or download at ``t_s``, why (``reason``: what
        happened to the transfer) and its ``cause`` (``_cause``; ``window_end_s`` and ``edge``: its upload's deadline
        and receiving edge, for an upload after training)."""
        cause = self._cause(state, vehicle, reason, t_s, window_end_s, edge)
        state.stragglers.append(
            {
                "step": state.steps + 1,
                "stage": stage,
                "cloud_round": 0 if stage == "I" else state.cloud_rounds + 1,
                "vehicle": vehicle,
                "reason": reason,
                "cause": cause,
                "t_s": t_s,
            }
        )
        log.info("step %d: %s straggles (%s, %s) at %.1f s", state.steps, vehicle, reason, cause, t_s)

    def _cause(
        self, state: FederationState, vehicle: str, reason: str, t_s: float, window_end_s: float | None,
        edge: str | None,
    ) -> str:
        """Why a vehicle straggled, the first that applies: "unavailable" (it was off at some moment between
        holding its model and ``t_s``, either way round), "out_of_coverage" (its transfer lost coverage),
        "slow_compute" (it missed the deadline, and an upload started when a vehicle of compute factor 1
        would have finished training makes it on the same links), "deadline" (its links were too slow for
        the deadline)."""
        held_s = state.ready_s[vehicle]  # past t_s when its last download came late
        if self.setup.fleet.off_between(vehicle, min(held_s, t_s), max(held_s, t_s)):
            return "unavailable"
        if reason.endswith("outage"):
            return "out_of_coverage"
        slowed_s = self._slowed_s.get(vehicle, 0.0)
        if slowed_s > 0 and window_end_s is not None:
            start_s = self._trained_at[vehicle] - slowed_s
            out = self._upload(vehicle, edge, start_s, self.setup.sizes.upload_bytes, window_end_s)
            if out is not None and out.ok:
                return "slow_compute"
        return "deadline"

    # -- SFL

    def _sfl_round(self, state: FederationState, ledger: Ledger) -> None:
        setup, cfg, sizes = self.setup, self.config, self.setup.sizes
        epochs = setup.hyper.edge_interval
        samples = self._data(state, ledger)
        picked = self._taking_part(state, tuple(samples))
        counts = {v: len(samples[v]) for v in picked}
        skipped = [v for v in setup.vehicles if v not in picked]
        window_end = state.open_s[CLOUD] + cfg.deadline_s
        events: dict[tuple[str, str, str], TransferEvent] = {}
        relays: list[RelayedTransfer] = []
        uploads = {
            v: self._upload(
                v, None, self._trained_s(v, state.ready_s[v], counts[v], epochs), sizes.upload_bytes, window_end
            )
            for v in picked
        }
        ends, received = self._gather_uploads(state, uploads, CLOUD, "III", lambda v: window_end, events, relays)
        cloud_s = max(ends)
        ready = dict(state.ready_s)
        delivered = set(self._send_down(state, CLOUD, setup.vehicles, cloud_s, "III", events, ready, relays))
        # the times first, the training last (as in _edge_step)
        averages, kept = self._train_and_average(
            state, epochs, {v: samples[v] for v in picked}, {CLOUD: received}, set(picked) - delivered
        )
        cloud_model = state.cloud_model
        if CLOUD in averages:
            average = self._server_update(state, "cloud", CLOUD, state.cloud_model, averages[CLOUD])
            cloud_model = self._sent(average, state.cloud_model)
        # a vehicle whose download failed keeps what it trained, or, if it sat the round out, what it held
        models = {v: cloud_model if v in delivered else kept.get(v, state.vehicle_models[v]) for v in setup.vehicles}
        topology = Topology((SFL_LINK,), (setup.vehicles,))
        next_round = state.cloud_rounds + 1
        schedule = self._step_schedule(topology, followed=True)
        if not charge_transfers(ledger, schedule, events, setup.rule, next_round, state):
            state.stop_reason = "budget"
            return
        state.vehicle_models, state.ready_s = models, ready
        state.open_s = {CLOUD: cloud_s}
        self._count_training(state, counts, epochs)
        state.skipped += len(skipped)
        state.cloud_model = cloud_model
        state.cloud_rounds = next_round
        extra = {"skipped": skipped} if skipped else {}
        self._evaluate_cloud(state, ledger, "III", cloud_s, received=len(received), samples=sum(counts.values()), **extra)


def _rank(line: Mapping[str, Any]) -> tuple[float, float, float]:
    """A model's place: balanced accuracy (the plain accuracy where there is none), then accuracy, then lower loss.

    Balanced accuracy first, because a model that always says "straight" has a high accuracy on data that is
    mostly straight, and cannot drive. NaN ranks last.
    """
    primary = line.get("balanced_accuracy")
    values = (line["accuracy"] if primary is None else primary, line["accuracy"], -line["loss"])
    return tuple(-math.inf if math.isnan(v) else v for v in values)


def _better(line: Mapping[str, Any], best: Mapping[str, Any]) -> bool:
    """``line``'s model beats the best so far (a NaN score never wins)."""
    rank = _rank(line)
    return rank[0] > -math.inf and rank > _rank(best)
