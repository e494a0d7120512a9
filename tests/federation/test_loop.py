"""The federation loop on scripted clocks with a toy trainer: counts, charges, FedAvg, policies
(and a real one: averages folded in as the models come equal the batch FedAvg)."""

from __future__ import annotations

import dataclasses
import math
import weakref

import numpy as np
import pytest
import torch

from crchfl_sumo.accounting.ledger import MIB, Ledger, LedgerConfig, replay, resolve_sizes
from crchfl_sumo.accounting.schedules import CLOUD, Topology, cloud_round_schedule
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.loop import Federation
from crchfl_sumo.federation.settings import FederationConfig, HyperParameters
from crchfl_sumo.federation.state import LoopInputs, initial_state
from crchfl_sumo.learning.aggregate import weighted_average
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.clock import ScriptedClock, Segment, wireless_transfer
from crchfl_sumo.links.fleet import Fleet
from crchfl_sumo.links.transfer import TransferConfig
from crchfl_sumo.planning.problem import make_plan
from crchfl_sumo.planning.settings import AllocationConfig


class SumTrainer:
    """A model is one tensor; training adds epochs x samples, so every state records its history."""

    def initial_state(self):
        return {"w": torch.zeros(2, dtype=torch.float64)}

    def train(self, states, samples, epochs, seed, needed=None):
        return [{"w": s["w"] + epochs * len(x)} for s, x in zip(states, samples)]

    def evaluate(self, state):
        total = float(state["w"].sum())
        return {"loss": 1.0 / (1.0 + total), "accuracy": total / (1.0 + total)}


class FixedTrainer(SumTrainer):
    """Training sets each vehicle's model to a fixed value (by its sample count), for hand-computed FedAvg."""

    def __init__(self, values_by_count):
        self.values = values_by_count

    def train(self, states, samples, epochs, seed, needed=None):
        return [{"w": torch.full((2,), float(self.values[len(x)]), dtype=torch.float64)} for x in samples]


def _samples(n: int) -> Samples:
    return Samples.from_numpy(
        np.zeros((n, 4, 1, 1, 3), np.uint8), np.zeros((n, 3), np.float32), np.zeros(n, np.int64), np.zeros(n),
        np.zeros(n), np.zeros(n),
    )


PAPER_HOME = {"a": 0, "b": 0, "c": 1, "d": 1, "e": 1}  # 2 vehicles in town 1, 3 in town 2


def _setup(config, hyper, counts, home, *, rule="paper", ledger=LedgerConfig(), transfer=TransferConfig(), edges=("e0", "e1")):
    return LoopInputs(
        config=config,
        hyper=hyper,
        vehicles=tuple(counts),
        samples={v: _samples(n) for v, n in counts.items()},
        home_site=home,
        edges=edges,
        sizes=resolve_sizes(ledger),
        rule=rule,
        wireline=WirelineConfig(),
        transfer=transfer,
    )


def _run(setup, clock, trainer=None):
    trainer = trainer or SumTrainer()
    return Federation(setup, clock, trainer).run(initial_state(setup, trainer, clock.start_s))


def _hyper(config):
    return HyperParameters(config.pretrain_batch, config.edge_interval, config.cloud_interval, config.cloud_rounds)


# ------------------------------------------------------------------ the paper's round counts


@pytest.mark.parametrize("scheme, expected", [("sfl", 13), ("hfl", 9)])
def test_paper_rule_20_gb_gives_sfl_13_and_hfl_9_cloud_rounds(scheme, expected):
    config = FederationConfig(scheme=scheme, edge_interval=2)
    setup = _setup(config, _hyper(config), {v: 3 for v in PAPER_HOME}, PAPER_HOME)
    state = _run(setup, ScriptedClock.constant(PAPER_HOME, 20e6, macro_rate_bps=10e6))
    assert state.cloud_rounds == expected
    assert state.stop_reason == "budget"
    ledger = Ledger(setup.sizes, state.records)
    assert not ledger.can_carry_model()
    # The loop spent exactly what replaying the ledger's schedule spends.
    reference = Ledger(setup.sizes)
    topology = Topology.from_counts((2, 3))
    assert replay(reference, (), cloud_round_schedule("paper", scheme, topology, setup.sizes, 1)) == expected
    assert ledger.spent_bytes == reference.spent_bytes
    assert ledger.totals("link") == reference.totals("link")


def test_crchfl_with_the_paper_plan_gives_9_cloud_rounds():
    plan = make_plan(AllocationConfig(), LedgerConfig())
    config = FederationConfig(
        scheme="crchfl", pretrain_batch=plan.pretrain_batch, edge_interval=plan.edge_interval,
        cloud_interval=plan.cloud_interval, pretrain_epochs=1,
    )
    setup = _setup(config, _hyper(config), {v: 100 for v in PAPER_HOME}, PAPER_HOME)
    state = _run(setup, ScriptedClock.constant(PAPER_HOME, 20e6))
    assert state.cloud_rounds == plan.cloud_rounds == 9
    ledger = Ledger(setup.sizes, state.records)
    assert ledger.totals("stage") == plan.stage_bytes
    assert state.metrics[0]["stage"] == "I" and state.metrics[0]["pretrain_samples"] == plan.pretrain_batch


def test_cloud_rounds_limit_stops_before_the_budget():
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_interval=2, cloud_rounds=2)
    setup = _setup(config, _hyper(config), {v: 2 for v in PAPER_HOME}, PAPER_HOME)
    state = _run(setup, ScriptedClock.constant(PAPER_HOME, 20e6))
    assert (state.cloud_rounds, state.edge_aggregations, state.stop_reason) == (2, 4, "cloud_rounds")
    assert [m["stage"] for m in state.metrics] == ["II", "II", "III", "II", "II", "III"]
    assert all(m["loss"] is None for m in state.metrics if m["stage"] == "II")  # evaluate_every_edge is off


# ------------------------------------------------------------------ one round's charges, by hand

# Small numbers for hand computation: 1 MiB models, 8 Mbit/s wireless (1 MiB takes 1.048576 s),
# 1 Gbit/s + 10 ms wireline (1 MiB takes 0.018388608 s), 2 samples at 0.5 s each: 1 s per epoch.
SMALL = LedgerConfig(nominal_model_mb=1.0, nominal_sample_kb=512.0, budget_gb=1.0)
HOME3 = {"a": 0, "b": 0, "c": 1}
WIRELESS_S = 8 * MIB / 8e6
WIRELINE_S = 8 * MIB / 1e9 + 0.010


def _one_round(scheme, rule, pretrain_batch=0):
    config = FederationConfig(
        scheme=scheme, pretrain_batch=pretrain_batch, edge_interval=1, cloud_rounds=1,
        compute_s_per_sample=0.5, pretrain_epochs=1,
    )
    setup = _setup(config, _hyper(config), {"a": 2, "b": 2, "c": 2}, HOME3, rule=rule, ledger=SMALL)
    return _run(setup, ScriptedClock.constant(HOME3, 8e6, step_s=0.25, macro_rate_bps=8e6))


def _rows(state):
    return [(r.link, r.direction, r.stage, r.sender, r.receiver, r.payload, r.size_bytes) for r in state.records]


M = MIB


def test_hfl_round_paper_rule_charges_by_hand():
    state = _one_round("hfl", "paper")
    assert _rows(state) == [
        ("wireless", "uplink", "II", "a", "e0", "model", M),
        ("wireless", "uplink", "II", "b", "e0", "model", M),
        ("wireless", "uplink", "II", "c", "e1", "model", M),
        ("wireline", "uplink", "III", "e0", CLOUD, "model", M),
        ("wireline", "uplink", "III", "e1", CLOUD, "model", M),
        ("wireline", "downlink", "III", CLOUD, "e0", "model", M),
        ("wireline", "downlink", "III", CLOUD, "e1", "model", M),
        ("wireless", "downlink", "III", "e0", "a", "model", M),
        ("wireless", "downlink", "III", "e0", "b", "model", M),
        ("wireless", "downlink", "III", "e1", "c", "model", M),
    ]
    # times: 1 s training, then uploads; the edges aggregate at the last arrival, the cloud after the wireline hops
    up_end = 1.0 + WIRELESS_S
    cloud_s = up_end + WIRELINE_S
    times = [(r.start_s, r.end_s) for r in state.records]
    assert times[0] == pytest.approx((1.0, up_end))
    assert times[3] == pytest.approx((up_end, cloud_s))
    assert times[5] == pytest.approx((cloud_s, cloud_s + WIRELINE_S))
    assert times[7] == pytest.approx((cloud_s + WIRELINE_S, cloud_s + WIRELINE_S + WIRELESS_S))
    assert state.metrics[-1]["sim_time_s"] == pytest.approx(cloud_s)
    assert state.metrics[-1]["consumed_bytes"] == 10 * M
    assert state.metrics[-1]["wireline_bytes"] == 4 * M


def test_hfl_round_physical_rule_with_two_edge_aggregations_charges_by_hand():
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_interval=2, cloud_rounds=1, compute_s_per_sample=0.5)
    setup = _setup(config, _hyper(config), {"a": 2, "b": 2, "c": 2}, HOME3, rule="physical", ledger=SMALL)
    state = _run(setup, ScriptedClock.constant(HOME3, 8e6, step_s=0.25))
    up = [("wireless", "uplink", "II", v, e, "model", M) for v, e in (("a", "e0"), ("b", "e0"), ("c", "e1"))]
    down_ii = [("wireless", "downlink", "II", e, v, "model", M) for v, e in (("a", "e0"), ("b", "e0"), ("c", "e1"))]
    assert _rows(state) == up + down_ii + up + [
        ("wireline", "uplink", "III", "e0", CLOUD, "model", M),
        ("wireline", "uplink", "III", "e1", CLOUD, "model", M),
        ("wireline", "downlink", "III", CLOUD, "e0", "model", M),
        ("wireline", "downlink", "III", CLOUD, "e1", "model", M),
        ("wireless", "downlink", "III", "e0", "a", "model", M),
        ("wireless", "downlink", "III", "e0", "b", "model", M),
        ("wireless", "downlink", "III", "e1", "c", "model", M),
    ]
    # the second edge window starts when the edge model arrived back: 1 s + up + down, then 1 s training
    second_start = 1.0 + WIRELESS_S + WIRELESS_S + 1.0
    assert state.records[6].start_s == pytest.approx(second_start)


def test_sfl_round_charges_by_hand():
    state = _one_round("sfl", "paper")
    assert _rows(state) == [("wireless", "uplink", "III", v, CLOUD, "model", M) for v in "abc"] + [
        ("wireless", "downlink", "III", CLOUD, v, "model", M) for v in "abc"
    ]
    assert state.edge_aggregations == 0 and state.cloud_rounds == 1


@pytest.mark.parametrize("rule", ["paper", "physical"])
def test_crchfl_stage_one_charges_by_hand(rule):
    state = _one_round("crchfl", rule, pretrain_batch=3)
    s = 512 * 1024
    stage_one = [r for r in _rows(state) if r[2] == "I"]
    # split 3 samples over (2, 2, 2) by largest remainder: a 1, b 1, c 1
    expected = [
        ("wireless", "uplink", "I", "a", "e0", "samples", s),
        ("wireless", "uplink", "I", "b", "e0", "samples", s),
        ("wireless", "uplink", "I", "c", "e1", "samples", s),
        ("wireline", "uplink", "I", "e0", CLOUD, "samples", 2 * s),
        ("wireline", "uplink", "I", "e1", CLOUD, "samples", s),
    ]
    if rule == "physical":
        expected += [
            ("wireline", "downlink", "I", CLOUD, "e0", "model", M),
            ("wireline", "downlink", "I", CLOUD, "e1", "model", M),
            ("wireless", "downlink", "I", "e0", "a", "model", M),
            ("wireless", "downlink", "I", "e0", "b", "model", M),
            ("wireless", "downlink", "I", "e1", "c", "model", M),
        ]
    assert stage_one == expected
    assert state.records[0].cloud_round == 0
    # the pretrained model (3 samples x 1 epoch) reached every vehicle before stage II
    assert state.metrics[0]["pretrain_samples"] == 3


# ------------------------------------------------------------------ FedAvg inside the loop


def test_edge_and_cloud_fedavg_weight_by_sample_counts():
    # a (1 sample) -> 1, b (3) -> 5 on e0; c (2) -> 10 on e1
    home = {"a": 0, "b": 0, "c": 1}
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=1, compute_s_per_sample=0.0)
    setup = _setup(config, _hyper(config), {"a": 1, "b": 3, "c": 2}, home, ledger=SMALL)
    state = _run(setup, ScriptedClock.constant(home, 8e6), FixedTrainer({1: 1.0, 3: 5.0, 2: 10.0}))
    e0 = (1 * 1 + 3 * 5) / 4
    assert state.edge_weights == {"e0": 4.0, "e1": 2.0}
    assert state.cloud_model["w"].tolist() == [pytest.approx((4 * e0 + 2 * 10) / 6)] * 2
    assert all(m["w"].tolist() == state.cloud_model["w"].tolist() for m in state.vehicle_models.values())


class CountingTrainer(SumTrainer):
    """Yields each model when it is asked for (as TorchTrainer and RayTrainer do) and counts how many of
    the models it yielded are still alive anywhere."""

    def __init__(self):
        self.alive = self.peak = 0

    def _dropped(self):
        self.alive -= 1

    def train(self, states, samples, epochs, seed, needed=None):
        for s, x in zip(states, samples):
            w = s["w"] + epochs * len(x)
            self.alive += 1
            self.peak = max(self.peak, self.alive)
            weakref.finalize(w, self._dropped)
            yield {"w": w}


@pytest.mark.parametrize("scheme", ["hfl", "sfl"])
def test_the_loop_drops_each_trained_model_once_it_is_averaged(scheme):
    counts = {f"v{i}": i + 1 for i in range(8)}
    home = {v: i % 2 for i, v in enumerate(counts)}
    config = FederationConfig(scheme=scheme, edge_interval=1, cloud_interval=1, cloud_rounds=2, compute_s_per_sample=0.0)
    setup = _setup(config, _hyper(config), counts, home, ledger=SMALL)
    trainer = CountingTrainer()
    state = _run(setup, ScriptedClock.constant(home, 8e6), trainer)
    assert state.cloud_rounds == 2 and state.stragglers == []
    # the model being averaged and the one before it; holding them all until the FedAvg would make 8
    assert trainer.peak == 2
    assert trainer.alive == 0  # every vehicle holds the released average, not its own model
    # the averages are still right: 2 epochs of (1 + ... + 8) samples, weighted by the counts
    assert state.cloud_model["w"].tolist() == [pytest.approx(2 * sum(n * n for n in range(1, 9)) / 36)] * 2


class OrderedTrainer(SumTrainer):
    """Training sets the i-th vehicle of a call to ``values[i]`` (the loop trains them in the setup's order)."""

    def __init__(self, values):
        self.values = values

    def train(self, states, samples, epochs, seed, needed=None):
        return ({"w": torch.full((2,), float(v), dtype=torch.float64)} for v in self.values[: len(states)])


def test_a_vehicle_whose_download_fails_keeps_the_model_it_trained():
    # a misses e0's deadline and cannot get the release either (drop); the cloud averages b (1) and c (3)
    state = _policy_run("wait", _handover_clock(), deadline_s=10.0, values=OrderedTrainer([7.0, 1.0, 3.0]),
                        download_handover="drop")
    assert [(s["vehicle"], s["reason"]) for s in state.stragglers] == [("a", "deadline"), ("a", "download outage")]
    assert state.cloud_model["w"].tolist() == [2.0, 2.0]
    assert {v: m["w"].tolist() for v, m in state.vehicle_models.items()} == {
        "a": [7.0, 7.0], "b": [2.0, 2.0], "c": [2.0, 2.0]
    }


class RecordingTrainer:
    """A real trainer whose yielded models are also copied aside: the inputs of a batch FedAvg."""

    def __init__(self, inner):
        self.inner, self.models = inner, []
        self.initial_state, self.evaluate = inner.initial_state, inner.evaluate

    def train(self, states, samples, epochs, seed, needed=None):
        for model in self.inner.train(states, samples, epochs, seed):
            self.models.append({k: t.clone() for k, t in model.items()})
            yield model


@pytest.mark.parametrize("scheme", ["hfl", "sfl"])
def test_averages_folded_in_as_models_come_equal_the_batch_fedavg_to_the_bit(scheme):
    from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
    from crchfl_sumo.learning.trainers import TorchTrainer

    from helpers import random_samples

    counts = {"a": 3, "b": 5, "c": 2, "d": 4}
    home = {"a": 0, "b": 1, "c": 0, "d": 1}
    interval = 1 if scheme == "sfl" else 2  # hfl: the step is an edge aggregation alone
    config = FederationConfig(scheme=scheme, edge_interval=1, cloud_interval=interval, cloud_rounds=1,
                              compute_s_per_sample=0.0)
    setup = _setup(config, _hyper(config), counts, home, ledger=SMALL)
    setup = dataclasses.replace(setup, samples={v: random_samples(n, seed=i) for i, (v, n) in enumerate(counts.items())})
    inner = TorchTrainer(ModelConfig("compact", 48, 64), TrainConfig(device="cpu", deterministic=True),
                         random_samples(4, seed=9), seed=0)
    trainer = RecordingTrainer(inner)
    start = initial_state(setup, trainer, 0.0)
    state = Federation(setup, ScriptedClock.constant(home, 8e6), trainer).step(start)  # one edge aggregation / SFL round
    trained = dict(zip(counts, trainer.models))
    groups = {CLOUD: list(counts)} if scheme == "sfl" else {"e0": ["a", "c"], "e1": ["b", "d"]}
    for receiver, vehicles in groups.items():
        batch = weighted_average([trained[v] for v in vehicles], [counts[v] for v in vehicles])
        folded = state.cloud_model if receiver == CLOUD else state.edge_models[receiver]
        assert not any(torch.equal(folded[k], start.cloud_model[k]) for k in folded if folded[k].is_floating_point())
        assert all(torch.equal(folded[k], batch[k]) for k in batch) and list(folded) == list(batch)
        assert all(state.vehicle_models[v] is folded for v in vehicles)


# ------------------------------------------------------------------ handover and straggler policies

# a is served by e0 until 1.5 s, then by e1 (from `back_s` on: by e0 again); b stays on e0, c on e1.


def _handover_clock(back_s=None):
    track_a = [Segment(0.0, 0, 8e6), Segment(1.5, 1, 8e6)]
    if back_s is not None:
        track_a.append(Segment(back_s, 0, 8e6))
    return ScriptedClock({"a": track_a, "b": [Segment(0.0, 0, 8e6)], "c": [Segment(0.0, 1, 8e6)]}, step_s=0.25)


def _policy_run(policy, clock, deadline_s=math.inf, values=None, download_handover="relay"):
    config = FederationConfig(
        scheme="hfl", edge_interval=1, cloud_rounds=1, compute_s_per_sample=0.5,
        handover_policy=policy, deadline_s=deadline_s, download_handover=download_handover,
    )
    setup = _setup(config, _hyper(config), {"a": 2, "b": 2, "c": 2}, HOME3, ledger=SMALL, rule="physical")
    trainer = FixedTrainer({2: 1.0}) if values is None else values
    fed = Federation(setup, clock, trainer)
    return fed.step(initial_state(setup, trainer, 0.0))


class NeededTrainer(FixedTrainer):
    """Records which vehicles each call needs, as a trainer that skips the rest would see them."""

    def __init__(self):
        super().__init__({2: 1.0})
        self.needed = []

    def train(self, states, samples, epochs, seed, needed=None):
        self.needed.append(None if needed is None else sorted(needed))
        return super().train(states, samples, epochs, seed)


def test_the_loop_asks_only_for_the_models_it_reads():
    # a misses e0's deadline; with its download relayed the release replaces its model: nobody reads it
    trainer = NeededTrainer()
    _policy_run("wait", _handover_clock(), deadline_s=10.0, values=trainer, download_handover="relay")
    assert trainer.needed == [[1, 2]]  # b and c, of a, b, c
    # dropped, the download fails: a keeps the model it trained, so it is needed
    trainer = NeededTrainer()
    state = _policy_run("wait", _handover_clock(), deadline_s=10.0, values=trainer, download_handover="drop")
    assert trainer.needed == [[0, 1, 2]] and state.vehicle_models["a"]["w"].tolist() == [1.0, 1.0]


def test_new_edge_policy_delivers_to_the_edge_serving_at_the_end_of_the_upload():
    state = _policy_run("new_edge", _handover_clock())
    uploads = {r.sender: r.receiver for r in state.records if r.direction == "uplink" and r.link == "wireless"}
    assert uploads == {"a": "e1", "b": "e0", "c": "e1"}
    assert state.member["a"] == "e1"
    assert state.edge_weights == {"e0": 2.0, "e1": 4.0}
    assert state.stragglers == []
    # the release reaches a from its new edge
    assert any(r.sender == "e1" and r.receiver == "a" for r in state.records)


def test_wait_policy_waits_for_the_own_edge():
    state = _policy_run("wait", _handover_clock(back_s=4.0), deadline_s=60.0)
    (a_up,) = [r for r in state.records if r.sender == "a" and r.direction == "uplink"]
    # 0.5 s of the 1.048576 s sent before 1.5 s, the rest after returning at 4 s
    assert a_up.receiver == "e0"
    assert a_up.end_s == pytest.approx(4.0 + WIRELESS_S - 0.5)
    assert state.member["a"] == "e0" and state.stragglers == []


def test_wait_policy_past_the_deadline_is_a_straggler_left_out_of_fedavg():
    trainer = FixedTrainer({2: 1.0})
    state = _policy_run("wait", _handover_clock(), deadline_s=10.0, values=trainer, download_handover="drop")
    # a never returns to e0: its upload misses the deadline, and e0's release cannot reach it either
    assert [(s["vehicle"], s["reason"]) for s in state.stragglers] == [("a", "deadline"), ("a", "download outage")]
    assert [r.size_bytes for r in state.records if r.receiver == "a"] == [0]  # physical: nothing crossed
    assert state.transfers == {"uploads": 3, "uploads_failed": 1, "downloads": 3, "downloads_failed": 1}
    assert state.edge_weights["e0"] == 2.0  # only b's samples behind e0's model
    (a_up,) = [r for r in state.records if r.sender == "a" and r.direction == "uplink"]
    assert a_up.end_s == pytest.approx(10.0)
    assert a_up.size_bytes == math.ceil(0.5 * 8e6 / 8)  # physical: the bytes sent before the handover
    e0_agg = [r for r in state.records if r.sender == "e0" and r.receiver == CLOUD][0]
    assert e0_agg.start_s == pytest.approx(10.0)  # the edge waited until its deadline
    # relayed, e0's release reaches a through e1: the whole model crosses the wireline e0 -> e1 first
    state = _policy_run("wait", _handover_clock(), deadline_s=10.0, values=trainer, download_handover="relay")
    assert [(s["vehicle"], s["reason"]) for s in state.stragglers] == [("a", "deadline")]
    (down,) = [r for r in state.records if r.receiver == "a"]
    (relay,) = [r for r in state.records if r.link == "relay"]
    assert (relay.sender, relay.receiver, relay.stage, relay.size_bytes) == ("e0", "e1", "III", down.size_bytes)
    assert relay.start_s == down.start_s > 10.0  # at the release: a is on e1 from its start
    assert down.end_s == pytest.approx(relay.end_s + WIRELESS_S)  # e1 sends it once it is there
    assert state.transfers == {"uploads": 3, "uploads_failed": 1, "downloads": 3, "downloads_failed": 0,
                               "relayed_transfers": 1}
    assert state.metrics[-1]["relay_bytes"] == relay.size_bytes


def test_forward_policy_forwards_an_upload_that_ends_at_another_edge():
    state = _policy_run("forward", _handover_clock())
    # a trains 1 s, uploads 1 -> 1 + WIRELESS_S over e0 then e1 (from 1.5 s): e1 forwards it to e0
    (a_up,) = [r for r in state.records if r.sender == "a" and r.direction == "uplink"]
    (relay,) = [r for r in state.records if r.link == "relay" and r.direction == "uplink"]
    assert (a_up.receiver, a_up.end_s) == ("e0", pytest.approx(1.0 + WIRELESS_S))
    assert (relay.sender, relay.receiver, relay.direction, relay.stage, relay.payload) == ("e1", "e0", "uplink", "II",
                                                                                            "model")
    assert relay.size_bytes == a_up.size_bytes == MIB
    assert relay.start_s == pytest.approx(a_up.end_s) and relay.end_s == pytest.approx(a_up.end_s + WIRELINE_S)
    assert state.member["a"] == "e0" and state.edge_weights == {"e0": 4.0, "e1": 2.0} and state.stragglers == []
    e0_agg = next(r for r in state.records if r.sender == "e0" and r.receiver == CLOUD)
    assert e0_agg.start_s == pytest.approx(relay.end_s)  # e0 waited for the forwarded model
    assert state.transfers["relayed_transfers"] == 2  # the upload, and e0's release that follows a to e1
    # forwarded past the deadline: a straggler, left out of e0's FedAvg
    late = _policy_run("forward", _handover_clock(), deadline_s=1.0 + WIRELESS_S + WIRELINE_S / 2)
    assert [(x["vehicle"], x["reason"]) for x in late.stragglers] == [("a", "deadline")]
    assert late.edge_weights["e0"] == 2.0


def test_miss_policy_fails_the_upload_at_the_handover():
    state = _policy_run("miss", _handover_clock(back_s=4.0))
    assert [(s["vehicle"], s["reason"], s["cause"], s["t_s"]) for s in state.stragglers] == [
        ("a", "outage", "out_of_coverage", 1.5)
    ]
    assert state.edge_weights == {"e0": 2.0, "e1": 2.0}
    assert state.member["a"] == "e0"


def test_a_vehicle_that_cannot_start_before_the_deadline_is_not_charged():
    home = {"a": 0, "b": 0}
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=1, compute_s_per_sample=1.0, deadline_s=5.0)
    setup = _setup(config, _hyper(config), {"a": 10, "b": 1}, home, ledger=SMALL, edges=("e0",))
    state = _run(setup, ScriptedClock.constant(home, 8e6))
    assert [(s["vehicle"], s["reason"]) for s in state.stragglers] == [("a", "no time to upload before the deadline")]
    assert [r.sender for r in state.records if r.direction == "uplink" and r.link == "wireless"] == ["b"]
    assert state.edge_weights == {"e0": 1.0}
    # a still receives the new model
    assert {r.receiver for r in state.records if r.direction == "downlink" and r.link == "wireless"} == {"a", "b"}


def test_the_best_model_is_the_one_of_highest_balanced_accuracy():
    # accuracy rises round by round (towards always-straight) while balanced accuracy falls after round 1
    class Majority(SumTrainer):
        def evaluate(self, state):
            w = float(state["w"][0])
            return {"loss": 1.0, "accuracy": w / (1.0 + w), "balanced_accuracy": 1.0 / (1.0 + abs(w - 1.0))}

    config = FederationConfig(scheme="sfl", edge_interval=1, cloud_rounds=3, compute_s_per_sample=0.0)
    setup = _setup(config, _hyper(config), {"a": 1, "b": 1}, {"a": 0, "b": 0}, ledger=SMALL, edges=("e0",))
    state = _run(setup, ScriptedClock.constant({"a": 0, "b": 0}, 8e6), Majority())
    lines = [m for m in state.metrics if m["stage"] == "III"]
    assert [m["accuracy"] for m in lines] == [0.5, 2 / 3, 0.75]  # w = 1, 2, 3 after rounds 1, 2, 3
    assert [m["balanced_accuracy"] for m in lines] == [1.0, 0.5, 1 / 3]
    assert state.best["cloud_round"] == 1 and state.best_model["w"].tolist() == [1.0, 1.0]


def test_best_model_is_kept_when_accuracy_falls():
    class Falling(SumTrainer):
        def evaluate(self, state):
            return {"loss": float(state["w"][0]), "accuracy": 1.0 / (1.0 + float(state["w"][0]))}

    config = FederationConfig(scheme="sfl", edge_interval=1, cloud_rounds=3, compute_s_per_sample=0.0)
    setup = _setup(config, _hyper(config), {"a": 1, "b": 1}, {"a": 0, "b": 0}, ledger=SMALL, edges=("e0",))
    state = _run(setup, ScriptedClock.constant({"a": 0, "b": 0}, 8e6), Falling())
    assert state.best["cloud_round"] == 1
    assert state.best_model["w"].tolist() == [1.0, 1.0]
    assert state.cloud_model["w"].tolist() == [3.0, 3.0]


# ------------------------------------------------------------------ pieces


def test_wireless_transfer_asks_the_clock_for_more_time_until_it_settles():
    clock = ScriptedClock({"a": [Segment(0.0, 0, 1e6), Segment(100.0, 1, 2e6)]}, step_s=1.0)
    out = wireless_transfer(clock, "a", "edge", 10.0, 50e6 / 8, TransferConfig(), horizon_s=5.0)
    # 90 s at 1 Mbit/s = 90 Mbit by 100 s... 50 Mbit needs 50 s: done at 60 s on site 0
    assert out.ok and out.end_s == pytest.approx(60.0) and out.site == 0
    out = wireless_transfer(clock, "a", "edge", 10.0, 130e6 / 8, TransferConfig(), horizon_s=5.0)
    # 90 Mbit by 100 s, 40 Mbit more at 2 Mbit/s: 120 s, delivered on site 1
    assert out.ok and out.end_s == pytest.approx(120.0) and out.site == 1


@pytest.mark.parametrize("key,value", [("pretrain_batch", 100), ("edge_interval", 4), ("cloud_interval", 2),
                                       ("cloud_rounds", 1)])
def test_a_hyper_parameter_set_beside_use_plan_is_refused_naming_it(key, value):
    # The optimizer's plan replaces it: silently ignored, a sweep over it would repeat one run.
    with pytest.raises(CrchflError, match=f"federation.{key}: {value} is not used with use_plan = true"):
        FederationConfig(scheme="crchfl", use_plan=True, **{key: value})
    assert getattr(FederationConfig(scheme="crchfl", use_plan=False, **{key: value}), key) == value


def test_config_rejects_impossible_combinations():
    with pytest.raises(CrchflError, match="cloud_interval"):
        FederationConfig(scheme="sfl", cloud_interval=2)
    with pytest.raises(CrchflError, match="pretrain_batch"):
        FederationConfig(scheme="hfl", pretrain_batch=10)
    with pytest.raises(CrchflError, match="use_plan"):
        FederationConfig(scheme="sfl", use_plan=True)
    with pytest.raises(CrchflError, match="handover_policy"):
        FederationConfig(handover_policy="teleport")
    with pytest.raises(CrchflError, match="deadline_s"):
        FederationConfig(deadline_s=0.0)
    with pytest.raises(CrchflError, match="finite federation.deadline_s"):
        FederationConfig(handover_policy="wait")


def test_state_round_trips_through_its_payload():
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=1)
    setup = _setup(config, _hyper(config), {"a": 2, "b": 2, "c": 2}, HOME3, ledger=SMALL)
    state = _run(setup, ScriptedClock.constant(HOME3, 8e6))
    payload = state.to_payload()
    assert not {"records", "metrics", "stragglers"} & set(payload)  # the history lives in the logs
    again = type(state).from_payload(payload, state.records, state.metrics, state.stragglers)
    assert again == state
    # the counters stand for the records
    assert Ledger(setup.sizes, byte_totals=state.ledger_totals).totals("link") == Ledger(setup.sizes, state.records).totals("link")
    assert state.transfers_end_s == max(r.end_s for r in state.records)


def test_evaluate_every_edge_reports_the_sample_weighted_edge_metrics():
    home = {"a": 0, "b": 0, "c": 1}
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=1, evaluate_every_edge=True)
    setup = _setup(config, _hyper(config), {"a": 1, "b": 3, "c": 2}, home, ledger=SMALL)
    state = _run(setup, ScriptedClock.constant(home, 8e6), FixedTrainer({1: 1.0, 3: 5.0, 2: 10.0}))
    edge_line, cloud_line = state.metrics
    # SumTrainer.evaluate: loss 1 / (1 + sum w); e0 = 4 (weight 4), e1 = 10 (weight 2), two entries each
    assert edge_line["stage"] == "II"
    assert edge_line["loss"] == pytest.approx((4 * (1 / 9) + 2 * (1 / 21)) / 6)
    assert cloud_line["loss"] == pytest.approx(1 / (1 + 2 * 6.0))


# ------------------------------------------------------------------ budgets: prefixes and marks


class WavyTrainer(SumTrainer):
    """SumTrainer whose balanced accuracy rises and falls, so that the best model is not simply the last."""

    def evaluate(self, state):
        total = float(state["w"].sum())
        return {"loss": 1.0 / (1.0 + total), "accuracy": 0.5, "balanced_accuracy": (total % 7.0) / 7.0}


@pytest.mark.parametrize("scheme", ["hfl", "sfl"])
def test_a_smaller_budget_is_a_prefix_of_a_larger_one_and_its_mark_keeps_the_best_within(scheme):
    from crchfl_sumo.accounting.ledger import GIB, budget_marks_bytes

    config = FederationConfig(scheme=scheme, edge_interval=1, compute_s_per_sample=0.5)

    def run(budget_gb, marks=()):
        ledger = LedgerConfig(nominal_model_mb=1.0, nominal_sample_kb=512.0, budget_gb=budget_gb, marks_gb=marks)
        setup = _setup(config, _hyper(config), {"a": 2, "b": 3, "c": 4}, HOME3, ledger=ledger)
        setup = dataclasses.replace(setup, budget_marks_bytes=budget_marks_bytes(ledger))
        return _run(setup, ScriptedClock.constant(HOME3, 8e6, step_s=0.25), WavyTrainer())

    small, large = run(0.05), run(0.1, marks=(0.01, 0.05))
    n = len(small.metrics)
    # HFL's and SFL's schedules do not depend on the budget: the smaller run is the larger one cut short
    assert 3 <= n < len(large.metrics)
    assert small.metrics == large.metrics[:n] and small.records == large.records[: len(small.records)]
    assert small.metrics[-1]["consumed_bytes"] <= 0.05 * GIB < large.metrics[n]["consumed_bytes"]
    # the mark at 0.05 GB kept the best of the smaller run, which is not its last model
    key = str(math.floor(0.05 * GIB))
    assert large.budget_marks[key] == small.best and small.best != small.metrics[-1]
    assert torch.equal(large.budget_mark_models[key]["w"], small.best_model["w"])
    # the best within 0.01 GB, by hand from the larger run's lines
    within = [m for m in large.metrics if m["consumed_bytes"] <= 0.01 * GIB and m.get("balanced_accuracy") is not None]
    best = max(within, key=lambda m: (m["balanced_accuracy"], -m["loss"]))  # ties: the lower loss (loop._rank)
    assert large.budget_marks[str(math.floor(0.01 * GIB))] == best
    assert set(large.budget_marks) == {str(math.floor(0.01 * GIB)), key}  # both passed


def test_budget_marks_must_lie_within_the_budget_and_increase():
    with pytest.raises(CrchflError, match=r"ledger.marks_gb: 25 exceeds budget_gb = 20"):
        LedgerConfig(marks_gb=(5.0, 25.0))
    for bad in ((10.0, 5.0), (5.0, 5.0), (0.0,), (float("nan"),)):
        with pytest.raises(CrchflError, match="ledger.marks_gb: .* increasing, each once"):
            LedgerConfig(marks_gb=bad)


def test_the_mean_uplink_rate_is_each_wireless_uplinks_bytes_over_its_duration():
    from crchfl_sumo.federation.run import mean_uplink_rate_mbps

    state = _one_round("hfl", "paper")
    assert mean_uplink_rate_mbps(state.records) == pytest.approx(8.0)  # 1 MiB in 8 * MIB / 8e6 s: 8 Mbit/s
    records = [dataclasses.replace(state.records[0], size_bytes=10**6, start_s=0.0, end_s=2.0),  # 4 Mbit/s
               dataclasses.replace(state.records[1], size_bytes=3 * 10**6, start_s=1.0, end_s=2.0),  # 24 Mbit/s
               dataclasses.replace(state.records[3], size_bytes=10**9, start_s=0.0, end_s=1.0),  # wireline: not counted
               dataclasses.replace(state.records[7], size_bytes=10**9, start_s=0.0, end_s=1.0)]  # downlink: not counted
    assert mean_uplink_rate_mbps(records) == pytest.approx(14.0)
    assert mean_uplink_rate_mbps(records[2:]) is None


# ------------------------------------------------------------------ the vehicles' own DAgger ([dagger])


class SampleCountTrainer(SumTrainer):
    """SumTrainer that records each training call's sample counts per vehicle."""

    def __init__(self):
        self.counts = []

    def train(self, states, samples, epochs, seed, needed=None):
        self.counts.append([len(x) for x in samples])
        return super().train(states, samples, epochs, seed)


class ScriptedLabeller:
    """Labels a fixed number of samples per vehicle and round; records the models each round was given."""

    def __init__(self, per_round):
        self.per_round, self.given, self.kept = per_round, {}, {}

    def label(self, cloud_round, models):
        self.given[cloud_round] = {v: float(m["w"][0]) for v, m in models.items()}
        self.kept[cloud_round] = {v: _samples(self.per_round[v]) for v in models}
        return self.kept[cloud_round]

    def labelled(self, cloud_round):
        return self.kept[cloud_round]


@pytest.mark.parametrize("scheme", ["hfl", "sfl"])
def test_dagger_rounds_add_each_vehicles_own_labels_to_its_data_and_cross_no_link(scheme):
    from crchfl_sumo.federation.settings import VehicleDaggerConfig

    config = FederationConfig(scheme=scheme, edge_interval=1, cloud_interval=1, cloud_rounds=4, compute_s_per_sample=0.5)
    counts = {"a": 2, "b": 2, "c": 2}
    plain = _setup(config, _hyper(config), counts, HOME3, ledger=SMALL)
    with_dagger = dataclasses.replace(plain, dagger=VehicleDaggerConfig(every_cloud_rounds=2))
    labeller = ScriptedLabeller({"a": 1, "b": 0, "c": 3})
    trainer = SampleCountTrainer()
    clock = ScriptedClock.constant(HOME3, 8e6, step_s=0.25, macro_rate_bps=8e6)
    state = Federation(with_dagger, clock, trainer, labeller=labeller).run(initial_state(with_dagger, trainer, 0.0))
    # Labelled after rounds 2 and 4 only (round 4 ended the run, so no later training used it).
    assert state.dagger_rounds == [2] and list(labeller.given) == [2]
    # Each vehicle drove the model it held after round 2: 2 rounds x 1 epoch x 2 samples, averaged.
    assert labeller.given[2] == {"a": 4.0, "b": 4.0, "c": 4.0}
    # Rounds 1-2 train on the shards; rounds 3-4 on each shard plus that vehicle's own labels.
    assert trainer.counts == [[2, 2, 2], [2, 2, 2], [3, 2, 5], [3, 2, 5]]
    # Only models crossed the links: the same transfers and bytes as without [dagger].
    reference = Federation(plain, ScriptedClock.constant(HOME3, 8e6, step_s=0.25, macro_rate_bps=8e6),
                           SumTrainer()).run(initial_state(plain, SumTrainer(), 0.0))
    assert _rows(state) == _rows(reference)
    # The labels count in FedAvg's weights as the vehicle's samples (|T_nk| = 3, 2, 5).
    assert state.cloud_model["w"].tolist() == pytest.approx([4.0 + 2 * (3 * 3 + 2 * 2 + 5 * 5) / 10] * 2)


def test_a_run_with_dagger_needs_a_labeller_and_dagger_rounds_survive_the_payload():
    from crchfl_sumo.federation.settings import VehicleDaggerConfig
    from crchfl_sumo.federation.state import FederationState

    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=2)
    setup = dataclasses.replace(_setup(config, _hyper(config), {"a": 2, "b": 2, "c": 2}, HOME3, ledger=SMALL),
                                dagger=VehicleDaggerConfig(every_cloud_rounds=1))
    with pytest.raises(CrchflError, match="labeller"):
        Federation(setup, ScriptedClock.constant(HOME3, 8e6), SumTrainer())
    state = initial_state(setup, SumTrainer(), 0.0)
    state.dagger_rounds = [1, 3]
    assert FederationState.from_payload(state.to_payload(), [], [], []).dagger_rounds == [1, 3]
    older = {k: v for k, v in state.to_payload().items() if k != "dagger_rounds"}
    assert FederationState.from_payload(older, [], [], []).dagger_rounds == []


@pytest.mark.parametrize("key, value, match", [
    ("every_cloud_rounds", -1, "dagger.every_cloud_rounds"), ("episodes", 0, "dagger.episodes"),
    ("tasks", (), "dagger.tasks"), ("seed", -3, "dagger.seed"), ("max_s", float("nan"), "dagger.max_s"),
])
def test_bad_dagger_settings_are_refused_naming_the_key(key, value, match):
    from crchfl_sumo.federation.settings import VehicleDaggerConfig

    with pytest.raises(CrchflError, match=match):
        VehicleDaggerConfig(**{key: value})


def test_no_labelling_for_a_step_the_budget_cannot_carry():
    """The paper rule: 3 rounds fit the budget, labelling is due after every round; the drives after
    round 3 would feed a round that is never counted, so the vehicles do not make them."""
    from crchfl_sumo.federation.settings import VehicleDaggerConfig

    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_interval=1, compute_s_per_sample=0.5)
    counts = {"a": 2, "b": 2, "c": 2}
    # one HFL round at 1 MiB models: 3 uploads, 2 + 2 wireline, 3 downloads = 10 MiB; 35 MiB carry 3 rounds
    ledger = LedgerConfig(nominal_model_mb=1.0, nominal_sample_kb=512.0, budget_gb=35 / 1024)
    setup = dataclasses.replace(_setup(config, _hyper(config), counts, HOME3, ledger=ledger),
                                dagger=VehicleDaggerConfig(every_cloud_rounds=1))
    labeller = ScriptedLabeller({"a": 1, "b": 1, "c": 1})
    clock = ScriptedClock.constant(HOME3, 8e6, step_s=0.25)
    state = Federation(setup, clock, SumTrainer(), labeller=labeller).run(initial_state(setup, SumTrainer(), 0.0))
    assert (state.cloud_rounds, state.stop_reason) == (3, "budget")
    assert list(labeller.given) == [1, 2] and state.dagger_rounds == [1, 2]


# ------------------------------------------------------------------ update codecs


def _codec_run(codec, budget_mib=35, fraction=0.5):
    """HFL at 1 MiB models (SumTrainer's model: two float64 entries, 16 raw bytes)."""
    from crchfl_sumo.federation.run import codec_fractions
    from crchfl_sumo.federation.run_config import RunConfig

    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_interval=1, compute_s_per_sample=0.5,
                              update_codec=codec, topk_fraction=fraction)
    ledger = LedgerConfig(nominal_model_mb=1.0, nominal_sample_kb=512.0, budget_gb=budget_mib / 1024)
    fractions = codec_fractions(RunConfig(federation=config),
                                SumTrainer().initial_state())
    setup = dataclasses.replace(_setup(config, _hyper(config), {"a": 2, "b": 2, "c": 2}, HOME3, ledger=ledger),
                                sizes=resolve_sizes(ledger, None, None, *fractions))
    return _run(setup, ScriptedClock.constant(HOME3, 8e6, step_s=0.25)), fractions


def test_int8_charges_every_model_transfer_its_encoded_size_and_makes_more_rounds():
    plain, _ = _codec_run("none")
    coded, (every, upload) = _codec_run("int8")
    assert every == upload == pytest.approx((2 + 4) / 16)  # two int8 entries and a float32 scale, of 16 bytes
    encoded = round(MIB * every)
    assert {r[6] for r in _rows(coded)} == {encoded} and {r[6] for r in _rows(plain)} == {MIB}
    # 10 model transfers a round: 10 MiB carry 3 rounds of 35 MiB, 3.75 MiB carry 9
    assert (plain.cloud_rounds, coded.cloud_rounds) == (3, 9)
    # SumTrainer's updates (n, n) quantize exactly: the model is what it is without the codec, round by round
    three, _ = _codec_run("int8", budget_mib=3 * 3.75 + 1)
    assert three.cloud_rounds == 3 and torch.allclose(three.cloud_model["w"], plain.cloud_model["w"])


def test_topk_shrinks_the_vehicles_uploads_only_and_keeps_what_it_left_out():
    coded, (every, upload) = _codec_run("topk", fraction=0.5)
    assert every == 1.0 and upload == pytest.approx((8 + 4) / 16)  # one of two float64 entries and its index
    sizes = {(r[0], r[1]): r[6] for r in _rows(coded)}
    assert sizes == {("wireless", "uplink"): round(MIB * upload), ("wireline", "uplink"): MIB,
                     ("wireline", "downlink"): MIB, ("wireless", "downlink"): MIB}
    # SumTrainer's update is (n, n): one entry sent, one left over for each vehicle's next upload
    assert set(coded.residuals) == {"a", "b", "c"}
    assert all(float(r["w"].abs().sum()) > 0 for r in coded.residuals.values())
    from crchfl_sumo.federation.state import FederationState

    back = FederationState.from_payload(coded.to_payload(), [], [], [])
    assert all(torch.equal(back.residuals[v]["w"], coded.residuals[v]["w"]) for v in "abc")


def test_the_optimizer_plans_a_quarter_size_transfer_as_a_quarter_size_model():
    plan = make_plan(AllocationConfig(), LedgerConfig())
    coded = make_plan(AllocationConfig(), LedgerConfig(), fractions=(0.25, 0.25))
    quarter = make_plan(AllocationConfig(), LedgerConfig(nominal_model_mb=LedgerConfig().nominal_model_mb / 4))
    assert plan.cloud_rounds == 9
    fixed = ("pretrain_batch", "edge_interval", "cloud_interval", "cloud_rounds")
    assert {k: getattr(coded, k) for k in fixed} == {k: getattr(quarter, k) for k in fixed}
    assert coded.cloud_rounds > plan.cloud_rounds


def test_a_bad_codec_is_refused_naming_the_key():
    with pytest.raises(CrchflError, match="federation.update_codec"):
        FederationConfig(update_codec="zip")
    with pytest.raises(CrchflError, match="federation.topk_fraction"):
        FederationConfig(topk_fraction=0.0)


# ------------------------------------------------------------------ heterogeneous and intermittent vehicles


def _fleet_run(fleet, deadline_s=math.inf, scheme="hfl"):
    """a and b on e0, 2 samples at 0.5 s: 1 s of nominal training, then 1 MiB at 8 Mbit/s."""
    home = {"a": 0, "b": 0}
    config = FederationConfig(scheme=scheme, edge_interval=1, cloud_rounds=1, compute_s_per_sample=0.5,
                              deadline_s=deadline_s)
    setup = dataclasses.replace(
        _setup(config, _hyper(config), {"a": 2, "b": 2}, home, ledger=SMALL, edges=("e0",)), fleet=fleet
    )
    return _run(setup, ScriptedClock.constant(home, 8e6, macro_rate_bps=8e6))


def _up(state, vehicle):
    return [r for r in state.records if r.sender == vehicle and r.direction == "uplink" and r.link == "wireless"]


@pytest.mark.parametrize("scheme", ["hfl", "sfl"])
def test_an_availability_trace_keeps_a_vehicle_out_exactly_while_it_is_off(scheme):
    # a is off from 0.5 s to 3 s: half its training before, half after -> trained at 3.5 s
    state = _fleet_run(Fleet(off_s={"a": np.array([[0.5, 3.0]])}), scheme=scheme)
    (a_up,), (b_up,) = _up(state, "a"), _up(state, "b")
    assert (a_up.start_s, a_up.end_s) == (pytest.approx(3.5), pytest.approx(3.5 + WIRELESS_S))
    assert (b_up.start_s, b_up.end_s) == (pytest.approx(1.0), pytest.approx(1.0 + WIRELESS_S))
    assert state.stragglers == []
    # off during its upload (from 1.5 s to 2 s): the upload waits 0.5 s, nothing crosses meanwhile
    state = _fleet_run(Fleet(off_s={"a": np.array([[1.5, 2.0]])}), scheme=scheme)
    (a_up,) = _up(state, "a")
    assert (a_up.start_s, a_up.end_s) == (pytest.approx(1.0), pytest.approx(1.0 + WIRELESS_S + 0.5))
    # off past the deadline: a straggler because it was unavailable, left out of the FedAvg
    state = _fleet_run(Fleet(off_s={"a": np.array([[0.5, 30.0]])}), deadline_s=5.0, scheme=scheme)
    assert [(s["vehicle"], s["reason"], s["cause"]) for s in state.stragglers] == [
        ("a", "no time to upload before the deadline", "unavailable")
    ]
    assert _up(state, "a") == []


def test_a_slow_vehicle_trains_longer_and_straggles_for_slow_compute_only_when_speed_decides():
    slow = Fleet(compute_factor={"a": 3.0})  # 3 s of training instead of 1 s
    state = _fleet_run(slow)
    assert state.train_s == {"a": 3.0, "b": 1.0}  # the time each trained, for its energy
    assert _up(state, "a")[0].start_s == pytest.approx(3.0) and _up(state, "b")[0].start_s == pytest.approx(1.0)
    # the deadline falls between the nominal arrival (1 + 1.05 s) and a's (3 + 1.05 s): its speed decided
    state = _fleet_run(slow, deadline_s=3.5)
    assert [(s["vehicle"], s["reason"], s["cause"]) for s in state.stragglers] == [("a", "deadline", "slow_compute")]
    state = _fleet_run(slow, deadline_s=2.5)
    assert [(s["vehicle"], s["cause"]) for s in state.stragglers] == [("a", "slow_compute")]  # could not even start
    # a deadline that even the nominal speed misses: the link's fault, for both
    state = _fleet_run(slow, deadline_s=1.5)
    assert [(s["vehicle"], s["cause"]) for s in state.stragglers] == [("a", "deadline"), ("b", "deadline")]
