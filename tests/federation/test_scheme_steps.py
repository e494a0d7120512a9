"""The schemes' steps (federation/scheme_steps.py): the step each built-in scheme takes when, a user's
sequence named by import path, and the asynchronous edges giving the summaries they gave before they
became a step object (tests/fixtures/async_summaries.json, recorded with the code before).

After an intended change of the asynchronous results, write the file anew:
`python tests/federation/test_scheme_steps.py`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from crchfl_sumo.accounting.ledger import LedgerConfig, resolve_sizes
from crchfl_sumo.core.config import from_mapping, read_toml
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.async_edges import AsyncEdgeStep
from crchfl_sumo.federation.loop import Federation
from crchfl_sumo.federation.run import run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig, builtin_experiments
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.federation.scheme_steps import FlatRoundStep, HierarchicalStep, PretrainingStep, steps_for
from crchfl_sumo.federation.settings import FederationConfig, HyperParameters
from crchfl_sumo.federation.state import LoopInputs, initial_state
from crchfl_sumo.links.channel import WirelineConfig
from crchfl_sumo.links.clock import ScriptedClock

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers import PAPER_VEHICLES, SumTrainer, result_files, run_config, write_dataset  # noqa: E402



HOME = {"a": 0, "b": 0, "c": 1, "d": 1, "e": 1}


def _samples(n):
    return Samples.from_numpy(np.zeros((n, 4, 1, 1, 3), np.uint8), np.zeros((n, 3), np.float32), np.zeros(n, np.int64),
                              np.zeros(n), np.zeros(n), np.zeros(n))


def _setup(config):
    hyper = HyperParameters(config.pretrain_batch, config.edge_interval, config.cloud_interval, config.cloud_rounds)
    return LoopInputs(config=config, hyper=hyper, vehicles=tuple(HOME), samples={v: _samples(2) for v in HOME},
                      home_site=HOME, edges=("e0", "e1"), sizes=resolve_sizes(LedgerConfig()), rule="paper",
                      wireline=WirelineConfig())


class Recorded:
    """The built-in steps, each step's name noted as the loop asks for it (a user's ``scheme_steps`` class)."""

    ran: list[str] = []

    def __init__(self, builtin):
        self.builtin = builtin

    def next_step(self, state):
        step = self.builtin.next_step(state)
        Recorded.ran.append(type(step).__name__)
        return step


class NoNextStep:
    """A ``scheme_steps`` class that cannot say which step comes next: refused."""

    def __init__(self, builtin):
        self.builtin = builtin


@pytest.mark.parametrize(
    "scheme, aggregation, expected",
    [
        ("crchfl", "sync", (PretrainingStep, HierarchicalStep)),
        ("crchfl", "async", (PretrainingStep, AsyncEdgeStep)),
        ("hfl", "sync", (None, HierarchicalStep)),
        ("hfl", "async", (None, AsyncEdgeStep)),
        ("sfl", "sync", (None, FlatRoundStep)),
    ],
)
def test_each_scheme_maps_to_its_steps(scheme, aggregation, expected):
    steps = steps_for(FederationConfig(scheme=scheme, aggregation=aggregation))
    assert (steps.pretraining and type(steps.pretraining), type(steps.training)) == expected


def test_each_builtin_config_maps_to_its_steps():
    names = {}
    for name, path in builtin_experiments().items():
        steps = steps_for(from_mapping(RunConfig, read_toml(path)).federation)
        names[name] = [type(s).__name__ for s in (steps.pretraining, steps.training) if s is not None]
    assert names == {"crchfl": ["PretrainingStep", "HierarchicalStep"], "hfl": ["HierarchicalStep"],
                     "sfl": ["FlatRoundStep"]}


@pytest.mark.parametrize(
    "federation, expected",
    [
        ({"scheme": "crchfl", "pretrain_batch": 4, "cloud_interval": 2},
         ["PretrainingStep"] + ["HierarchicalStep"] * 4),
        ({"scheme": "crchfl", "pretrain_batch": 0}, ["HierarchicalStep"] * 2),  # no stage I to run
        ({"scheme": "hfl", "aggregation": "async", "async_buffer": 2}, ["AsyncEdgeStep"] * 4),  # 2 a round: 2 edges
        ({"scheme": "sfl"}, ["FlatRoundStep"] * 2),
    ],
)
def test_the_loop_runs_the_steps_of_its_scheme_in_order(federation, expected):
    # the stopping rule comes first: the step after the last cloud round asks for no step
    config = FederationConfig(edge_interval=1, cloud_rounds=2, pretrain_epochs=1, **federation)
    setup, trainer = _setup(config), SumTrainer()
    Recorded.ran = []
    steps = Recorded(steps_for(config))
    state = Federation(setup, ScriptedClock.constant(HOME, 8e6), trainer, steps=steps).run(
        initial_state(setup, trainer, 0.0))
    assert Recorded.ran == expected and state.steps == len(expected) + 1 and state.cloud_rounds == 2


def test_a_users_scheme_steps_named_by_import_path_drive_the_run(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    runs = {}
    for name, extra in (("builtin", {}), ("yours", {"scheme_steps": "test_scheme_steps:Recorded"})):
        mapping = run_config(dataset, scheme="crchfl", pretrain_batch=3, pretrain_epochs=1, **extra)
        config = from_mapping(RunConfig, mapping)
        Recorded.ran = []
        run_federation_dir(config, read_inputs(config), tmp_path / name, trainer=SumTrainer())
        runs[name] = result_files(tmp_path / name)
    assert Recorded.ran == ["PretrainingStep", "HierarchicalStep", "HierarchicalStep"]
    assert runs["yours"] == runs["builtin"]  # the same steps: the same results
    for bad in ("test_scheme_steps:HOME", "test_scheme_steps:NoNextStep", "test_scheme_steps:FlatRoundStep"):
        with pytest.raises(CrchflError, match="federation.scheme_steps"):  # no class, no next_step, no argument
            steps_for(FederationConfig(scheme_steps=bad))
