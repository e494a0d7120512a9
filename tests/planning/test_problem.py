from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from crchfl_sumo.accounting.ledger import GIB, KIB, MIB, Ledger, LedgerConfig, replay, resolve_sizes
from crchfl_sumo.accounting.schedules import Topology, cloud_round_schedule, schedule_bytes, stage_one_schedule
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.planning.plan_command import format_plan, plan_command
from crchfl_sumo.planning.problem import _Relaxation, costs_for, make_plan, objective_value, round_time_s, split_pretrain_batch
from crchfl_sumo.planning.settings import AllocationConfig

# Explicit values, so that recalibrating the shipped defaults does not change these tests.
PAPER_LIKE = AllocationConfig(
    alpha=0.1,
    gamma=0.5,
    d=5.0,
    vehicles_per_edge=(2, 3),
    local_samples=12584,
    max_edge_interval=10,
    max_cloud_interval=4,
    epoch_time_s=120.0,
    training_time_budget_s=7200.0,
    wireless_rate_bps=20e6,
    wireline_rate_bps=1e9,
    pretrain_time_per_sample_s=0.05,
)


def test_paper_scenario_keeps_nine_cloud_rounds():
    plan = make_plan(PAPER_LIKE, LedgerConfig(budget_gb=20.0))
    # 9 rounds of 2100 MB leave 1580 MB: 449 samples charged twice at 1800 KB
    assert (plan.cloud_rounds, plan.cloud_interval, plan.pretrain_batch) == (9, 1, 449)
    assert plan.round_bytes == 14 * 150 * MIB and plan.transfers_per_round == 7
    assert plan.sample_bytes == 2 * 1800 * KIB
    assert plan.stage_bytes["I"] == 449 * 2 * 1800 * KIB
    assert plan.stage_bytes["II"] == 9 * 5 * 150 * MIB
    assert plan.stage_bytes["III"] == 9 * 9 * 150 * MIB
    assert sum(plan.stage_percent.values()) == pytest.approx(100.0)
    # the wall clock bounds I_e: 9 rounds of (I_e * 120 s + hops) must fit in 7200 s
    assert plan.edge_interval == 5
    assert plan.training_time_s <= PAPER_LIKE.training_time_budget_s
    assert plan.objective == pytest.approx(objective_value(PAPER_LIKE, 449, 5, 1, 9))


def test_mobility_rates_change_the_answer():
    slow = dataclasses.replace(PAPER_LIKE, wireless_rate_bps=2e6)  # 150 MB takes 629 s per wireless hop
    plan = make_plan(slow, LedgerConfig(budget_gb=20.0))
    costs = costs_for(slow, "paper", Topology.from_counts((2, 3)), resolve_sizes(LedgerConfig()))
    assert plan.round_time_s == pytest.approx(round_time_s(slow, costs, plan.edge_interval, plan.cloud_interval))
    assert (plan.edge_interval, plan.cloud_rounds) != (5, 9)


@pytest.mark.parametrize("rule", ["paper", "physical"])
@pytest.mark.parametrize("budget_gb", [3.0, 20.0, 25.0, 40.0])
def test_plan_replays_within_budget(rule, budget_gb):
    ledger_config = LedgerConfig(rule=rule, budget_gb=budget_gb)
    plan = make_plan(PAPER_LIKE, ledger_config)
    sizes = resolve_sizes(ledger_config)
    topo = Topology.from_counts(PAPER_LIKE.vehicles_per_edge)
    local = dict(zip(topo.all_vehicles, (2928, 2928, 2586, 2587, 1555)))
    shares = split_pretrain_batch(plan.pretrain_batch, local)
    ledger = Ledger(sizes)
    stage_one = stage_one_schedule(rule, "crchfl", topo, shares, sizes)
    one_round = cloud_round_schedule(rule, "crchfl", topo, sizes, plan.cloud_interval)
    assert replay(ledger, stage_one, one_round, max_rounds=plan.cloud_rounds) == plan.cloud_rounds
    assert ledger.spent_bytes <= sizes.budget_bytes
    assert ledger.totals("stage") == plan.stage_bytes


def test_fix_edge_interval_ablation():
    for fixed in (2, 3, 4):
        plan = make_plan(dataclasses.replace(PAPER_LIKE, fix_edge_interval=fixed), LedgerConfig())
        assert plan.edge_interval == fixed
        assert 0 < plan.cloud_interval < fixed
    with pytest.raises(CrchflError, match="fix_edge_interval"):
        dataclasses.replace(PAPER_LIKE, fix_edge_interval=1)


def test_costs_read_off_the_schedule():
    topo = Topology.from_counts((2, 3))
    sizes = resolve_sizes(LedgerConfig())
    paper = costs_for(PAPER_LIKE, "paper", topo, sizes)
    physical = costs_for(PAPER_LIKE, "physical", topo, sizes)
    assert paper.sample_bytes == physical.sample_bytes == 2 * 1800 * KIB
    assert paper.stage_one_fixed_bytes == 0
    assert physical.stage_one_fixed_bytes == 7 * 150 * MIB  # release: 2 edges + 5 vehicles
    # one round, by hand: I_c I_e epochs + 2 I_c wireless hops + 2 wireline hops
    hop_w, hop_l = 150 * MIB * 8 / 20e6, 150 * MIB * 8 / 1e9
    assert round_time_s(PAPER_LIKE, paper, 3, 2) == pytest.approx(6 * 120.0 + 4 * hop_w + 2 * hop_l)


def test_relaxation_is_dpp_and_matches_the_lp_by_hand():
    topo = Topology.from_counts((2, 3))
    sizes = resolve_sizes(LedgerConfig())
    costs = costs_for(PAPER_LIKE, "paper", topo, sizes)
    relaxation = _Relaxation(PAPER_LIKE, costs, sizes.budget_bytes, PAPER_LIKE.training_time_budget_s)
    assert relaxation.problem.is_dpp()
    value, x, rounds = relaxation.solve(14 * 150 * MIB, 1.0, 0.0)  # 1 s rounds: time not binding
    # rounds pay more per byte than samples: every byte goes to rounds, T = 20480 / 2100
    assert rounds == pytest.approx(20480 / 2100, rel=1e-6)
    assert x == pytest.approx(0.0, abs=1e-3)
    assert value == pytest.approx(0.5 * 12584 * 20480 / 2100, rel=1e-6)


def _exhaustive(config: AllocationConfig, ledger_config: LedgerConfig, model_bytes: int, sample_bytes: int):
    """Best objective over every integer (I_e, I_c, T, x), bytes from the ledger schedule directly."""
    sizes = resolve_sizes(ledger_config, model_bytes, sample_bytes)
    rule = ledger_config.rule
    topo = Topology.from_counts(config.vehicles_per_edge)
    costs = costs_for(config, rule, topo, sizes)
    first = topo.all_vehicles[0]
    stage_one = [schedule_bytes(stage_one_schedule(rule, "crchfl", topo, {first: x}, sizes))
                 for x in range(config.local_samples + 1)]
    best = None
    for ie in config.edge_intervals():
        for ic in config.cloud_intervals(ie):
            rb = schedule_bytes(cloud_round_schedule(rule, "crchfl", topo, sizes, ic))
            rs = round_time_s(config, costs, ie, ic)
            for rounds in range(1, sizes.budget_bytes // rb + 1):
                for x in range(config.local_samples + 1):
                    bytes_ok = stage_one[x] + rounds * rb <= sizes.budget_bytes
                    stage_one_s = x * costs.sample_time_s + (costs.stage_one_fixed_time_s if x else 0.0)
                    time_ok = rounds * rs + stage_one_s <= config.training_time_budget_s
                    if bytes_ok and time_ok:
                        value = objective_value(config, x, ie, ic, rounds)
                        if best is None or value > best[0]:
                            best = (value, x, ie, ic, rounds)
    return best


@pytest.mark.parametrize("seed", range(8))
def test_search_matches_exhaustive_enumeration(seed):
    rng = np.random.default_rng(seed)
    rule = ("paper", "physical")[seed % 2]
    config = AllocationConfig(
        alpha=float(rng.uniform(0.05, 1.0)),
        gamma=float(rng.uniform(0.05, 1.0)),
        d=float(rng.uniform(0.0, 10.0)),
        vehicles_per_edge=((1, 2), (2, 1), (3,), (1, 1, 1))[seed % 4],
        local_samples=int(rng.integers(5, 40)),
        max_edge_interval=4,
        max_cloud_interval=3,
        epoch_time_s=float(rng.uniform(1.0, 20.0)),
        training_time_budget_s=float(rng.uniform(100.0, 600.0)),
        wireless_rate_bps=float(rng.uniform(1e3, 1e5)),
        wireline_rate_bps=1e6,
        pretrain_time_per_sample_s=float(rng.uniform(0.0, 2.0)),
    )
    model_bytes, sample_bytes = 1000, int(rng.integers(50, 400))
    ledger_config = LedgerConfig(rule=rule, model_size="real", sample_size="measured",
                                 budget_gb=float(rng.uniform(15_000, 60_000)) / GIB)
    plan = make_plan(config, ledger_config, real_model_bytes=model_bytes, measured_sample_bytes=sample_bytes)
    best = _exhaustive(config, ledger_config, model_bytes, sample_bytes)
    assert plan.objective == pytest.approx(best[0], rel=1e-9, abs=1e-9)


def test_infeasible_inputs_name_the_key():
    with pytest.raises(CrchflError, match=r"budget_gb.*at least 0\.1465"):
        make_plan(PAPER_LIKE, LedgerConfig(budget_gb=0.1))
    # one model fits, one cloud round (14 models, 2.05 GB) does not
    with pytest.raises(CrchflError, match=r"budget_gb.*cloud round.*at least 2\.0508"):
        make_plan(PAPER_LIKE, LedgerConfig(budget_gb=1.0))
    with pytest.raises(CrchflError, match="training_time_budget_s"):
        make_plan(dataclasses.replace(PAPER_LIKE, training_time_budget_s=100.0), LedgerConfig())
    with pytest.raises(CrchflError, match="alpha"):
        dataclasses.replace(PAPER_LIKE, alpha=1.5)
    with pytest.raises(CrchflError, match="epoch_time_s"):
        dataclasses.replace(PAPER_LIKE, epoch_time_s=-1.0)
    with pytest.raises(CrchflError, match="vehicles_per_edge"):
        dataclasses.replace(PAPER_LIKE, vehicles_per_edge=(0, 0))
    with pytest.raises(CrchflError, match="measured_sample_bytes"):
        make_plan(PAPER_LIKE, LedgerConfig(model_size="real", sample_size="measured"),
                  real_model_bytes=10, measured_sample_bytes=0)


def test_no_pretraining_when_samples_are_worthless():
    plan = make_plan(dataclasses.replace(PAPER_LIKE, alpha=0.0), LedgerConfig())
    assert plan.cloud_rounds == 9  # alpha = 0: rounds take what they can, the rest stays unused or goes to x
    no_samples = make_plan(dataclasses.replace(PAPER_LIKE, local_samples=0), LedgerConfig())
    assert no_samples.pretrain_batch == 0 and no_samples.stage_bytes["I"] == 0


def test_split_pretrain_batch():
    local = {"a": 2928, "b": 2928, "c": 2586, "d": 2587, "e": 1555}
    shares = split_pretrain_batch(449, local)
    assert sum(shares.values()) == 449
    assert all(abs(shares[v] - 449 * n / 12584) < 1 for v, n in local.items())
    assert split_pretrain_batch(0, local) == {v: 0 for v in local}
    assert split_pretrain_batch(12584, local) == local
    with pytest.raises(CrchflError):
        split_pretrain_batch(12585, local)


def test_plan_command_text_json_and_config(tmp_path):
    text = plan_command(budget_gb=20)
    for word in ("pretrain_batch", "edge_interval", "cloud_interval", "cloud_rounds", "objective", "III"):
        assert word in text
    config = tmp_path / "run.toml"
    config.write_text(
        "[ledger]\nrule = 'physical'\nbudget_gb = 30\n"
        "[allocation]\nepoch_time_s = 60.0\nmax_edge_interval = 4\n"
        "[scenario]\nname = 'ignored here'\n"
    )
    data = plan_command(budget_gb=25, config_path=config, as_json=True, fix_edge_interval=3)
    json.dumps(data)
    assert data["rule"] == "physical" and data["edge_interval"] == 3
    assert data["budget_bytes"] == 25 * GIB  # the command line wins over the file
    assert set(data["stage_bytes"]) == {"I", "II", "III"}
    config.write_text("[allocation]\nalfa = 0.2\n")
    with pytest.raises(CrchflError, match="alfa"):
        plan_command(config_path=config)


def test_format_plan_lists_stage_shares():
    text = format_plan(make_plan(PAPER_LIKE, LedgerConfig()))
    assert "7.7 %" in text and "cloud_rounds    9" in text


def test_calibration_file_supplies_the_weights(tmp_path):
    from crchfl_sumo.planning.calibration import Fit, calibration_toml
    from crchfl_sumo.planning.settings import calibrated

    # the file exactly as `calibrate` writes it (the record's values do not matter here)
    data = {"metric": "loss", "local_samples": 10, "test_samples": 4, "epochs": 2, "reference_samples": [4, 10],
            "reference_scores": [-2.0, -1.0], "pretrain_samples": [2], "pretrain_scores": [-1.5],
            "hfl": [{"edge_interval": 2, "cloud_interval": 1, "cloud_rounds": 1, "score": -1.2}]}
    fit = Fit(0.4, 0.3, 2.5, (1.0, 2.0, 0.5), 0.0, 0.0, 0.0)
    path = tmp_path / "calibration.toml"
    path.write_text(calibration_toml(fit, data, {"pretrain_effective": [1.0], "hfl_effective": [2.0]}, 0, "paper"))
    config = calibrated(dataclasses.replace(PAPER_LIKE, calibration_file=str(path)))
    assert (config.alpha, config.gamma, config.d) == (0.4, 0.3, 2.5)
    assert config.epoch_time_s == PAPER_LIKE.epoch_time_s and config.calibration_file is None
    assert calibrated(PAPER_LIKE) is PAPER_LIKE
    # plan reads it from a config file's [allocation] table
    cfg = tmp_path / "plan.toml"
    cfg.write_text(f'[allocation]\ncalibration_file = "{path}"\n')
    assert plan_command(config_path=cfg, as_json=True)["objective"] == pytest.approx(
        make_plan(calibrated(AllocationConfig(calibration_file=str(path))), LedgerConfig()).objective
    )
    with pytest.raises(CrchflError, match="allocation.calibration_file: .* not found"):
        calibrated(AllocationConfig(calibration_file=str(tmp_path / "missing.toml")))
    (tmp_path / "partial.toml").write_text("[allocation]\nalpha = 0.5\n")
    with pytest.raises(CrchflError, match="no gamma, d"):
        calibrated(AllocationConfig(calibration_file=str(tmp_path / "partial.toml")))
