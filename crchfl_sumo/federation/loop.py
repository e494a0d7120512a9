"""Algorithm 1 of the paper on SUMO's clock: CRCHFL, HFL and SFL as configurations of one loop.

The loop (docs/federation.md maps it line by line):

* stage I (CRCHFL with ``pretrain_batch`` > 0): each vehicle uploads a fixed,
  seeded subset of its samples to its edge, the edges relay them to the
  cloud, the cloud pretrains and releases the model to every edge and
  vehicle;
* stage II: every vehicle trains ``edge_interval`` local epochs and uploads
  its model; each edge averages what it received (FedAvg, weights |T_nk|)
  and, unless a cloud aggregation follows, sends the result down;
* stage III: after ``cloud_interval`` edge aggregations the edges send their
  models to the cloud, which averages them (weights: the samples behind each
  edge model) and releases the global model to every edge and vehicle.

SFL has no edge tier: vehicles upload straight to the cloud over the macro
link, one cloud aggregation per round (``cloud_interval`` = 1). HFL is the
hierarchy without stage I and without the optimizer.

Time: local training takes ``compute_s_per_sample`` x samples x epochs of
simulated time; every wireless transfer runs over the vehicle's link on the
clock (``fl_clock``), every wireline one takes latency + size / rate. An
aggregation waits for its vehicles' uploads until ``deadline_s`` after its
window opened; a model that has not arrived by then is a straggler's,
recorded and left out of that FedAvg (weights renormalised over the rest).

Bytes: every step's transfers come from the ledger's schedule functions
(``ledger.stage_one_schedule``, ``edge_aggregation_schedule``,
``cloud_aggregation_schedule``) for the step's actual topology, and are
charged with their simulated start and end times. Training stops when the
rest of the budget cannot carry one more model transfer; a step whose
transfers do not all fit is not counted and its models are dropped (its
charged bytes stay spent, as ``ledger.replay`` does).

The loop's whole memory is a ``FederationState`` (models, times, counters,
ledger records, metric lines), so a checkpoint is the state and a resume
continues from it. Mobility and training are injected (a ``Clock`` and a
``Trainer``), so the loop runs with scripted tracks and tiny models in tests.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Callable, Literal, Mapping, Protocol, Sequence

import numpy as np

from crchfl_sumo.accounting.ledger import Ledger, Record
from crchfl_sumo.accounting.schedules import (
    CLOUD,
    ByteSizes,
    Topology,
    Transfer,
    cloud_aggregation_schedule,
    edge_aggregation_schedule,
    stage_one_schedule,
)
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.schemes import SCHEMES, Scheme
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.aggregate import fedavg
from crchfl_sumo.learning.model import State
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.clock import Clock, WirelessOutcome, wireless_transfer, with_deadline
from crchfl_sumo.links.mobility import NO_SITE
from crchfl_sumo.links.transfer import TransferConfig, wireline_transfer_time_s
from crchfl_sumo.planning.problem import split_pretrain_batch

log = logging.getLogger(__name__)

HandoverPolicy = Literal["new_edge", "wait", "miss"]
SFL_LINK = "macro"  # the pseudo-edge name of SFL's topology (the ledger needs one group)

# Default compute speed: the allocator's epoch_time_s (120 s) for the paper's largest shard (2928 samples).
DEFAULT_COMPUTE_S_PER_SAMPLE = 120.0 / 2928


@dataclass(frozen=True)
class FederationConfig:
    """The scheme and its four hyper-parameters (TOML table ``[federation]``).

    scheme: "crchfl" (stage I + hierarchy), "hfl" (hierarchy only), "sfl"
        (vehicles straight to the cloud).
    use_plan: CRCHFL only: ask the resource optimizer (allocation.make_plan)
        for the four values below instead of taking them from here.
    pretrain_batch: samples uploaded for cloud pretraining (CRCHFL; 0 = no stage I).
    edge_interval: local epochs between two edge aggregations (SFL: between
        two cloud aggregations).
    cloud_interval: edge aggregations between two cloud aggregations (SFL: 1).
    cloud_rounds: stop after this many cloud rounds; 0 = until the budget is spent.
    pretrain_epochs: epochs of the cloud's pretraining on the uploaded subset.
    evaluate_every_edge: also evaluate the edge models after every edge aggregation.
    handover_policy: what a vehicle's upload does when the vehicle is not (or
        no longer) served by its edge: "new_edge" (the model goes to whichever
        edge serves the vehicle when the upload ends; the vehicle joins it),
        "wait" (it is sent only while its own edge serves it, waiting out any
        time elsewhere, up to the deadline), "miss" (leaving its edge's
        coverage during the upload fails it: the vehicle misses that aggregation).
    deadline_s: per aggregation: how long after its window opened an edge
        (or, in SFL, the cloud) waits for uploads [s]; inf = for all of them.
    compute_s_per_sample: simulated time of one sample of one local epoch on a
        vehicle, and of the cloud's pretraining [s].
    seed: seed of the initial model, the pretraining subset and the shuffling.
    """

    scheme: Scheme = "crchfl"
    use_plan: bool = False
    pretrain_batch: int = 0
    edge_interval: int = 2
    cloud_interval: int = 1
    cloud_rounds: int = 0
    pretrain_epochs: int = 10
    evaluate_every_edge: bool = False
    handover_policy: Literal["new_edge", "wait", "miss"] = "new_edge"
    deadline_s: float = math.inf
    compute_s_per_sample: float = DEFAULT_COMPUTE_S_PER_SAMPLE
    seed: int = 0

    def __post_init__(self) -> None:
        if self.scheme not in SCHEMES:
            raise CrchflError(f"federation.scheme: {self.scheme!r} is not one of 'crchfl', 'hfl', 'sfl'")
        if self.handover_policy not in ("new_edge", "wait", "miss"):
            raise CrchflError(
                f"federation.handover_policy: {self.handover_policy!r} is not one of 'new_edge', 'wait', 'miss'"
            )
        if self.use_plan and self.scheme != "crchfl":
            raise CrchflError("federation.use_plan: only CRCHFL asks the optimizer; set use_plan = false for HFL/SFL")
        if self.pretrain_batch < 0:
            raise CrchflError(f"federation.pretrain_batch: {self.pretrain_batch} must be >= 0")
        if self.pretrain_batch > 0 and self.scheme != "crchfl":
            raise CrchflError(
                f"federation.pretrain_batch: {self.scheme.upper()} has no pretraining stage; set it to 0 or use crchfl"
            )
        if self.edge_interval < 1:
            raise CrchflError(f"federation.edge_interval: {self.edge_interval} must be >= 1 (local epochs)")
        if self.cloud_interval < 1:
            raise CrchflError(f"federation.cloud_interval: {self.cloud_interval} must be >= 1")
        if self.scheme == "sfl" and self.cloud_interval != 1:
            raise CrchflError("federation.cloud_interval: SFL has no edge tier; set cloud_interval = 1")
        if self.cloud_rounds < 0:
            raise CrchflError(
                f"federation.cloud_rounds: {self.cloud_rounds} must be >= 0 (0 = until the budget is spent)"
            )
        if self.pretrain_epochs < 1:
            raise CrchflError(f"federation.pretrain_epochs: {self.pretrain_epochs} must be >= 1")
        if not self.deadline_s > 0:
            raise CrchflError(f"federation.deadline_s: {self.deadline_s} must be > 0 (inf = no deadline)")
        if self.handover_policy == "wait" and not math.isfinite(self.deadline_s):
            raise CrchflError(
                "federation.handover_policy = 'wait' waits for the vehicle's own edge until the aggregation "
                "deadline; set a finite federation.deadline_s"
            )
        if not (math.isfinite(self.compute_s_per_sample) and self.compute_s_per_sample >= 0):
            raise CrchflError(f"federation.compute_s_per_sample: {self.compute_s_per_sample} must be a number >= 0")

    @property
    def hierarchical(self) -> bool:
        return self.scheme != "sfl"


@dataclass(frozen=True)
class HyperParameters:
    """The four hyper-parameters a run uses (from the config or from the optimizer's plan)."""

    pretrain_batch: int
    edge_interval: int
    cloud_interval: int
    cloud_rounds: int  # 0 = until the budget is spent


class Trainer(Protocol):
    """What the loop needs from learning; models are state dicts."""

    def initial_state(self) -> State: ...

    def train(self, states: Sequence[State], samples: Sequence[Samples], epochs: int, seed: int) -> list[State]: ...

    def evaluate(self, state: State) -> tuple[float, float]:
        """(Loss, Accuracy) on the test set."""
        ...


@dataclass(frozen=True)
class LoopInputs:
    """Everything fixed for one run: who takes part, sizes, links.

    vehicles: the federated vehicles in a fixed order (their training seeds
    follow it); home_site: each vehicle's edge site index at the start;
    edges: edge site names (index = site index).
    """

    config: FederationConfig
    hyper: HyperParameters
    vehicles: tuple[str, ...]
    samples: Mapping[str, Samples]
    home_site: Mapping[str, int]
    edges: tuple[str, ...]
    sizes: ByteSizes
    rule: Literal["paper", "physical"]
    wireline: WirelineConfig = WirelineConfig()
    transfer: TransferConfig = TransferConfig()

    def __post_init__(self) -> None:
        names = list(self.vehicles) + list(self.edges)
        if len(set(names)) != len(names) or CLOUD in names or SFL_LINK in names:
            raise CrchflError(f"vehicle ids and edge names must be distinct and not {CLOUD!r}/{SFL_LINK!r}: {names}")
        for v in self.vehicles:
            if v not in self.samples or len(self.samples[v]) == 0:
                raise CrchflError(f"vehicle '{v}' has no training samples; check the data set's train shards")
            if self.config.hierarchical and not 0 <= self.home_site.get(v, NO_SITE) < len(self.edges):
                raise CrchflError(
                    f"vehicle '{v}' has no home edge among {list(self.edges)}; check the data set's edges"
                )

    def count(self, vehicle: str) -> int:
        return len(self.samples[vehicle])


@dataclass
class FederationState:
    """All the loop remembers; a checkpoint stores exactly this.

    member: vehicle -> edge name it belongs to now; ready_s: when each vehicle
    holds its current model; open_s: per edge (or the cloud, SFL) when its
    current aggregation window opened; steps: steps done (the training seed
    of step k derives from it).
    """

    vehicle_models: dict[str, State]
    edge_models: dict[str, State]
    edge_weights: dict[str, float]
    cloud_model: State
    member: dict[str, str]
    ready_s: dict[str, float]
    open_s: dict[str, float]
    stage_one_done: bool = False
    steps: int = 0
    cloud_rounds: int = 0
    edge_aggregations: int = 0
    tau: int = 0  # edge aggregations done in the current cloud round
    records: list[Record] = field(default_factory=list)
    metrics: list[dict] = field(default_factory=list)
    stragglers: list[dict] = field(default_factory=list)
    best_model: State | None = None
    best: dict | None = None  # metrics line of the best cloud model
    stop_reason: str | None = None

    @property
    def done(self) -> bool:
        return self.stop_reason is not None

    def to_payload(self) -> dict:
        """Plain dict of tensors and JSON-like values (torch.load(weights_only=True) reads it back)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["records"] = [r.to_dict() for r in self.records]
        return out

    @classmethod
    def from_payload(cls, payload: Mapping) -> "FederationState":
        values = dict(payload)
        values["records"] = [Record(**r) for r in payload["records"]]
        return cls(**values)


def initial_state(setup: LoopInputs, trainer: Trainer, start_s: float) -> FederationState:
    """Every node holds the same seeded initial model (no transfer needed: only the seed)."""
    model = trainer.initial_state()
    edges = setup.edges if setup.config.hierarchical else ()
    member = {v: setup.edges[setup.home_site[v]] if setup.config.hierarchical else CLOUD for v in setup.vehicles}
    weights = {e: float(sum(setup.count(v) for v in setup.vehicles if member[v] == e)) for e in edges}
    return FederationState(
        vehicle_models={v: model for v in setup.vehicles},
        edge_models={e: model for e in edges},
        edge_weights=weights,
        cloud_model=model,
        member=member,
        ready_s={v: start_s for v in setup.vehicles},
        open_s={k: start_s for k in (edges or (CLOUD,))},
        stage_one_done=setup.hyper.pretrain_batch == 0,
    )


# ------------------------------------------------------------------ one step


@dataclass(frozen=True)
class TransferEvent:
    """A simulated transfer: who, when, how much arrived."""

    start_s: float
    end_s: float
    ok: bool
    sent_bytes: float


def _wireline(start_s: float, size_bytes: int, cfg: WirelineConfig) -> TransferEvent:
    return TransferEvent(start_s, start_s + wireline_transfer_time_s(size_bytes, cfg), True, float(size_bytes))


def _wireless(outcome: WirelessOutcome) -> TransferEvent:
    return TransferEvent(outcome.start_s, outcome.end_s, outcome.ok, outcome.sent_bytes)


def _charge(
    ledger: Ledger,
    schedule: Sequence[Transfer],
    events: Mapping[tuple[str, str, str], TransferEvent],
    rule: str,
    cloud_round: int,
) -> bool:
    """Charge the schedule's transfers that happened, with their times; False when one does not fit.

    ``paper`` charges the schedule's size of every transfer that started,
    ``physical`` the bytes that crossed (fewer than the size for a failed
    transfer, or for a relay that lost some of its vehicles' samples).
    A transfer the schedule lists but that never started is not charged.
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
    return True


def _bytes_line(ledger: Ledger) -> dict:
    links = ledger.totals("link")
    return {
        "wireless_bytes": links["wireless"],
        "wireline_bytes": links["wireline"],
        "consumed_bytes": ledger.spent_bytes,
    }


class Federation:
    """Runs the loop of one setup on a clock with a trainer; ``step`` advances one aggregation step.

    ``data(vehicle, t_s)``: the samples a vehicle trains on when it starts
    training at ``t_s`` (default: its fixed shard, ``setup.samples``; the
    online data mode adds what it collected while driving).
    """

    def __init__(
        self, setup: LoopInputs, clock: Clock, trainer: Trainer, data: Callable[[str, float], Samples] | None = None
    ) -> None:
        self.setup = setup
        self.clock = clock
        self.trainer = trainer
        self.config = setup.config
        self.data = data or (lambda vehicle, t_s: setup.samples[vehicle])

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
        )
        ledger = Ledger(self.setup.sizes, state.records)
        hyper = self.setup.hyper
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
        state.records = list(ledger.records)
        state.steps += 1
        return state

    # -- pieces

    def _compute_s(self, samples: int, epochs: int) -> float:
        return epochs * samples * self.config.compute_s_per_sample

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
        if policy == "new_edge":
            return wireless_transfer(self.clock, vehicle, "edge", start_s, size, cfg)
        if policy == "wait":
            cfg = dataclasses.replace(cfg, on_outage="stall", max_outage_s=math.inf)
        else:  # miss: any time off its own edge fails the upload
            cfg = dataclasses.replace(cfg, on_outage="fail")
        return wireless_transfer(self.clock, vehicle, "edge", start_s, size, cfg, only_site=home)

    def _download(self, vehicle: str, start_s: float, size: int, edge: str | None) -> WirelessOutcome:
        """Edge -> vehicle (only while that edge serves it) or, for SFL (edge None), cloud -> vehicle."""
        if edge is None:
            return wireless_transfer(self.clock, vehicle, "macro", start_s, size, self.setup.transfer)
        site = self.setup.edges.index(edge)
        return wireless_transfer(self.clock, vehicle, "edge", start_s, size, self.setup.transfer, only_site=site)

    def _train(self, state: FederationState, epochs: int) -> tuple[dict[str, State], dict[str, int]]:
        """Every vehicle's model after ``epochs`` on its data, and the sample counts |T_nk| behind them."""
        vehicles = self.setup.vehicles
        samples = [self.data(v, state.ready_s[v]) for v in vehicles]
        seed = int(np.random.SeedSequence([self.config.seed, 1, state.steps]).generate_state(1)[0])
        new = self.trainer.train([state.vehicle_models[v] for v in vehicles], samples, epochs, seed)
        return dict(zip(vehicles, new)), {v: len(x) for v, x in zip(vehicles, samples)}

    def _line(self, state: FederationState, ledger: Ledger, stage: str, t_s: float, metrics=None, **extra) -> dict:
        loss, accuracy = metrics if metrics is not None else (None, None)
        line = {
            "step": state.steps + 1,
            "stage": stage,
            "cloud_round": state.cloud_rounds,
            "edge_aggregations": state.edge_aggregations,
            **_bytes_line(ledger),
            "sim_time_s": t_s,
            "loss": loss,
            "accuracy": accuracy,
            **extra,
        }
        state.metrics.append(line)
        return line

    def _evaluate_cloud(self, state: FederationState, ledger: Ledger, stage: str, t_s: float, **extra) -> None:
        loss, accuracy = self.trainer.evaluate(state.cloud_model)
        line = self._line(state, ledger, stage, t_s, (loss, accuracy), **extra)
        better = state.best is None or _better(accuracy, loss, state.best["accuracy"], state.best["loss"])
        if better:
            state.best, state.best_model = dict(line), state.cloud_model

    # -- stage I

    def _stage_one(self, state: FederationState, ledger: Ledger) -> None:
        setup, cfg, sizes = self.setup, self.config, self.setup.sizes
        counts = {v: setup.count(v) for v in setup.vehicles}
        shares = split_pretrain_batch(setup.hyper.pretrain_batch, counts)
        member = dict(state.member)
        events: dict[tuple[str, str, str], TransferEvent] = {}
        uploaded: dict[str, Samples] = {}
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
            events[(v, member[v], "uplink")] = _wireless(out)
            if out.ok:
                # the fixed uploaded subset: a seeded choice of the vehicle's samples
                rng = np.random.default_rng([cfg.seed, 2, i])
                uploaded[v] = setup.samples[v].subset(np.sort(rng.permutation(counts[v])[: shares[v]]))
            else:
                self._straggler(state, v, "I", out.reason, out.end_s)
        topology = self._topology(member)
        relay_end = {}
        for e, vehicles in topology.active():
            ends = [events[(v, e, "uplink")].end_s for v in vehicles if (v, e, "uplink") in events]
            if ends:
                n = sum(len(uploaded[v]) for v in vehicles if v in uploaded)
                events[(e, CLOUD, "uplink")] = _wireline(max(ends), n * sizes.sample_bytes, setup.wireline)
                relay_end[e] = events[(e, CLOUD, "uplink")].end_s
        start_s = max(relay_end.values(), default=max(state.ready_s.values()))
        n = sum(len(s) for s in uploaded.values())
        model = state.cloud_model
        if uploaded:
            parts = [uploaded[v] for v in setup.vehicles if v in uploaded]
            seed = int(np.random.SeedSequence([cfg.seed, 3]).generate_state(1)[0])
            model = self.trainer.train([state.cloud_model], [Samples.concat(parts)], cfg.pretrain_epochs, seed)[0]
        pretrained_s = start_s + cfg.pretrain_epochs * n * cfg.compute_s_per_sample
        # release: cloud -> every edge (wireline), edge -> its vehicles (wireless)
        ready, models, open_s = dict(state.ready_s), dict(state.vehicle_models), dict(state.open_s)
        for e, vehicles in topology.active():
            ev = _wireline(pretrained_s, sizes.model_bytes, setup.wireline)
            events[(CLOUD, e, "downlink")] = ev
            open_s[e] = ev.end_s
            for v in vehicles:
                out = self._download(v, ev.end_s, sizes.model_bytes, e)
                events[(e, v, "downlink")] = _wireless(out)
                ready[v] = out.end_s
                if out.ok:
                    models[v] = model
                else:
                    self._straggler(state, v, "I", f"download {out.reason}", out.end_s)
        received = {v: shares[v] for v in setup.vehicles}
        schedule = stage_one_schedule(setup.rule, cfg.scheme, topology, received, sizes)
        if not _charge(ledger, schedule, events, setup.rule, cloud_round=0):
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
        """Stage II: one edge aggregation; when it is the ``cloud_interval``-th, stage III follows."""
        setup, cfg, sizes = self.setup, self.config, self.setup.sizes
        followed = state.tau + 1 == setup.hyper.cloud_interval
        trained, counts = self._train(state, setup.hyper.edge_interval)
        events: dict[tuple[str, str, str], TransferEvent] = {}
        uploads, member = self._vehicle_uploads(state, counts)
        topology = self._topology(member)
        agg_s, received_by, edge_models, edge_weights = self._edge_fedavg(
            state, topology, uploads, trained, counts, events
        )
        edge_metrics = self._evaluate_edges(edge_models, edge_weights, agg_s) if cfg.evaluate_every_edge else None
        for e in agg_s:
            # the edge -> cloud upload: real when a cloud aggregation follows; the paper rule charges it every time
            events[(e, CLOUD, "uplink")] = _wireline(agg_s[e], sizes.model_bytes, setup.wireline)
        cloud_model, cloud_s, release_s = state.cloud_model, None, agg_s
        if followed:
            cloud_s = max(events[(e, CLOUD, "uplink")].end_s for e in agg_s)
            fresh = [(edge_models[e], edge_weights[e]) for e in agg_s if received_by[e]]
            cloud_model = fedavg(fresh) if fresh else state.cloud_model
            release_s = {}
            for e in agg_s:
                events[(CLOUD, e, "downlink")] = _wireline(cloud_s, sizes.model_bytes, setup.wireline)
                edge_models[e] = cloud_model
                release_s[e] = events[(CLOUD, e, "downlink")].end_s
        stage = "III" if followed else "II"
        models, ready, open_s = self._release(state, topology, release_s, edge_models, trained, events, stage)
        next_round = state.cloud_rounds + 1
        schedule = edge_aggregation_schedule(setup.rule, cfg.scheme, topology, sizes, followed_by_cloud=followed)
        if followed:
            schedule += cloud_aggregation_schedule(setup.rule, cfg.scheme, topology, sizes)
        if not _charge(ledger, schedule, events, setup.rule, cloud_round=next_round):
            state.stop_reason = "budget"
            return
        state.vehicle_models, state.ready_s, state.open_s, state.member = models, ready, open_s, member
        state.edge_models, state.edge_weights = edge_models, edge_weights
        state.edge_aggregations += 1
        state.tau += 1
        received = {e: len(vs) for e, vs in received_by.items()}
        t_s, samples = max(agg_s.values()), sum(counts.values())
        self._line(state, ledger, "II", t_s, edge_metrics, received=received, samples=samples)
        if followed:
            state.cloud_model = cloud_model
            state.cloud_rounds = next_round
            state.tau = 0
            self._evaluate_cloud(state, ledger, "III", cloud_s)

    def _vehicle_uploads(
        self, state: FederationState, counts: Mapping[str, int]
    ) -> tuple[dict[str, WirelessOutcome | None], dict[str, str]]:
        """Each vehicle's upload after its training, and the membership after them (``new_edge`` moves vehicles)."""
        setup, cfg = self.setup, self.config
        member = dict(state.member)
        uploads: dict[str, WirelessOutcome | None] = {}
        for v in setup.vehicles:
            edge = state.member[v]
            start_s = state.ready_s[v] + self._compute_s(counts[v], setup.hyper.edge_interval)
            out = self._upload(v, edge, start_s, setup.sizes.model_bytes, state.open_s[edge] + cfg.deadline_s)
            uploads[v] = out
            if out is not None and out.ok and cfg.handover_policy == "new_edge":
                member[v] = setup.edges[out.site]
        return uploads, member

    def _edge_fedavg(self, state, topology, uploads, trained, counts, events):
        """Each edge averages the models that arrived, once its members' uploads ended (at the latest, its deadline).

        Returns (aggregation time, received vehicles, edge models, edge weights) per edge; records the
        uploads in ``events`` and the stragglers in ``state``.
        """
        agg_s: dict[str, float] = {}
        received_by: dict[str, list[str]] = {}
        edge_models, edge_weights = dict(state.edge_models), dict(state.edge_weights)
        for e, vehicles in topology.active():
            ends, received = self._gather_uploads(
                state,
                {v: uploads[v] for v in vehicles},
                e,
                "II",
                lambda v: state.open_s[state.member[v]] + self.config.deadline_s,
                events,
            )
            agg_s[e] = max(ends)
            received_by[e] = received
            if received:
                edge_models[e] = fedavg([(trained[v], counts[v]) for v in received])
                edge_weights[e] = float(sum(counts[v] for v in received))
        return agg_s, received_by, edge_models, edge_weights

    def _release(self, state, topology, release_s, edge_models, trained, events, stage):
        """Each edge sends its model to its vehicles from ``release_s[edge]`` on.

        Returns the vehicles' models (a failed download leaves the vehicle its own trained model),
        the times they hold them, and the edges' new window openings.
        """
        models, ready, open_s = dict(trained), dict(state.ready_s), dict(state.open_s)
        size = self.setup.sizes.model_bytes
        for e, vehicles in topology.active():
            open_s[e] = release_s[e]
            for v in vehicles:
                out = self._download(v, release_s[e], size, e)
                events[(e, v, "downlink")] = _wireless(out)
                ready[v] = out.end_s
                if out.ok:
                    models[v] = edge_models[e]
                else:
                    self._straggler(state, v, stage, f"download {out.reason}", out.end_s)
        return models, ready, open_s

    def _evaluate_edges(self, models, weights, edges) -> tuple[float, float]:
        """Sample-weighted mean of the edge models' test Loss and Accuracy."""
        results = [(self.trainer.evaluate(models[e]), weights[e]) for e in edges]
        total = sum(w for _, w in results) or 1.0
        return (sum(m[0] * w for m, w in results) / total, sum(m[1] * w for m, w in results) / total)

    def _gather_uploads(self, state, uploads, receiver: str, stage: str, missed_at, events):
        """Arrival time of each vehicle's upload to ``receiver`` and the vehicles whose model arrived.

        An upload that could not start before the deadline (None) ends at
        ``missed_at(vehicle)``; it and every failed upload are recorded as
        stragglers. Started uploads are recorded in ``events``.
        """
        ends, received = [], []
        for v, out in uploads.items():
            if out is None:
                ends.append(missed_at(v))
                self._straggler(state, v, stage, "no time to upload before the deadline", ends[-1])
                continue
            events[(v, receiver, "uplink")] = _wireless(out)
            ends.append(out.end_s)
            if out.ok:
                received.append(v)
            else:
                self._straggler(state, v, stage, out.reason, out.end_s)
        return ends, received

    def _straggler(self, state: FederationState, vehicle: str, stage: str, reason: str, t_s: float) -> None:
        state.stragglers.append(
            {
                "step": state.steps + 1,
                "stage": stage,
                "cloud_round": 0 if stage == "I" else state.cloud_rounds + 1,
                "vehicle": vehicle,
                "reason": reason,
                "t_s": t_s,
            }
        )
        log.info("step %d: %s straggles (%s) at %.1f s", state.steps, vehicle, reason, t_s)

    # -- SFL

    def _sfl_round(self, state: FederationState, ledger: Ledger) -> None:
        setup, cfg, sizes = self.setup, self.config, self.setup.sizes
        epochs = setup.hyper.edge_interval
        trained, counts = self._train(state, epochs)
        window_end = state.open_s[CLOUD] + cfg.deadline_s
        events: dict[tuple[str, str, str], TransferEvent] = {}
        uploads = {
            v: self._upload(
                v, None, state.ready_s[v] + self._compute_s(counts[v], epochs), sizes.model_bytes, window_end
            )
            for v in setup.vehicles
        }
        ends, received = self._gather_uploads(state, uploads, CLOUD, "III", lambda v: window_end, events)
        cloud_s = max(ends)
        cloud_model = fedavg([(trained[v], counts[v]) for v in received]) if received else state.cloud_model
        models, ready = dict(trained), dict(state.ready_s)
        for v in setup.vehicles:
            out = self._download(v, cloud_s, sizes.model_bytes, None)
            events[(CLOUD, v, "downlink")] = _wireless(out)
            ready[v] = out.end_s
            if out.ok:
                models[v] = cloud_model
            else:
                self._straggler(state, v, "III", f"download {out.reason}", out.end_s)
        topology = Topology((SFL_LINK,), (setup.vehicles,))
        next_round = state.cloud_rounds + 1
        schedule = cloud_aggregation_schedule(setup.rule, "sfl", topology, sizes)
        if not _charge(ledger, schedule, events, setup.rule, next_round):
            state.stop_reason = "budget"
            return
        state.vehicle_models, state.ready_s = models, ready
        state.open_s = {CLOUD: cloud_s}
        state.cloud_model = cloud_model
        state.cloud_rounds = next_round
        self._evaluate_cloud(state, ledger, "III", cloud_s, received=len(received), samples=sum(counts.values()))


def _better(accuracy: float, loss: float, best_accuracy: float, best_loss: float) -> bool:
    """Higher Accuracy wins; equal Accuracy: lower Loss (NaN never wins)."""
    if math.isnan(accuracy):
        return False
    if math.isnan(best_accuracy) or accuracy > best_accuracy:
        return True
    return accuracy == best_accuracy and loss < best_loss


def sim_time_s(state: FederationState) -> float:
    """The latest simulated time the run reached (the last model's arrival)."""
    return max(list(state.ready_s.values()) + [r.end_s for r in state.records], default=0.0)
