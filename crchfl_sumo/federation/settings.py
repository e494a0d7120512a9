"""The federation's settings: the scheme and its four hyper-parameters (TOML [federation]), and the values a run resolves them to.

No torch here: every config that names a federation reads this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Literal, get_args

from crchfl_sumo.core.config import OMIT_DEFAULT
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import (
    MAX_DRIVE_S,
    MAX_EPOCHS,
    MAX_SAMPLE_S,
    MAX_SAMPLES,
    MAX_SIMULATED_S,
    check_range,
    check_seed,
)
from crchfl_sumo.core.schemes import DISPLAY_NAMES, SCHEMES, SHAPES, Scheme
from crchfl_sumo.links.clock import DOWNLOAD_HANDOVERS, DownloadHandover

HandoverPolicy = Literal["new_edge", "forward", "wait", "miss"]

# Which vehicles train in an edge aggregation (federation/selection.py): every member of an edge, or
# all but those predicted to leave the cell their upload needs before their training and upload end.
ClientSelection = Literal["all", "skip_leaving"]
CLIENT_SELECTIONS: tuple[str, ...] = get_args(ClientSelection)


SFL_LINK = "macro"  # the pseudo-edge name of SFL's topology (the ledger needs one group)


# How a transfer carries a model (learning/codecs.py): whole, as an 8-bit difference, or a vehicle's top-k update.
UpdateCodec = Literal["none", "int8", "topk"]
UPDATE_CODECS: tuple[str, ...] = get_args(UpdateCodec)


# When an edge aggregates (federation/async_edges.py): once all its vehicles' uploads are in (or at the
# deadline), or, FedBuff-style, once ``async_buffer`` of them have arrived.
Aggregation = Literal["sync", "async"]
AGGREGATIONS: tuple[str, ...] = get_args(Aggregation)


# Default compute speed: the allocator's epoch_time_s (120 s) for the paper's largest shard (2928 samples).
DEFAULT_COMPUTE_S_PER_SAMPLE = 120.0 / 2928


@dataclass(frozen=True)
class FederationConfig:
    """The scheme and its four hyper-parameters (TOML table ``[federation]``).

    scheme: "crchfl" (stage I + hierarchy), "hfl" (hierarchy only), "sfl"
        (vehicles straight to the cloud).
    use_plan: CRCHFL only: ask the resource optimizer (planning.problem.make_plan)
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
        "forward" (it goes over whichever site serves the vehicle, and an edge
        it reaches that is not the vehicle's own forwards it over the wireline
        to that one, charged as link "relay"; the vehicle stays a member),
        "wait" (it is sent only while its own edge serves it, waiting out any
        time elsewhere, up to the deadline), "miss" (leaving its edge's
        coverage during the upload fails it: the vehicle misses that aggregation).
    download_handover: what an edge -> vehicle download does when another site
        takes the vehicle over: "relay" (the rest goes over the wireline to the
        new edge, which sends it on; charged as link "relay"), "restart" (the
        whole model is relayed and sent again), "drop" (it runs only while
        the sending edge serves the vehicle).
    selection: which vehicles train in an edge aggregation: "all" (every
        member, the paper) or "skip_leaving" (not those whose predicted time
        left in the cell their upload needs is shorter than their local
        training plus upload; they sit the aggregation out and still receive
        the model; federation/selection.py). Hierarchical schemes only.
    deadline_s: per aggregation: how long after its window opened an edge
        (or, in SFL, the cloud) waits for uploads [s]; inf = for all of them.
    compute_s_per_sample: simulated time of one sample of one local epoch on a
        vehicle, and of the cloud's pretraining [s].
    seed: seed of the initial model, the pretraining subset and the shuffling.
    update_codec: how transfers carry models (learning/codecs.py): "none" (whole, the paper), "int8"
        (every model transfer as its 8-bit difference from the last global model: about a quarter of
        the bytes) or "topk" (a vehicle's upload as the ``topk_fraction`` largest entries of its
        update, with error feedback; the rest whole). The ledger charges, and CRCHFL's optimizer
        plans with, the encoded sizes.
    topk_fraction: the share of each tensor's entries a "topk" upload keeps.
    aggregation: "sync" (the paper: an edge waits for its vehicles, or its deadline) or "async"
        (FedBuff-style, hierarchical schemes: an edge aggregates as soon as ``async_buffer`` updates
        have arrived, each weighted by ``(1 + staleness) ** -staleness_exponent``, the staleness
        counted in versions of the receiving edge's model; the cloud aggregates after every
        ``cloud_interval`` x edges edge aggregations; federation/async_edges.py).
    async_buffer: updates an asynchronous edge aggregates at once (at most its vehicles).
    staleness_exponent: the polynomial staleness weight's exponent (0: no discount; 0.5: FedBuff's).
    strategy: how aggregators turn what they received into their model and what local training adds
        (learning/strategies.py): "fedavg" (the paper), "fedavgm" (server momentum), "fedprox" (a
        proximal term in local training) or "package.module:Class" (your own).
    strategy_options: the strategy's options, e.g. {momentum = 0.9} or {proximal_mu = 0.01}.
    scheme_steps: "package.module:Class": your own sequence of the scheme's steps
        (federation/scheme_steps.py): ``Class(builtin)`` is given the scheme's built-in ``SchemeSteps``
        and answers ``next_step(state)``; "" (default) = the built-in.
    """

    scheme: Scheme = "crchfl"
    use_plan: bool = False
    pretrain_batch: int = 0
    edge_interval: int = 2
    cloud_interval: int = 1
    cloud_rounds: int = 0
    pretrain_epochs: int = 10
    evaluate_every_edge: bool = False
    handover_policy: HandoverPolicy = "new_edge"
    download_handover: DownloadHandover = "relay"
    selection: ClientSelection = "all"
    deadline_s: float = math.inf
    compute_s_per_sample: float = DEFAULT_COMPUTE_S_PER_SAMPLE
    seed: int = 0
    update_codec: UpdateCodec = "none"
    topk_fraction: float = 0.01
    aggregation: Aggregation = "sync"
    async_buffer: int = 2
    staleness_exponent: float = 0.5
    strategy: str = "fedavg"
    strategy_options: dict[str, float] = field(default_factory=dict)
    scheme_steps: str = field(default="", metadata={OMIT_DEFAULT: True})  # config.json of older runs: no key

    def __post_init__(self) -> None:
        if self.scheme not in SCHEMES:
            raise CrchflError(f"federation.scheme: {self.scheme!r} is not one of 'crchfl', 'hfl', 'sfl'")
        for key, value in self.strategy_options.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise CrchflError(f"federation.strategy_options.{key}: {value!r} is not a finite number")
        if self.aggregation not in AGGREGATIONS:
            raise CrchflError(f"federation.aggregation: {self.aggregation!r} is not one of 'sync', 'async'")
        check_range(self.async_buffer, "federation.async_buffer", 1, MAX_SAMPLES, "a number of updates")
        check_range(self.staleness_exponent, "federation.staleness_exponent", 0, 10, "an exponent")
        if self.aggregation == "async":
            self._check_async()
        if self.update_codec not in UPDATE_CODECS:
            raise CrchflError(
                f"federation.update_codec: {self.update_codec!r} is not one of {', '.join(map(repr, UPDATE_CODECS))}"
            )
        check_range(self.topk_fraction, "federation.topk_fraction", 0, 1, "a share of the entries", lo_open=True)
        shape, name = SHAPES[self.scheme], DISPLAY_NAMES[self.scheme]
        if self.handover_policy not in get_args(HandoverPolicy):
            raise CrchflError(
                f"federation.handover_policy: {self.handover_policy!r} is not one of 'new_edge', 'forward', 'wait', 'miss'"
            )
        if self.download_handover not in DOWNLOAD_HANDOVERS:
            raise CrchflError(
                f"federation.download_handover: {self.download_handover!r} is not one of 'relay', 'restart', 'drop'"
            )
        if self.selection not in CLIENT_SELECTIONS:
            raise CrchflError(
                f"federation.selection: {self.selection!r} is not one of "
                f"{', '.join(repr(name) for name in CLIENT_SELECTIONS)}"
            )
        if self.selection != "all" and not shape.edge_tier:
            raise CrchflError(
                f"federation.selection = {self.selection!r} predicts the time left in an edge cell; {name} has no "
                "edge tier: set selection = \"all\" or use crchfl/hfl"
            )
        if self.use_plan and not shape.planned:
            raise CrchflError(f"federation.use_plan: only CRCHFL asks the optimizer; set use_plan = false for {name}")
        if self.use_plan:
            # The plan replaces these four: a value set beside it would be ignored (a sweep over one would
            # run the same plan at every point), so it is refused. One set to its default is not seen.
            defaults = {f.name: f.default for f in fields(self)}
            for key in PLANNED_BY_THE_OPTIMIZER:
                if getattr(self, key) != defaults[key]:
                    raise CrchflError(
                        f"federation.{key}: {getattr(self, key)} is not used with use_plan = true (the optimizer "
                        f"picks {', '.join(PLANNED_BY_THE_OPTIMIZER)}); remove it, or set use_plan = false to choose "
                        "all four yourself (allocation.fix_edge_interval fixes edge_interval inside the plan)"
                    )
        check_range(self.pretrain_batch, "federation.pretrain_batch", 0, MAX_SAMPLES,
                    "a number of samples (0 = no stage I)")
        if self.pretrain_batch > 0 and not shape.pretraining:
            raise CrchflError(
                f"federation.pretrain_batch: {name} has no pretraining stage; set it to 0 or use crchfl"
            )
        check_range(self.edge_interval, "federation.edge_interval", 1, MAX_EPOCHS, "a number of local epochs")
        check_range(self.cloud_interval, "federation.cloud_interval", 1, MAX_EPOCHS, "a number of edge aggregations")
        if not shape.edge_tier and self.cloud_interval != 1:
            raise CrchflError(f"federation.cloud_interval: {name} has no edge tier; set cloud_interval = 1")
        check_range(self.cloud_rounds, "federation.cloud_rounds", 0, MAX_EPOCHS,
                    "a number of rounds (0 = until the budget is spent)")
        check_range(self.pretrain_epochs, "federation.pretrain_epochs", 1, MAX_EPOCHS, "a number of epochs")
        # an aggregation waits at most a simulated day (the longest a command simulates); inf waits for every upload
        check_range(self.deadline_s, "federation.deadline_s", 0, MAX_SIMULATED_S,
                    "simulated seconds (or inf: no deadline)", lo_open=True, inf_ok=True)
        if self.handover_policy == "wait" and not math.isfinite(self.deadline_s):
            raise CrchflError(
                "federation.handover_policy = 'wait' waits for the vehicle's own edge until the aggregation "
                "deadline; set a finite federation.deadline_s"
            )
        check_range(self.compute_s_per_sample, "federation.compute_s_per_sample", 0, MAX_SAMPLE_S,
                    "simulated seconds a sample")

    @property
    def hierarchical(self) -> bool:
        """Vehicles reach the cloud through edges (core.schemes.SchemeShape.edge_tier)."""
        return SHAPES[self.scheme].edge_tier

    def _check_async(self) -> None:
        """What asynchronous edges do not combine with: each refused by its key."""
        refusals = {
            "scheme": (not self.hierarchical, "it has no edges to aggregate asynchronously; use hfl or crchfl"),
            "deadline_s": (math.isfinite(self.deadline_s),
                           "an asynchronous edge waits for no deadline (staleness weights late updates); remove it"),
            "handover_policy": (self.handover_policy == "wait", "'wait' needs a deadline; use new_edge, forward or miss"),
            "selection": (self.selection != "all", "client selection predicts a synchronous window; use \"all\""),
            "update_codec": (self.update_codec != "none", "compressed transfers assume synchronous rounds; use \"none\""),
            "strategy": (self.strategy != "fedavg", "asynchronous edges weight by staleness; use \"fedavg\""),
            "strategy_options": (bool(self.strategy_options), "an asynchronous edge takes every update that arrives; "
                                 "remove them"),
        }
        for key, (refused, why) in refusals.items():
            if refused:
                raise CrchflError(f"federation.{key}: {getattr(self, key)!r} with aggregation = \"async\": {why}")


@dataclass(frozen=True)
class VehicleDaggerConfig:
    """DAgger on the vehicles (TOML table ``[dagger]``): each vehicle carries the route expert.

    After every ``every_cloud_rounds``-th cloud round, each federated vehicle drives the model it
    holds (the global model it received, or its own where the download failed) on ``episodes``
    routes per task of its own town; the expert labels the states that model visits, as
    `crchfl-sumo dagger` does for one model (driving/dagger.py). The labels stay on the vehicle:
    from then on it trains on its shard and on every round's labels, and only models cross the
    links, charged as before. 0 = off (the paper).

    tasks: drive-bench suites the routes are drawn from; seed: draws them (with the run's seed,
    the round and the vehicle); every: one labelled state every this many steps; max_s: a drive's
    longest simulated time; corrections_only: keep only the states where the expert would step in.
    The drives take no simulated time of the run: the vehicle collects while it drives, as the
    online data mode does.
    """

    every_cloud_rounds: int = 0
    episodes: int = 2
    tasks: tuple[str, ...] = ("navigation_traffic",)
    seed: int = 1000
    every: int = 2
    max_s: float = 90.0
    corrections_only: bool = True

    def __post_init__(self) -> None:
        check_range(self.every_cloud_rounds, "dagger.every_cloud_rounds", 0, MAX_EPOCHS,
                    "a number of cloud rounds (0 = off)")
        check_range(self.episodes, "dagger.episodes", 1, 10_000, "a number of drives per task")
        if not self.tasks:
            raise CrchflError("dagger.tasks: empty; name at least one drive-bench task, e.g. [\"navigation_traffic\"]")
        check_seed(self.seed, "dagger.seed")
        check_range(self.every, "dagger.every", 1, 10_000, "a number of steps")
        check_range(self.max_s, "dagger.max_s", 0, MAX_DRIVE_S, "simulated seconds", lo_open=True)

    @property
    def enabled(self) -> bool:
        return self.every_cloud_rounds > 0

    def due(self, cloud_round: int) -> bool:
        """Do the vehicles drive and label after cloud round ``cloud_round``?"""
        return self.enabled and cloud_round > 0 and cloud_round % self.every_cloud_rounds == 0


@dataclass(frozen=True)
class HyperParameters:
    """The four hyper-parameters a run uses (from the config or from the optimizer's plan)."""

    pretrain_batch: int
    edge_interval: int
    cloud_interval: int
    cloud_rounds: int  # 0 = until the budget is spent


# The four hyper-parameters of the paper's problem P: with use_plan the optimizer's, else the config's.
PLANNED_BY_THE_OPTIMIZER = tuple(f.name for f in fields(HyperParameters))
