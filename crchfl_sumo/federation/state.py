"""What the loop is given (LoopInputs), what it needs from learning (Trainer), and all it remembers (FederationState: a checkpoint stores exactly this).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Collection, Iterable, Literal, Mapping, Protocol, Sequence

import torch

from crchfl_sumo.accounting.ledger import Record
from crchfl_sumo.accounting.schedules import (
    CLOUD,
    ByteSizes,
)
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.settings import SFL_LINK, FederationConfig, HyperParameters, VehicleDaggerConfig
from crchfl_sumo.learning.model import State
from crchfl_sumo.learning.strategies import FedAvg, Strategy
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.fleet import Fleet
from crchfl_sumo.links.mobility import NO_SITE
from crchfl_sumo.links.residence import Coverage
from crchfl_sumo.links.transfer import TransferConfig


class Trainer(Protocol):
    """What the loop needs from learning; models are state dicts."""

    def initial_state(self) -> State: ...

    def train(
        self, states: Sequence[State], samples: Sequence[Samples], epochs: int, seed: int,
        needed: Collection[int] | None = None,
    ) -> Iterable[State | None]:
        """Each vehicle's new state, in the order of ``states``. An iterator that yields each as it is
        trained lets the loop fold it into its FedAvg and drop it before the next arrives.

        ``needed``: the indices whose states the loop will use (None: all). A trainer may skip the others
        and yield None in their place (a model whose upload failed and that a download replaces is never
        read); vehicle i's state must not depend on which others were trained."""
        ...

    def evaluate(self, state: State) -> Mapping[str, Any]:
        """Test-set metrics: at least ``loss`` and ``accuracy``; every key goes into the metric line.

        The loop ranks models by ``balanced_accuracy`` where the metrics carry it.
        """
        ...


class Labeller(Protocol):
    """The vehicles' route experts ([dagger], federation.settings.VehicleDaggerConfig): what the loop needs
    from driving, which builds it (driving/vehicle_dagger.py)."""

    def label(self, cloud_round: int, models: Mapping[str, State]) -> Mapping[str, Samples]:
        """Each vehicle drives its model of ``models``; the expert's labels of the states it visited, per
        vehicle. Called once per round; a labeller that kept a round's labels returns them without driving."""
        ...

    def labelled(self, cloud_round: int) -> Mapping[str, Samples]:
        """The labels ``label`` gave for ``cloud_round`` (a resumed run reads them back)."""
        ...


@dataclass(frozen=True)
class LoopInputs:
    """Everything fixed for one run: who takes part, sizes, links.

    vehicles: the federated vehicles in a fixed order (their training seeds
    follow it); home_site: each vehicle's edge site index at the start;
    edges: edge site names (index = site index); coverage: where those sites
    stand and how far they reach (client selection predicts from it; None:
    no geometry, as on the constant clock, so no vehicle is predicted to leave).
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
    coverage: Coverage | None = None
    budget_marks_bytes: tuple[int, ...] = ()  # [ledger] marks_gb in bytes: the best model within each is kept
    dagger: VehicleDaggerConfig = VehicleDaggerConfig()  # when the vehicles drive and label (off: never)
    fleet: Fleet = field(default_factory=Fleet)  # each vehicle's compute speed and off periods (links/fleet.py)
    strategy: Strategy = field(default_factory=FedAvg)  # how aggregators update (learning/strategies.py)

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

        if self.coverage is not None and len(self.coverage.sites_xy_m) != len(self.edges):
            raise CrchflError(
                f"coverage: {len(self.coverage.sites_xy_m)} site positions for {len(self.edges)} edges "
                f"{list(self.edges)}; give one per edge"
            )

    def count(self, vehicle: str) -> int:
        return len(self.samples[vehicle])


@dataclass
class FederationState:
    """All the loop remembers.

    member: vehicle -> edge name it belongs to now; ready_s: when each vehicle
    holds its current model; open_s: per edge (or the cloud, SFL) when its
    current aggregation window opened; steps: steps done (the training seed
    of step k derives from it).

    The loop reads only the counters: ``ledger_totals`` (Ledger.byte_totals)
    and ``transfers_end_s`` stand for the records; ``records``, ``metrics``
    and ``stragglers`` are the run's history, which the loop only appends to.
    A checkpoint stores everything but that history (``to_payload``); the
    run's append-only logs hold it.
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
    ledger_totals: dict[str, dict[str, int]] = field(default_factory=dict)  # bytes charged so far
    transfers_end_s: float = 0.0  # the latest end of a charged transfer
    # wireless transfers that started: downloads, uploads, each *_failed; relayed_transfers: downloads relayed
    transfers: dict[str, int] = field(default_factory=dict)
    skipped: int = 0  # vehicle-aggregations that client selection left out (federation/selection.py)
    wasted_bytes: int = 0  # charged to wireless transfers whose payload was not used (failed, or arrived too late)
    records: list[Record] = field(default_factory=list)
    metrics: list[dict] = field(default_factory=list)
    stragglers: list[dict] = field(default_factory=list)
    best_model: State | None = None
    best: dict | None = None  # metrics line of the best cloud model
    stop_reason: str | None = None
    # per budget mark (str of its bytes, LoopInputs.budget_marks_bytes) the run has passed: the best metrics line
    # and model among the evaluations within it (None: no evaluation was); a mark not yet passed is the best
    budget_marks: dict[str, dict | None] = field(default_factory=dict)
    budget_mark_models: dict[str, State] = field(default_factory=dict)
    dagger_rounds: list[int] = field(default_factory=list)  # the cloud rounds after which the vehicles labelled
    residuals: dict[str, State] = field(default_factory=dict)  # what each vehicle's topk uploads left out
    train_s: dict[str, float] = field(default_factory=dict)  # each vehicle's training time so far, at its own speed
    # asynchronous edges (federation/async_edges.py): when each vehicle's model was released to it, and the times
    # each edge's model changed (its aggregations and the cloud's releases), which count an update's staleness
    base_s: dict[str, float] = field(default_factory=dict)
    edge_history: dict[str, list[float]] = field(default_factory=dict)
    strategy_memory: dict[str, State] = field(default_factory=dict)  # what the strategy keeps at each aggregator

    @property
    def done(self) -> bool:
        return self.stop_reason is not None

    def to_payload(self) -> dict:
        """The state less its history: plain tensors and JSON-like values (torch.load(weights_only=True) reads it)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in HISTORY}

    @classmethod
    def from_payload(
        cls, payload: Mapping, records: list[Record], metrics: list[dict], stragglers: list[dict]
    ) -> "FederationState":
        return cls(**payload, records=records, metrics=metrics, stragglers=stragglers)


HISTORY = ("records", "metrics", "stragglers")  # what the loop appends to and never reads back
MODELS = ("vehicle_models", "edge_models", "budget_mark_models", "residuals", "strategy_memory")  # name -> State (cloud_model, best_model: one)
ADDED_LATER = ("budget_marks", "budget_mark_models", "dagger_rounds", "residuals", "train_s", "base_s",
               "edge_history", "strategy_memory")  # an older checkpoint lacks them: empty


def check_payload(payload: Any, where: str) -> None:
    """Refuse a checkpointed state (``to_payload``) that ``from_payload`` could not use: a key missing or
    unknown, a value of the wrong type, a model that is not a table of dense tensors."""
    fix = "delete the folder to start afresh"
    if not isinstance(payload, Mapping):
        raise CrchflError(f"{where}: malformed federation checkpoint (its state is not a table); {fix}")
    expected = [f.name for f in dataclasses.fields(FederationState) if f.name not in HISTORY]
    missing = sorted(set(expected) - set(payload) - set(ADDED_LATER))
    unknown = sorted(set(payload) - set(expected))
    if missing or unknown:
        raise CrchflError(
            f"{where}: malformed federation checkpoint (state {'lacks ' + ', '.join(missing) if missing else ''}"
            f"{' and ' if missing and unknown else ''}{'has unknown ' + ', '.join(unknown) if unknown else ''}); {fix}"
        )
    hints = typing.get_type_hints(FederationState)
    for name in expected:
        if name not in payload:  # one of ADDED_LATER: from_payload gives its default
            continue
        value = payload[name]
        if name in MODELS:
            ok = isinstance(value, dict) and all(isinstance(k, str) and _is_state(m) for k, m in value.items())
        elif name in ("cloud_model", "best_model"):
            ok = _is_state(value) or (name == "best_model" and value is None)
        else:
            ok = _is_plain(hints[name], value)
        if not ok:
            raise CrchflError(f"{where}: malformed federation checkpoint (state.{name} has the wrong type); {fix}")


def _is_state(value: Any) -> bool:
    """A model's weights: a table of named dense tensors."""
    return isinstance(value, dict) and all(
        isinstance(k, str) and isinstance(t, torch.Tensor) and t.layout == torch.strided for k, t in value.items()
    )


def _is_plain(hint: Any, value: Any) -> bool:
    """``value`` fits the field type ``hint`` (a table's keys and values too, where the hint names them)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_is_plain(a, value) for a in args)
    if origin is dict and args:
        return isinstance(value, dict) and all(_is_plain(args[0], k) and _is_plain(args[1], v) for k, v in value.items())
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is Any:
        return True
    kind = origin or hint
    return isinstance(value, kind) if isinstance(kind, type) else True


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


def sim_time_s(state: FederationState) -> float:
    """The latest simulated time the run reached (the last model's arrival)."""
    return max([*state.ready_s.values(), state.transfers_end_s])
