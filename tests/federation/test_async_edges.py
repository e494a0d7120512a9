"""Asynchronous edges (federation/async_edges.py): the buffered, staleness-weighted update by hand,
FedAvg when every update is fresh, a vehicle out of coverage contributing later, refusals, resume."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from crchfl_sumo.accounting.ledger import MIB, LedgerConfig, resolve_sizes
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.loop import Federation
from crchfl_sumo.federation.run import run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.federation.settings import FederationConfig, HyperParameters
from crchfl_sumo.federation.state import LoopInputs, initial_state
from crchfl_sumo.learning.aggregate import buffered_update, fedavg, staleness_factor
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.clock import ScriptedClock, Segment
from crchfl_sumo.links.fleet import Fleet

from helpers import PAPER_VEHICLES, Killed, SumTrainer, kill_after, result_files, run_config, write_dataset

SMALL = LedgerConfig(nominal_model_mb=1.0, nominal_sample_kb=512.0, budget_gb=1.0)
W = 8 * MIB / 8e6  # 1 MiB at 8 Mbit/s
WIRE = 8 * MIB / 1e9 + 0.010  # over the wireline


class PlusCount:
    """Training adds the sample count to every weight: each update is n, whatever it started from."""

    def initial_state(self):
        return {"w": torch.zeros(2, dtype=torch.float64)}

    def train(self, states, samples, epochs, seed, needed=None):
        return [{"w": s["w"] + len(x)} for s, x in zip(states, samples)]

    def evaluate(self, state):
        return {"loss": 1.0, "accuracy": 0.5}


class ByCount:
    """Training sets the model to a fixed value per sample count (FedAvg by hand)."""

    def __init__(self, values):
        self.values = values

    initial_state = PlusCount.initial_state
    evaluate = PlusCount.evaluate

    def train(self, states, samples, epochs, seed, needed=None):
        return [{"w": torch.full((2,), float(self.values[len(x)]), dtype=torch.float64)} for x in samples]


def _samples(n):
    return Samples.from_numpy(np.zeros((n, 4, 1, 1, 3), np.uint8), np.zeros((n, 3), np.float32), np.zeros(n, np.int64),
                              np.zeros(n), np.zeros(n), np.zeros(n))


def _setup(config, counts, home, edges, fleet=Fleet()):
    hyper = HyperParameters(0, config.edge_interval, config.cloud_interval, config.cloud_rounds)
    return LoopInputs(config=config, hyper=hyper, vehicles=tuple(counts), samples={v: _samples(n) for v, n in counts.items()},
                      home_site=home, edges=edges, sizes=resolve_sizes(SMALL), rule="paper", wireline=WirelineConfig(),
                      fleet=fleet)


def _run(setup, clock, trainer):
    return Federation(setup, clock, trainer).run(initial_state(setup, trainer, clock.start_s))


def test_staleness_weights_and_the_buffered_update_by_hand():
    assert staleness_factor(0, 0.5) == 1.0 and staleness_factor(3, 0.5) == 0.5 and staleness_factor(7, 1.0) == 0.125
    assert staleness_factor(5, 0.0) == 1.0
    current = {"w": torch.tensor([1.0, 1.0])}
    updates = [({"w": torch.tensor([0.0, 0.0])}, {"w": torch.tensor([2.0, 4.0])}, 1, 1.0),
               ({"w": torch.tensor([1.0, 1.0])}, {"w": torch.tensor([1.0, 3.0])}, 3, 0.5)]
    # 1 + (1 * 1 * (2, 4) + 3 * 0.5 * (0, 2)) / 4 = (1.5, 2.75)
    assert buffered_update(current, updates)["w"].tolist() == [1.5, 2.75]
    # fresh updates from the current model: FedAvg
    fresh = [(current, {"w": torch.tensor([3.0, 5.0])}, 1, 1.0), (current, {"w": torch.tensor([7.0, 1.0])}, 3, 1.0)]
    assert buffered_update(current, fresh)["w"].tolist() == fedavg([(u[1], u[2]) for u in fresh])["w"].tolist()


def test_an_edge_aggregates_its_first_two_updates_and_weights_a_stale_one_by_hand():
    home = {"a": 0, "b": 0, "c": 0}
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=2, compute_s_per_sample=0.5,
                              aggregation="async", async_buffer=2, staleness_exponent=0.5)
    fleet = Fleet(compute_factor={"b": 2.0, "c": 4.0})  # training 1, 2 and 4 s
    setup = _setup(config, {"a": 2, "b": 2, "c": 2}, home, ("e0",), fleet)
    state = _run(setup, ScriptedClock.constant(home, 8e6), PlusCount())
    lines = [m for m in state.metrics if m["stage"] == "II"]
    # 1: a (1 + W) and b (2 + W) fill the buffer: fresh, 0 + (2 * 2 + 2 * 2) / 4 = 2
    assert lines[0]["sim_time_s"] == pytest.approx(2 + W) and lines[0]["staleness"] == {"a": 0, "b": 0}
    # the cloud follows (cloud_interval 1, one edge) and releases to the edge: a second version of it
    # 2: c (4 + W, from the initial model: 2 versions stale) and a (back at 2 + 2W, trains 1 s: 3 + 3W)
    assert lines[1]["sim_time_s"] == pytest.approx(3 + 3 * W) and lines[1]["staleness"] == {"a": 1, "c": 2}
    assert lines[1]["received"] == {"e0": 2}
    expected = 2 + (2 * staleness_factor(2, 0.5) * 2 + 2 * staleness_factor(1, 0.5) * 2) / 4
    assert state.cloud_rounds == 2 and state.cloud_model["w"].tolist() == pytest.approx([expected] * 2)


def test_with_every_update_fresh_async_gives_the_synchronous_fedavg_and_bytes():
    home = {"a": 0, "b": 0, "c": 1, "d": 1, "e": 1}
    counts = {"a": 2, "b": 3, "c": 1, "d": 2, "e": 4}
    trainer = ByCount({1: 10.0, 2: 20.0, 3: 30.0, 4: 40.0})
    results = {}
    for aggregation, buffer in (("sync", 1), ("async", 3)):
        config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=1, compute_s_per_sample=0.5,
                                  aggregation=aggregation, async_buffer=buffer)
        setup = _setup(config, counts, home, ("e0", "e1"))
        results[aggregation] = _run(setup, ScriptedClock.constant(home, 8e6), trainer)
    sync, asyn = results["sync"], results["async"]
    assert asyn.cloud_model["w"].tolist() == pytest.approx(sync.cloud_model["w"].tolist())
    assert asyn.edge_aggregations == 2 and asyn.cloud_rounds == 1
    spent = [sum(r.size_bytes for r in s.records) for s in (sync, asyn)]
    assert spent[0] == spent[1]  # 5 uploads, 4 wireline hops, 5 downloads either way


def test_a_vehicle_out_of_coverage_straggles_and_contributes_later_with_its_staleness():
    home = {"a": 0, "b": 0, "c": 0}
    tracks = {v: [Segment(0.0, 0, 8e6)] for v in "ab"} | {"c": [Segment(0.0, -1, 0.0), Segment(100.0, 0, 8e6)]}
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=60, compute_s_per_sample=0.5,
                              aggregation="async", async_buffer=2)
    setup = _setup(config, {"a": 2, "b": 2, "c": 2}, home, ("e0",))
    state = _run(setup, ScriptedClock(tracks), PlusCount())
    first = next(m for m in state.metrics if m["stage"] == "II")
    assert set(first["staleness"]) == {"a", "b"}  # the edge did not wait for c
    c_missed = [s for s in state.stragglers if s["vehicle"] == "c"]
    assert c_missed and all(s["cause"] == "out_of_coverage" and s["t_s"] < 130 for s in c_missed)
    c_in = [m for m in state.metrics if m["stage"] == "II" and "c" in m["staleness"]]
    assert c_in and c_in[0]["sim_time_s"] > 100 and c_in[0]["staleness"]["c"] >= 1


@pytest.mark.parametrize(
    "federation, match",
    [
        ({"scheme": "sfl"}, "federation.scheme: 'sfl' with aggregation"),
        ({"deadline_s": 30.0}, "federation.deadline_s"),
        ({"handover_policy": "wait", "deadline_s": 30.0}, "federation.deadline_s"),
        ({"selection": "skip_leaving"}, "federation.selection"),
        ({"update_codec": "int8"}, "federation.update_codec"),
        ({"async_buffer": 0}, "federation.async_buffer"),
        ({"staleness_exponent": -1.0}, "federation.staleness_exponent"),
    ],
)
def test_what_async_edges_do_not_combine_with_is_refused_by_its_key(federation, match):
    with pytest.raises(CrchflError, match=match):
        from_mapping(RunConfig, {"federation": {"scheme": "hfl", "aggregation": "async", **federation}}, "run.toml")


def test_async_with_vehicle_dagger_is_refused():
    with pytest.raises(CrchflError, match=r"\[dagger\]"):
        from_mapping(RunConfig, {"federation": {"aggregation": "async", "scheme": "hfl"},
                                 "dagger": {"every_cloud_rounds": 1}}, "run.toml")


def test_an_async_run_killed_anywhere_resumes_to_the_same_files(tmp_path):
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    mapping = run_config(dataset, scheme="crchfl", pretrain_batch=3, pretrain_epochs=1, cloud_rounds=3,
                         aggregation="async", async_buffer=2)
    mapping["clock"] |= {"compute_profile": "tiers", "compute_tiers": [1.0, 3.0]}
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)
    whole = run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    assert whole["cloud_rounds"] == 3 and whole["edge_aggregations"] >= 3
    for kill_at in (2, 4):
        out = tmp_path / f"killed{kill_at}"
        with pytest.raises(Killed):
            run_federation_dir(config, inputs, out, trainer=SumTrainer(), after_checkpoint=kill_after(kill_at))
        run_federation_dir(config, inputs, out, trainer=SumTrainer(), resume=True)
        assert result_files(out) == result_files(tmp_path / "whole")
    assert not math.isnan(whole["consumed_bytes"])


def test_a_vehicle_whose_uploads_fail_at_once_retries_a_clock_step_later_and_the_run_goes_on():
    # c has no coverage at all, trains in no time and fails the moment it tries ("miss"); physical rule:
    # its failures cost nothing, so only time can end its retries
    home = {"a": 0, "b": 0, "c": 0}
    tracks = {v: [Segment(0.0, 0, 8e6)] for v in "ab"}
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=3, compute_s_per_sample=0.0,
                              aggregation="async", async_buffer=2, handover_policy="miss")
    hyper = HyperParameters(0, 1, 1, 3)
    setup = LoopInputs(config=config, hyper=hyper, vehicles=("a", "b", "c"), samples={v: _samples(2) for v in "abc"},
                       home_site=home, edges=("e0",), sizes=resolve_sizes(SMALL), rule="physical",
                       wireline=WirelineConfig())
    trainer = PlusCount()
    federation = Federation(setup, ScriptedClock(tracks, step_s=0.5), trainer)
    state = initial_state(setup, trainer, 0.0)
    for _ in range(500):  # a bounded number of steps: retries at one moment would never end
        if state.done:
            break
        state = federation.step(state)
    assert state.done and state.cloud_rounds == 3
    tries = [s["t_s"] for s in state.stragglers if s["vehicle"] == "c"]
    assert tries and all(b - a >= 0.5 - 1e-9 for a, b in zip(tries, tries[1:]))  # a step apart at least
