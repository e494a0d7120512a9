"""The plan's timing taken from the run: time-mean link rates and the loop's compute model."""

import dataclasses

import numpy as np
import pytest

from crchfl_sumo.accounting.ledger import LedgerConfig
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.links.clock import LinkSeries, ScriptedClock, Segment
from crchfl_sumo.planning.problem import make_plan
from crchfl_sumo.planning.settings import AllocationConfig
from crchfl_sumo.planning.timing import measured_rates_bps, run_timing, time_mean_rate_bps

PAPER_LIKE = AllocationConfig(alpha=0.1, gamma=0.5, d=5.0, vehicles_per_edge=(2, 3), local_samples=12584)


def test_time_mean_rate_by_hand():
    series = LinkSeries(np.array([0.0, 1.0, 2.0, 3.0]), np.array([10.0, 0.0, 20.0, 40.0]), np.array([0, -1, 0, 0]))
    # [0.5, 2.5]: 0.5 s at 10, 1 s at 0, 0.5 s at 20 -> 15 / 2
    assert time_mean_rate_bps(series, 0.5, 2.5) == pytest.approx(7.5)
    # past the last sample the last rate holds
    assert time_mean_rate_bps(series, 3.0, 5.0) == pytest.approx(40.0)
    with pytest.raises(ValueError):
        time_mean_rate_bps(series, 1.0, 1.0)


def test_measured_rates_count_outages_as_zero():
    clock = ScriptedClock(
        {"a": [Segment(0.0, 0, 12e6), Segment(100.0, -1, 0.0)], "b": [Segment(0.0, 1, 30e6)]}, step_s=0.5
    )
    rates = measured_rates_bps(clock, ["a", "b", "c"], window_s=300.0)
    assert rates["a"] == pytest.approx(12e6 * 100 / 300)
    assert rates["b"] == pytest.approx(30e6)
    assert rates["c"] == 0.0  # never covered


def test_run_timing_takes_the_loops_compute_model():
    timed = run_timing(
        PAPER_LIKE,
        samples_per_vehicle={"a": 100, "b": 250},
        compute_s_per_sample=0.04,
        pretrain_epochs=10,
        rates_bps={"a": 4e6, "b": 0.0, "c": 8e6},
        wireline_rate_bps=5e8,
    )
    assert timed.epoch_time_s == pytest.approx(250 * 0.04)  # the slowest vehicle
    assert timed.pretrain_time_per_sample_s == pytest.approx(10 * 0.04)
    assert timed.wireless_rate_bps == pytest.approx(4e6)  # mean over vehicles, outage included
    assert timed.wireline_rate_bps == 5e8
    assert (timed.alpha, timed.gamma, timed.d) == (PAPER_LIKE.alpha, PAPER_LIKE.gamma, PAPER_LIKE.d)


def test_no_coverage_is_a_clear_error():
    with pytest.raises(CrchflError, match="rate_window_s"):
        run_timing(PAPER_LIKE, samples_per_vehicle={"a": 1}, compute_s_per_sample=0.1, pretrain_epochs=1,
                   rates_bps={"a": 0.0}, wireline_rate_bps=1e9)


def test_patchier_mobility_gives_another_plan():
    """Same topology and compute, two mobility tracks: the covered one plans more local epochs per round."""
    samples = {"a": 2928, "b": 2586}

    def plan_for(tracks):
        rates = measured_rates_bps(ScriptedClock(tracks), list(samples), PAPER_LIKE.rate_window_s)
        timed = run_timing(PAPER_LIKE, samples_per_vehicle=samples, compute_s_per_sample=120.0 / 2928,
                           pretrain_epochs=10, rates_bps=rates, wireline_rate_bps=1e9)
        return make_plan(timed, LedgerConfig(budget_gb=20.0))

    covered = plan_for({v: [Segment(0.0, 0, 20e6)] for v in samples})
    # covered 30 s of every 300 s: a tenth of the mean rate, so each model hop takes ten times longer
    patchy = plan_for({v: [Segment(0.0, 0, 20e6), Segment(30.0, -1, 0.0)] for v in samples})
    assert covered.wireless_rate_bps == pytest.approx(20e6)
    assert patchy.wireless_rate_bps == pytest.approx(2e6)
    assert covered.edge_interval == 5 and covered.cloud_rounds == 9
    assert (patchy.edge_interval, patchy.cloud_rounds) != (covered.edge_interval, covered.cloud_rounds)
    assert patchy.training_time_s <= PAPER_LIKE.training_time_budget_s


def test_zero_compute_time_is_allowed():
    plan = make_plan(dataclasses.replace(PAPER_LIKE, epoch_time_s=0.0, pretrain_time_per_sample_s=0.0), LedgerConfig())
    assert plan.epoch_time_s == 0.0 and plan.cloud_rounds >= 1


def test_plan_command_measures_the_scenarios_rate():
    from crchfl_sumo.planning.plan_command import plan_command
    from crchfl_sumo.planning.timing import scenario_rates_bps

    rates = scenario_rates_bps("town02", 3, 60.0)
    assert set(rates) == {"t02_data_0", "t02_data_1", "t02_data_2"} and min(rates.values()) > 0
    assert scenario_rates_bps("town02", 3, 60.0) == rates  # seeded: the same mobility and channel
    planned = plan_command(scenario="town02", seed=3, as_json=True, budget_gb=20.0)
    default = plan_command(as_json=True, budget_gb=20.0)
    window = AllocationConfig().rate_window_s
    assert planned["wireless_rate_bps"] == pytest.approx(np.mean(list(scenario_rates_bps("town02", 3, window).values())))
    assert default["wireless_rate_bps"] == AllocationConfig().wireless_rate_bps
    assert planned["round_time_s"] != default["round_time_s"]


def test_plan_command_measures_with_the_configs_channel_and_mobility(tmp_path):
    from crchfl_sumo.links.channel import ChannelConfig
    from crchfl_sumo.planning.plan_command import plan_command
    from crchfl_sumo.planning.timing import scenario_rates_bps

    config = tmp_path / "links.toml"
    config.write_text("[allocation]\nrate_window_s = 60.0\n[channel]\nefficiency = 0.3\n")
    planned = plan_command(config_path=config, scenario="town02", seed=3, as_json=True)
    weaker = scenario_rates_bps("town02", 3, 60.0, ChannelConfig(efficiency=0.3))
    assert planned["wireless_rate_bps"] == pytest.approx(np.mean(list(weaker.values())))
    assert np.mean(list(weaker.values())) < np.mean(list(scenario_rates_bps("town02", 3, 60.0).values()))
    config.write_text("[mobility]\ncoverage_m = 300.0\n")
    with pytest.raises(CrchflError, match="links.toml: mobility.*coverage_m"):
        plan_command(config_path=config, scenario="town02")


def test_plan_command_measures_a_plain_scenario_on_the_vehicles_it_adds(grid_dir):
    # a plain .sumocfg names no data vehicles: the simulation adds them (sumo/injection.py), and the rate is theirs
    from crchfl_sumo.planning.plan_command import plan_command
    from crchfl_sumo.planning.timing import scenario_rates_bps

    planned = plan_command(scenario=str(grid_dir / "grid.sumocfg"), as_json=True)
    rates = scenario_rates_bps(str(grid_dir / "grid.sumocfg"), 0, 60.0)
    assert sorted(rates) == [f"grid_data_{i}" for i in range(5)] and all(r > 0 for r in rates.values())
    assert planned["wireless_rate_bps"] > 0
