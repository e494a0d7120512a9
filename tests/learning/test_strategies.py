"""Aggregation strategies (learning/strategies.py): FedAvgM's momentum by hand, FedProx's pull towards the
start, a user's strategy by import path, refusals; and in a run: FedProx from a TOML alone, FedAvgM's
memory across a kill and resume."""

from __future__ import annotations

import json

import pytest
import torch

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.federation.run import run_command, run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.learning.model import build_model
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.strategies import FedAvg, FedAvgM, strategy_from, taking_part
from crchfl_sumo.learning.training import train_vehicle

from helpers import PAPER_VEHICLES, Killed, SumTrainer, kill_after, random_samples, result_files, run_config, write_dataset

SMALL = ModelConfig("compact", 48, 64)
CPU = TrainConfig(device="cpu", precision="fp32")


def _w(*values):
    return {"w": torch.tensor(values, dtype=torch.float32), "n": torch.tensor(3)}


def test_fedavg_hands_the_average_on_untouched():
    average = _w(0.5)
    new, memory = FedAvg().server_update("cloud", "cloud", _w(1.0), average, {})
    assert new["w"] is average["w"] and memory == {}


def test_fedavgm_moves_the_cloud_model_with_momentum_by_hand():
    m = FedAvgM(momentum=0.9, server_lr=1.0)
    new, v = m.server_update("cloud", "cloud", _w(1.0), _w(0.5), {})
    assert new["w"].tolist() == [0.5] and v["w"].tolist() == [0.5]  # first: v = 1 - 0.5, new = the average
    new, v = m.server_update("cloud", "cloud", new, _w(0.3), v)
    # v = 0.9 * 0.5 + (0.5 - 0.3) = 0.65, new = 0.5 - 0.65
    assert v["w"].tolist() == pytest.approx([0.65]) and new["w"].tolist() == pytest.approx([-0.15])
    assert new["n"].item() == 3  # counters are averaged, not moved
    edge, memory = m.server_update("edge", "e0", _w(1.0), _w(0.5), {})
    assert edge["w"].tolist() == [0.5] and memory == {}  # the edges average
    half = FedAvgM(momentum=0.0, server_lr=0.5).server_update("cloud", "cloud", _w(1.0), _w(0.5), {})[0]
    assert half["w"].tolist() == [0.75]


def test_fedprox_pulls_local_training_towards_its_start():
    state = build_model(SMALL, seed=0).state_dict()
    samples = random_samples(64, seed=2)
    distance = {}
    for mu in (0.0, 10.0):
        trained = train_vehicle(state, samples, 2, SMALL, CPU, seed=5, proximal_mu=mu)[0]
        distance[mu] = sum(float(((trained[k].double() - state[k].double()) ** 2).sum()) for k in state
                           if state[k].is_floating_point())
    assert distance[10.0] < 0.9 * distance[0.0]
    plain = train_vehicle(state, samples, 1, SMALL, CPU, seed=5)[0]
    zero = train_vehicle(state, samples, 1, SMALL, CPU, seed=5, proximal_mu=0.0)[0]
    assert all(torch.equal(plain[k], zero[k]) for k in plain)  # mu 0 is plain training, bit for bit


def test_strategies_by_name_and_by_import_path_and_refusals(tmp_path, monkeypatch):
    assert strategy_from("fedprox", {"proximal_mu": 0.1}).proximal_mu == 0.1
    assert isinstance(strategy_from("fedavgm", {}), FedAvgM)
    (tmp_path / "my_strategy.py").write_text(
        "class Half:\n"
        "    proximal_mu = 0.0\n"
        "    def __init__(self, share=0.5):\n"
        "        self.share = share\n"
        "    def server_update(self, tier, node, current, average, memory):\n"
        "        return {k: current[k] + self.share * (average[k] - current[k]) for k in current}, {}\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    half = strategy_from("my_strategy:Half", {"share": 0.25})
    assert half.server_update("cloud", "cloud", _w(1.0), _w(0.0), {})[0]["w"].tolist() == [0.75]
    for name, options, match in [
        ("fedsgd", {}, "neither fedavg, fedavgm, fedprox nor"),
        ("no_such_module:X", {}, "federation.strategy: module 'no_such_module' of 'no_such_module:X' is not importable"),
        ("my_strategy:Missing", {}, "names no class"),
        ("fedavgm", {"speed": 1.0}, "strategy_options: .*speed"),
        ("fedavgm", {"momentum": 1.5}, "0 <= momentum < 1"),
        ("fedprox", {"proximal_mu": -1.0}, "0 <= proximal_mu"),
    ]:
        with pytest.raises(CrchflError, match=match):
            strategy_from(name, options)
    with pytest.raises(CrchflError, match="federation.strategy_options.mu"):
        from_mapping(RunConfig, {"federation": {"strategy_options": {"mu": float("nan")}}}, "run.toml")
    with pytest.raises(CrchflError, match="federation.strategy: 'fedavgm' with aggregation"):
        from_mapping(RunConfig, {"federation": {"scheme": "hfl", "aggregation": "async", "strategy": "fedavgm"}}, "r")


def test_fedprox_runs_from_a_toml_alone(tmp_path):
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    summaries = {}
    for name, extra in (("fedavg", ""), ("fedprox", 'strategy = "fedprox"\nstrategy_options = {proximal_mu = 1.0}\n')):
        config = tmp_path / f"{name}.toml"
        config.write_text(
            f'dataset = "{dataset}"\n[federation]\nscheme = "hfl"\nedge_interval = 2\ncloud_rounds = 1\n{extra}'
            '[ledger]\nnominal_model_mb = 10.0\n[model]\nimage_height = 48\nimage_width = 64\n'
            '[train]\ndevice = "cpu"\nprecision = "fp32"\n[clock]\nkind = "constant"\n'
        )
        summaries[name] = run_command(config, tmp_path / name)
    assert summaries["fedprox"]["cloud_rounds"] == summaries["fedavg"]["cloud_rounds"] == 1
    assert summaries["fedprox"]["consumed_bytes"] == summaries["fedavg"]["consumed_bytes"]
    stored = json.loads((tmp_path / "fedprox" / "config.json").read_text())["config"]["federation"]
    assert stored["strategy"] == "fedprox" and stored["strategy_options"] == {"proximal_mu": 1.0}
    from crchfl_sumo.learning.checkpoint import load_checkpoint

    a = load_checkpoint(tmp_path / "fedavg" / "final_model.pt").state_dict
    b = load_checkpoint(tmp_path / "fedprox" / "final_model.pt").state_dict
    assert any(not torch.equal(a[k], b[k]) for k in a)  # the proximal term changed what was learned


def test_fedavgm_keeps_its_momentum_across_a_kill_and_resume(tmp_path):
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    mapping = run_config(dataset, scheme="sfl", cloud_rounds=4, strategy="fedavgm",
                         strategy_options={"momentum": 0.5})
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)
    whole = run_federation_dir(config, inputs, tmp_path / "whole", trainer=SumTrainer())
    plain = run_federation_dir(from_mapping(RunConfig, run_config(dataset, scheme="sfl", cloud_rounds=4)), inputs,
                               tmp_path / "plain", trainer=SumTrainer())
    assert whole["best_accuracy"] != plain["best_accuracy"]  # momentum moved the cloud model elsewhere
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), after_checkpoint=kill_after(2))
    run_federation_dir(config, inputs, tmp_path / "killed", trainer=SumTrainer(), resume=True)
    assert result_files(tmp_path / "killed") == result_files(tmp_path / "whole")


def test_fraction_draws_each_aggregators_share_by_seed_in_the_candidates_order():
    candidates = ("a", "b", "c", "d", "e")
    assert FedAvg().configure("edge", "e0", candidates, 1) is candidates  # every candidate, no draw
    half = FedAvg(fraction=0.5)
    chosen = half.configure("edge", "e0", candidates, 7)
    assert len(chosen) == 3 and set(chosen) <= set(candidates)  # 2.5 rounds up
    assert list(chosen) == sorted(chosen, key=candidates.index)
    assert half.configure("edge", "e0", candidates, 7) == chosen  # the same seed, the same draw
    assert len({half.configure("edge", "e0", candidates, s) for s in range(20)}) > 1
    assert FedAvg(fraction=0.01).configure("cloud", "cloud", candidates, 3) != ()  # at least one
    assert strategy_from("fedprox", {"fraction": 0.4}).fraction == 0.4
    with pytest.raises(CrchflError, match="fraction must lie in"):
        strategy_from("fedavg", {"fraction": 0.0})


def test_a_strategy_without_configure_takes_all_and_one_choosing_strangers_is_refused():
    class Plain:
        proximal_mu = 0.0

    class Stranger(Plain):
        def configure(self, tier, node, candidates, seed):
            return ("x",)

    assert taking_part(Plain(), "edge", "e0", ("a", "b"), 0) == ("a", "b")
    with pytest.raises(CrchflError, match="federation.strategy: configure chose \\['x'\\] for e0"):
        taking_part(Stranger(), "edge", "e0", ("a", "b"), 0)


@pytest.mark.parametrize("scheme, fraction, sits_out", [("hfl", 0.5, 2), ("sfl", 0.4, 3)])
def test_a_fraction_of_the_vehicles_trains_in_a_run_and_the_rest_is_skipped(tmp_path, scheme, fraction, sits_out):
    """HFL, 0.5: edge01 has 2 members (1 trains), edge02 3 (2 train, 1.5 rounded up); SFL, 0.4 of 5: 2 train."""
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    counts = dict(zip((v for v, _, _ in PAPER_VEHICLES), (2, 3, 2, 2, 1)))
    lines = {}
    for name in ("a", "b"):
        config = from_mapping(RunConfig, run_config(dataset, scheme=scheme, cloud_rounds=3,
                                                    strategy_options={"fraction": fraction}))
        summary = run_federation_dir(config, read_inputs(config), tmp_path / name, trainer=SumTrainer())
        lines[name] = [json.loads(x) for x in (tmp_path / name / "metrics.jsonl").read_text().splitlines()]
    trained = [x for x in lines["a"] if "skipped" in x]
    assert len(trained) == 3 and summary["cloud_rounds"] == 3
    for x in trained:
        assert len(x["skipped"]) == sits_out
        assert x["samples"] == sum(n for v, n in counts.items() if v not in x["skipped"])
    assert [x["skipped"] for x in lines["a"] if "skipped" in x] == [x["skipped"] for x in lines["b"] if "skipped" in x]
    with pytest.raises(CrchflError, match="federation.strategy_options: .* with aggregation"):
        from_mapping(RunConfig, {"federation": {"scheme": "hfl", "aggregation": "async",
                                                "strategy_options": {"fraction": 0.5}}}, "r")
