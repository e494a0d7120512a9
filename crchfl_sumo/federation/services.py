"""What every scheme's step uses (federation/scheme_steps.py): the vehicles' transfers on the clock and
their charges, stragglers, the vehicles' data, training and averaging, the strategy's server update,
evaluation and the metric lines.

Time: local training takes ``compute_s_per_sample`` x samples x epochs of
simulated time; every wireless transfer runs over the vehicle's link on the
clock (links/clock.py), every wireline one takes latency + size / rate. An
aggregation waits for its vehicles' uploads until ``deadline_s`` after its
window opened; a model that has not arrived by then is a straggler's,
recorded and left out of that FedAvg (weights renormalised over the rest).

Bytes: every step's transfers come from the schedule functions
(``schedules.stage_one_schedule``, ``edge_aggregation_schedule``,
``cloud_aggregation_schedule``) for the step's actual topology, and are
charged with their simulated start and end times (``charge_transfers``); a
step whose transfers do not all fit is not counted and its models are dropped
(its charged bytes stay spent, as ``ledger.replay`` does).
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
)
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.settings import SFL_LINK
from crchfl_sumo.federation.state import FederationState, Labeller, LoopInputs, Trainer
from crchfl_sumo.learning import codecs
from crchfl_sumo.learning.aggregate import RunningAverage
from crchfl_sumo.learning.model import State
from crchfl_sumo.learning.strategies import taking_part
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.clock import Clock, Relay, WirelessOutcome, edge_download, wireless_transfer, with_deadline
from crchfl_sumo.links.fleet import AvailableClock
from crchfl_sumo.links.transfer import wireline_transfer_time_s

log = logging.getLogger(__name__)

EPS_S = 1e-9  # float slack when comparing simulated times

# The test metrics that an edge evaluation averages over edges (the rest: per-class counts and rates).
SCALAR_METRICS = ("loss", "accuracy", "balanced_accuracy", "steer_error", "throttle_error", "brake_error")


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


class StepServices:
    """The shared services of a run's steps, on its clock with its trainer.

    ``data(vehicle, t_s)``: the samples a vehicle trains on when it starts
    training at ``t_s`` (default: its fixed shard, ``setup.samples``; the
    online data mode adds what it collected while driving).
    ``labeller``: the vehicles' route experts, which [dagger] (``setup.dagger``) needs: after each
    cloud round it names, every vehicle drives the model it holds and keeps the expert's labels,
    and trains on them from then on (``training_data``).
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

    def start_step(self) -> None:
        """Forget the previous step's training times (a straggler's cause reads this step's)."""
        self._trained_at, self._slowed_s = {}, {}

    # -- pieces

    def _compute_s(self, samples: int, epochs: int) -> float:
        """Nominal training time: a vehicle of compute factor 1 that stays on."""
        return epochs * samples * self.config.compute_s_per_sample

    def _own_compute_s(self, vehicle: str, samples: int, epochs: int) -> float:
        """``vehicle``'s training time at its own speed (links/fleet.py), not counting time off."""
        return self._compute_s(samples, epochs) * self.setup.fleet.factor(vehicle)

    def count_training(self, state: FederationState, counts: Mapping[str, int], epochs: int) -> None:
        """A counted step's training time of each vehicle that trained, at its own speed (its energy)."""
        own = {v: self._own_compute_s(v, n, epochs) for v, n in counts.items()}
        state.train_s = {v: state.train_s.get(v, 0.0) + own.get(v, 0.0) for v in self.setup.vehicles
                         if v in state.train_s or v in own}

    def trained_s(self, vehicle: str, start_s: float, samples: int, epochs: int) -> float:
        """When ``vehicle``, starting at ``start_s``, has trained: at its own speed, paused while it is off."""
        own_s = self._own_compute_s(vehicle, samples, epochs)
        self._slowed_s[vehicle] = own_s - self._compute_s(samples, epochs)
        self._trained_at[vehicle] = self.setup.fleet.work_end_s(vehicle, start_s, own_s)
        return self._trained_at[vehicle]

    def upload(
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

    def download(
        self, vehicle: str, start_s: float, size: int, edge: str | None
    ) -> tuple[WirelessOutcome, tuple[Relay, ...]]:
        """Edge -> vehicle (across handovers as ``download_handover`` says) or, for SFL (edge None), cloud -> vehicle."""
        setup = self.setup
        if edge is None:
            return wireless_transfer(self.clock, vehicle, "macro", start_s, size, setup.transfer), ()
        site = setup.edges.index(edge)
        return edge_download(self.clock, vehicle, site, start_s, size, setup.transfer, setup.wireline,
                             self.config.download_handover)

    def forward(self, out: WirelessOutcome, receiver: str, size: int, payload: str, stage: str, relays) -> float:
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

    def training_data(self, state: FederationState, ledger: Ledger) -> dict[str, Samples]:
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

    def server_update(self, state: FederationState, tier: str, node: str, current: State, average: State) -> State:
        """The aggregator's new model from the FedAvg of what it received ([federation] strategy); what the
        strategy keeps at the node goes into ``state.strategy_memory``."""
        kept = state.strategy_memory.get(node, {})
        new, memory = self.setup.strategy.server_update(tier, node, current, average, kept)
        if memory or node in state.strategy_memory:
            state.strategy_memory = {**state.strategy_memory, node: memory}
        return new

    def sent(self, model: State, reference: State) -> State:
        """What the receivers of a whole-model transfer (a release, an edge's upload) hold: under int8, its
        difference from ``reference`` (the last global model, which every node holds) in 8 bits."""
        return codecs.int8_transfer(model, reference) if self.config.update_codec == "int8" else model

    def step_schedule(self, topology: Topology, followed: bool) -> tuple[Transfer, ...]:
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
        return ledger.can_carry(schedule_bytes(self.step_schedule(cheapest, followed)))

    def train_and_average(
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
        # a model neither received nor kept is never read: its upload failed (or came late) and a download
        # replaces it. Its transfers were worked out without it, so skipping its training changes nothing.
        needed = [i for i, v in enumerate(vehicles) if v in receiver or v in keep]
        trained = self.trainer.train(starts, [samples[v] for v in vehicles], epochs, seed, needed)
        for v, start, model in zip(vehicles, starts, trained, strict=True):
            if v in receiver:
                running[receiver[v]].add(self._uploaded(state, v, model, start))
            if v in keep:
                kept[v] = model
        return {r: average.result() for r, average in running.items()}, kept

    def taking_part(self, state: FederationState, candidates: Sequence[str]) -> tuple[str, ...]:
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

    def line(
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

    def evaluate_cloud(self, state: FederationState, ledger: Ledger, stage: str, t_s: float, **extra) -> None:
        line = self.line(state, ledger, stage, t_s, self.trainer.evaluate(state.cloud_model), **extra)
        for mark in self.setup.budget_marks_bytes:  # first evaluation past a mark: the best within it is known
            if str(mark) not in state.budget_marks and line["consumed_bytes"] > mark:
                state.budget_marks[str(mark)] = None if state.best is None else dict(state.best)
                if state.best_model is not None:
                    state.budget_mark_models[str(mark)] = state.best_model
        if state.best is None or _better(line, state.best):
            state.best, state.best_model = dict(line), state.cloud_model

    def topology(self, member: Mapping[str, str]) -> Topology:
        edges = tuple(e for e in self.setup.edges if any(member[v] == e for v in self.setup.vehicles))
        groups = tuple(tuple(v for v in self.setup.vehicles if member[v] == e) for e in edges)
        return Topology(edges, groups)


    def send_down(self, state, sender: str, vehicles, start_s: float, stage: str, events, ready, relays) -> list[str]:
        """``sender`` (an edge, or the cloud in SFL) sends its model to each of ``vehicles`` from ``start_s`` on.

        Returns the vehicles whose download arrived. Records each download in ``events``, its relays in
        ``relays`` and its arrival in ``ready``; a vehicle whose download fails is recorded as a straggler.
        """
        edge = None if sender == CLOUD else sender
        delivered = []
        for v in vehicles:
            out, moved = self.download(v, start_s, self.setup.sizes.model_bytes, edge)
            events[(sender, v, "downlink")] = wireless_event(out)
            count_transfer(state, "downloads", out.ok)
            if moved:
                relays.append(RelayedTransfer(stage, "downlink", "model", moved))
            ready[v] = out.end_s
            if out.ok:
                delivered.append(v)
            else:
                self.straggler(state, v, stage, f"download {out.reason}", out.end_s)
        return delivered

    def evaluate_edges(self, models, weights, edges) -> dict[str, float]:
        """Sample-weighted means of the edge models' scalar test metrics."""
        results = [(self.trainer.evaluate(models[e]), weights[e]) for e in edges]
        total = sum(w for _, w in results) or 1.0
        keys = [k for k in SCALAR_METRICS if all(k in m for m, _ in results)]
        return {k: sum(m[k] * w for m, w in results) / total for k in keys}

    def gather_uploads(self, state, uploads, receiver: str, stage: str, missed_at, events, relays):
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
                self.straggler(state, v, stage, "no time to upload before the deadline", ends[-1], **late)
                continue
            events[(v, receiver, "uplink")] = wireless_event(out)
            count_transfer(state, "uploads", out.ok)
            arrival_s = self.forward(out, receiver, self.setup.sizes.upload_bytes, "model", stage, relays)
            if out.ok and arrival_s > missed_at(v) + EPS_S:  # forwarded past the deadline
                events[(v, receiver, "uplink")] = dataclasses.replace(events[(v, receiver, "uplink")], wasted=True)
                ends.append(missed_at(v))
                self.straggler(state, v, stage, "deadline", ends[-1], **late)
            elif out.ok:
                ends.append(arrival_s)
                received.append(v)
            else:
                ends.append(out.end_s)
                self.straggler(state, v, stage, out.reason, out.end_s, **late)
        return ends, received

    def straggler(
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
            out = self.upload(vehicle, edge, start_s, self.setup.sizes.upload_bytes, window_end_s)
            if out is not None and out.ok:
                return "slow_compute"
        return "deadline"


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
