"""Mobility-aware client selection on a scripted clock: a vehicle about to leave its cell is skipped."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from crchfl_sumo.accounting.ledger import MIB, LedgerConfig, resolve_sizes
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation import selection
from crchfl_sumo.federation.loop import Federation
from crchfl_sumo.federation.run import run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.federation.settings import FederationConfig, HyperParameters
from crchfl_sumo.federation.state import LoopInputs, initial_state
from crchfl_sumo.links.clock import ScriptedClock, Segment
from crchfl_sumo.links.residence import Coverage, Pose

from helpers import PAPER_VEHICLES, Killed, kill_after, result_files, run_config, write_dataset

SMALL = LedgerConfig(nominal_model_mb=1.0, nominal_sample_kb=512.0, budget_gb=1.0)
# Sites e0 at x = 0 and e1 at x = 400 m, 300 m range: their border is x = 200 m.
COVERAGE = Coverage(((0.0, 0.0), (400.0, 0.0)), 300.0)
RATE_BPS = 8e6
# Training 2 samples x 0.5 s, then 1 MiB at 8 Mbit/s: a vehicle needs 2.05 s in its cell.
NEEDED_S = 2 * 0.5 + 8 * MIB / RATE_BPS


class ValueTrainer:
    """Training sets a model to 1; so an untrained vehicle's model stays 0."""

    def initial_state(self):
        return {"w": torch.zeros(1, dtype=torch.float64)}

    def train(self, states, samples, epochs, seed, needed=None):
        return [{"w": torch.ones(1, dtype=torch.float64)} for _ in states]

    def evaluate(self, state):
        return {"loss": 1.0 - float(state["w"][0]), "accuracy": float(state["w"][0])}


def _samples(n: int) -> Samples:
    return Samples.from_numpy(
        np.zeros((n, 4, 1, 1, 3), np.uint8), np.zeros((n, 3), np.float32), np.zeros(n, np.int64), np.zeros(n),
        np.zeros(n), np.zeros(n),
    )


def _clock(a_x_m: float) -> ScriptedClock:
    """a drives east at 10 m/s from ``a_x_m`` and is handed to e1 when it crosses x = 200 m; b and c stand."""
    cross_s = max((200.0 - a_x_m) / 10.0, 0.0)
    return ScriptedClock(
        {"a": [Segment(0.0, 0, RATE_BPS), Segment(cross_s, 1, RATE_BPS)], "b": [Segment(0.0, 0, RATE_BPS)],
         "c": [Segment(0.0, 1, RATE_BPS)]},
        step_s=0.25,
        motion={"a": Pose(a_x_m, 0.0, 10.0, 0.0), "b": Pose(-50.0, 0.0, 0.0, 0.0), "c": Pose(420.0, 0.0, 0.0, 0.0)},
    )


def _step(choice: str, clock: ScriptedClock, policy: str = "miss", coverage=COVERAGE):
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=1, compute_s_per_sample=0.5,
                              handover_policy=policy, selection=choice)
    setup = LoopInputs(
        config=config,
        hyper=HyperParameters(0, 1, 1, 1),
        vehicles=("a", "b", "c"),
        samples={v: _samples(2) for v in "abc"},
        home_site={"a": 0, "b": 0, "c": 1},
        edges=("e0", "e1"),
        sizes=resolve_sizes(SMALL),
        rule="physical",
        coverage=coverage,
    )
    trainer = ValueTrainer()
    return Federation(setup, clock, trainer).step(initial_state(setup, trainer, 0.0))


def _uploaders(state):
    return sorted(r.sender for r in state.records if r.direction == "uplink" and r.link == "wireless")


def test_with_all_a_vehicle_about_to_leave_trains_and_its_upload_is_wasted():
    # a crosses the border 1.5 s in, while uploading: under "miss" its upload fails there
    state = _step("all", _clock(185.0))
    assert _uploaders(state) == ["a", "b", "c"]
    assert [(s["vehicle"], s["reason"]) for s in state.stragglers] == [("a", "outage")]
    (a_up,) = [r for r in state.records if r.sender == "a"]
    assert state.wasted_bytes == a_up.size_bytes > 0  # the bytes it sent before the handover
    assert state.skipped == 0 and "skipped" not in state.metrics[-1]


def test_skip_leaving_skips_it_and_wastes_nothing():
    state = _step("skip_leaving", _clock(185.0))
    assert _uploaders(state) == ["b", "c"]
    assert state.stragglers == [] and state.wasted_bytes == 0
    assert state.skipped == 1 and state.metrics[-2]["skipped"] == ["a"]  # the edge line, then the cloud's
    assert state.edge_weights == {"e0": 2.0, "e1": 2.0}  # only b behind e0's model
    # a sat it out (untrained) but still receives the new global model
    assert any(r.receiver == "a" and r.direction == "downlink" and r.link == "wireless" for r in state.records)
    assert float(state.vehicle_models["a"]["w"][0]) == 1.0


def test_skip_leaving_keeps_a_vehicle_that_stays_long_enough():
    # 10 s to the border at 10 m/s: far more than the 2.05 s it needs
    state = _step("skip_leaving", _clock(100.0))
    assert _uploaders(state) == ["a", "b", "c"] and state.skipped == 0


def test_without_coverage_or_poses_nobody_is_skipped():
    assert _step("skip_leaving", _clock(185.0), coverage=None).skipped == 0
    constant = ScriptedClock.constant({"a": 0, "b": 0, "c": 1}, RATE_BPS, step_s=0.25)
    assert _step("skip_leaving", constant).skipped == 0


def test_an_edge_whose_only_member_is_skipped_keeps_its_model_and_the_run_goes_on():
    config = FederationConfig(scheme="hfl", edge_interval=1, cloud_rounds=2, compute_s_per_sample=0.5,
                              handover_policy="miss", selection="skip_leaving")
    setup = LoopInputs(config=config, hyper=HyperParameters(0, 1, 1, 2), vehicles=("a", "c"),
                       samples={v: _samples(2) for v in "ac"}, home_site={"a": 0, "c": 1}, edges=("e0", "e1"),
                       sizes=resolve_sizes(SMALL), rule="physical", coverage=COVERAGE)
    trainer = ValueTrainer()
    state = Federation(setup, _clock(185.0), trainer).run(initial_state(setup, trainer, 0.0))
    assert state.cloud_rounds == 2 and state.stop_reason == "cloud_rounds"
    # round 1: a is leaving; round 2: a is on e1, not its own edge, so under "miss" it has no time there
    assert state.skipped == 2 and "a" not in _uploaders(state)


def test_the_cell_an_upload_needs_depends_on_the_handover_policy():
    clock = _clock(185.0)  # a is on e1 from 1.5 s
    assert selection.residence_on_clock(clock, "a", 2.0, COVERAGE, own_site=0) == 0.0  # miss/wait: off its edge
    assert selection.residence_on_clock(clock, "a", 2.0, COVERAGE, own_site=None) == pytest.approx(
        (700.0 - 205.0) / 10.0  # new_edge/forward: e1's cell, left at x = 700 m
    )


def test_needed_time_is_training_plus_one_upload():
    assert selection.needed_s(1.0, MIB, RATE_BPS) == pytest.approx(NEEDED_S)
    assert selection.needed_s(1.0, MIB, 0.0) == math.inf
    assert selection.recent_rate_bps(_clock(185.0), "a", 0.0) == RATE_BPS


def test_selection_is_validated_and_read_from_toml_keys():
    with pytest.raises(CrchflError, match="federation.selection: 'nearby' is not one of 'all', 'skip_leaving'"):
        FederationConfig(selection="nearby")
    with pytest.raises(CrchflError, match="SFL has no edge tier"):
        FederationConfig(scheme="sfl", selection="skip_leaving")
    config = from_mapping(RunConfig, {"federation": {"scheme": "hfl", "selection": "skip_leaving"}}, where="test")
    assert config.federation.selection == "skip_leaving"
    assert FederationConfig().selection == "all"


# ------------------------------------------------------------------ a run on the SUMO clock


@pytest.mark.slow
def test_a_sumo_run_skips_moving_vehicles_counts_them_and_resumes_exactly(tmp_path):
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    # 30 s a sample: 60 to 90 s of training, more than a moving vehicle's straight line stays in 300 m
    mapping = run_config(dataset, cloud_rounds=3, compute_s_per_sample=30.0, selection="skip_leaving")
    mapping["clock"] = {"kind": "sumo"}
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)

    class CountTrainer(ValueTrainer):
        def evaluate(self, state):
            return {"loss": 0.5, "accuracy": 0.5}

    summary = run_federation_dir(config, inputs, tmp_path / "whole", trainer=CountTrainer())
    assert summary["selection"] == "skip_leaving" and summary["cloud_rounds"] == 3
    # at the start every vehicle stands (infinite time left): all train; later some drive and are skipped
    assert 0 < summary["skipped_by_selection"] < 3 * len(PAPER_VEHICLES)
    lines = [json.loads(x) for x in (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()]
    edge_lines = [m for m in lines if m["stage"] == "II"]
    assert edge_lines[0]["skipped"] == []
    assert sum(len(m["skipped"]) for m in edge_lines) == summary["skipped_by_selection"]
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", trainer=CountTrainer(), after_checkpoint=kill_after(1))
    run_federation_dir(config, inputs, tmp_path / "killed", trainer=CountTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")
