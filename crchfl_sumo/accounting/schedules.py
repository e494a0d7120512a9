"""What each scheme sends: the transfers of stage I, of one edge aggregation, of one cloud aggregation and of a whole cloud round.

Pure functions of a scheme (``crchfl``/``hfl`` hierarchical, ``sfl`` vehicles
straight to the cloud), a topology and an accounting rule (``paper`` or
``physical``; the two rule sets are tabulated in docs/ledger.md). The
federation loop charges them (accounting/ledger.py) and problem P prices them
(planning/problem.py), so the two always agree on bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Literal, Mapping, Sequence

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.schemes import SCHEMES, SHAPES, Scheme

Rule = Literal["paper", "physical"]


Link = Literal["wireless", "wireline", "relay"]  # relay: edge -> edge, a download that followed its vehicle


Direction = Literal["uplink", "downlink"]


Stage = Literal["I", "II", "III"]


Payload = Literal["model", "samples"]


CLOUD = "cloud"


RULES = ("paper", "physical")


LINKS = ("wireless", "wireline", "relay")


STAGES = ("I", "II", "III")


@dataclass(frozen=True)
class ByteSizes:
    """What one model transfer and one sample cost, and the budget [bytes].

    ``vehicle_upload_bytes``: a vehicle's model upload (its wireless uplink), where an update codec
    compresses it apart from the other transfers ([federation] update_codec = "topk"); 0 = model_bytes.
    """

    model_bytes: int
    sample_bytes: int
    budget_bytes: int
    vehicle_upload_bytes: int = 0

    def __post_init__(self) -> None:
        for key in ("model_bytes", "sample_bytes", "budget_bytes"):
            if getattr(self, key) <= 0:
                raise CrchflError(f"{key} must be > 0, got {getattr(self, key)}")
        if self.vehicle_upload_bytes < 0:
            raise CrchflError(f"vehicle_upload_bytes must be >= 0, got {self.vehicle_upload_bytes}")

    def to_dict(self) -> dict[str, int]:
        """The sizes as files record them (without vehicle_upload_bytes when it is not set, as before it existed)."""
        out = {"model_bytes": self.model_bytes, "sample_bytes": self.sample_bytes, "budget_bytes": self.budget_bytes}
        return out | ({"vehicle_upload_bytes": self.vehicle_upload_bytes} if self.vehicle_upload_bytes else {})

    @property
    def upload_bytes(self) -> int:
        """A vehicle's model upload [bytes]."""
        return self.vehicle_upload_bytes or self.model_bytes

    @property
    def smallest_model_bytes(self) -> int:
        """The cheapest model transfer: what the stopping rule asks the budget to carry."""
        return min(self.model_bytes, self.upload_bytes)


@dataclass(frozen=True)
class Topology:
    """Which vehicles each edge server serves: ``vehicles[i]`` belong to ``edges[i]``.

    An edge that serves no vehicle in a round takes no part in it (no transfer).
    """

    edges: tuple[str, ...]
    vehicles: tuple[tuple[str, ...], ...]

    def __post_init__(self) -> None:
        if len(self.edges) != len(self.vehicles):
            raise CrchflError(f"topology: {len(self.edges)} edges but {len(self.vehicles)} vehicle groups")
        names = list(self.edges) + [v for group in self.vehicles for v in group]
        if len(set(names)) != len(names) or CLOUD in names or "" in names:
            raise CrchflError(f"topology: node names must be unique, non-empty and not {CLOUD!r}: {names}")
        if not self.all_vehicles:
            raise CrchflError("topology: no vehicles; at least one vehicle must take part")

    @classmethod
    def from_counts(cls, vehicles_per_edge: Sequence[int]) -> "Topology":
        """(2, 3) -> edges edge0, edge1 serving vehicles v0 v1 and v2 v3 v4."""
        if not vehicles_per_edge or any(n < 0 for n in vehicles_per_edge):
            raise CrchflError(f"vehicles_per_edge: needs non-negative counts, got {tuple(vehicles_per_edge)}")
        edges, groups, next_id = [], [], 0
        for i, count in enumerate(vehicles_per_edge):
            edges.append(f"edge{i}")
            groups.append(tuple(f"v{next_id + k}" for k in range(count)))
            next_id += count
        return cls(tuple(edges), tuple(groups))

    @property
    def all_vehicles(self) -> tuple[str, ...]:
        return tuple(v for group in self.vehicles for v in group)

    def active(self) -> tuple[tuple[str, tuple[str, ...]], ...]:
        """(edge, its vehicles) for the edges that serve at least one vehicle."""
        return tuple((e, vs) for e, vs in zip(self.edges, self.vehicles) if vs)


@dataclass(frozen=True)
class Transfer:
    """One planned transfer. Uplink = towards the cloud, downlink = away from it."""

    link: Link
    direction: Direction
    stage: Stage
    sender: str
    receiver: str
    payload: Payload
    size_bytes: int


def _model(link: Link, direction: Direction, stage: Stage, sender: str, receiver: str, sizes: ByteSizes) -> Transfer:
    # a wireless uplink carries a vehicle's upload (to its edge, or SFL's cloud)
    vehicle_upload = link == "wireless" and direction == "uplink"
    size = sizes.upload_bytes if vehicle_upload else sizes.model_bytes
    return Transfer(link, direction, stage, sender, receiver, "model", size)


def _check_rule_scheme(rule: str, scheme: str) -> None:
    if rule not in RULES:
        raise ValueError(f"unknown accounting rule {rule!r}")
    if scheme not in SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}")


def stage_one_schedule(
    rule: Rule,
    scheme: Scheme,
    topology: Topology,
    samples_per_vehicle: Mapping[str, int],
    sizes: ByteSizes,
) -> tuple[Transfer, ...]:
    """Stage I: pretraining samples to the cloud (and, physically, the pretrained model back).

    Hierarchical: each vehicle's samples over the wireless hop to its edge,
    then each edge relays its vehicles' samples over the wireline hop (both
    rules). ``physical`` adds the release of the pretrained model (cloud ->
    edge, edge -> vehicle); the reference did not charge it. SFL: one
    wireless hop vehicle -> cloud (both rules) and, physically, the release
    cloud -> vehicle. No samples: no transfer at all (every node starts from
    the same seeded initial model, which needs no transfer).
    """
    _check_rule_scheme(rule, scheme)
    unknown = sorted(set(samples_per_vehicle) - set(topology.all_vehicles))
    if unknown:
        raise ValueError(f"samples_per_vehicle names vehicles not in the topology: {unknown}")
    if any(n < 0 for n in samples_per_vehicle.values()):
        raise ValueError("samples_per_vehicle: counts must be >= 0")
    if sum(samples_per_vehicle.values()) == 0:
        return ()
    out: list[Transfer] = []
    if not SHAPES[scheme].edge_tier:
        for v in topology.all_vehicles:
            n = samples_per_vehicle.get(v, 0)
            if n:
                out.append(Transfer("wireless", "uplink", "I", v, CLOUD, "samples", n * sizes.sample_bytes))
        if rule == "physical":
            out += [_model("wireless", "downlink", "I", CLOUD, v, sizes) for v in topology.all_vehicles]
        return tuple(out)
    relays = []
    for edge, vehicles in topology.active():
        edge_total = 0
        for v in vehicles:
            n = samples_per_vehicle.get(v, 0)
            if n:
                out.append(Transfer("wireless", "uplink", "I", v, edge, "samples", n * sizes.sample_bytes))
                edge_total += n
        if edge_total:
            relays.append(Transfer("wireline", "uplink", "I", edge, CLOUD, "samples", edge_total * sizes.sample_bytes))
    out += relays
    if rule == "physical":
        out += [_model("wireline", "downlink", "I", CLOUD, e, sizes) for e, _ in topology.active()]
        out += [_model("wireless", "downlink", "I", e, v, sizes) for e, vs in topology.active() for v in vs]
    return tuple(out)


def edge_aggregation_schedule(
    rule: Rule, scheme: Scheme, topology: Topology, sizes: ByteSizes, *, followed_by_cloud: bool
) -> tuple[Transfer, ...]:
    """One edge aggregation (hierarchical schemes only).

    Both rules: every vehicle uploads its model to its edge (wireless, II).
    ``paper``: every edge then sends one model to the cloud side (wireline,
    III), whether or not a cloud aggregation follows. ``physical``: if no
    cloud aggregation follows, the edge sends its model down to its vehicles
    (wireless, II); if one follows, the edge -> cloud upload belongs to
    ``cloud_aggregation_schedule``.
    """
    _check_rule_scheme(rule, scheme)
    if not SHAPES[scheme].edge_tier:
        raise ValueError(f"{scheme} has no edge aggregation; use cloud_aggregation_schedule")
    out = [_model("wireless", "uplink", "II", v, e, sizes) for e, vs in topology.active() for v in vs]
    if rule == "paper":
        out += [_model("wireline", "uplink", "III", e, CLOUD, sizes) for e, _ in topology.active()]
    elif not followed_by_cloud:
        out += [_model("wireless", "downlink", "II", e, v, sizes) for e, vs in topology.active() for v in vs]
    return tuple(out)


def cloud_aggregation_schedule(rule: Rule, scheme: Scheme, topology: Topology, sizes: ByteSizes) -> tuple[Transfer, ...]:
    """One cloud aggregation and the release of the global model (stage III).

    Hierarchical: (``physical`` only: edge -> cloud, wireline), then
    cloud -> edge (wireline) and edge -> vehicle (wireless), one model each.
    SFL: vehicle -> cloud and cloud -> vehicle over the long-range wireless
    link, one model each, under both rules.
    """
    _check_rule_scheme(rule, scheme)
    if not SHAPES[scheme].edge_tier:
        up = [_model("wireless", "uplink", "III", v, CLOUD, sizes) for v in topology.all_vehicles]
        down = [_model("wireless", "downlink", "III", CLOUD, v, sizes) for v in topology.all_vehicles]
        return tuple(up + down)
    out: list[Transfer] = []
    if rule == "physical":
        out += [_model("wireline", "uplink", "III", e, CLOUD, sizes) for e, _ in topology.active()]
    out += [_model("wireline", "downlink", "III", CLOUD, e, sizes) for e, _ in topology.active()]
    out += [_model("wireless", "downlink", "III", e, v, sizes) for e, vs in topology.active() for v in vs]
    return tuple(out)


def cloud_round_schedule(
    rule: Rule, scheme: Scheme, topology: Topology, sizes: ByteSizes, cloud_interval: int
) -> tuple[Transfer, ...]:
    """Everything between two cloud aggregations: ``cloud_interval`` edge aggregations, then one cloud aggregation.

    SFL has no edge tier: its round is one cloud aggregation and
    ``cloud_interval`` must be 1.
    """
    if cloud_interval < 1:
        raise ValueError(f"cloud_interval must be >= 1, got {cloud_interval}")
    if not SHAPES[scheme].edge_tier:
        if cloud_interval != 1:
            raise ValueError(f"{scheme} has no edge tier: cloud_interval must be 1")
        return cloud_aggregation_schedule(rule, scheme, topology, sizes)
    out: list[Transfer] = []
    for tau in range(1, cloud_interval + 1):
        out += edge_aggregation_schedule(rule, scheme, topology, sizes, followed_by_cloud=tau == cloud_interval)
    out += cloud_aggregation_schedule(rule, scheme, topology, sizes)
    return tuple(out)


def schedule_bytes(transfers: Iterable[Transfer]) -> int:
    return sum(t.size_bytes for t in transfers)
