"""The timing problem P's wall-clock bound takes from a run: link rates from mobility, epoch time from the loop.

The optimizer bounds I_e, I_c and T with a wall-clock budget (planning/problem.py,
"The wall-clock bound"). In a run its inputs are not free settings:

* the mean wireless rate is measured on the run's own clock (the SUMO
  scenario with the channel and association models) over the first
  ``rate_window_s`` seconds of the federated vehicles' edge links, outages
  counted as zero rate, so that slower or patchier mobility gives a
  different plan; the SUMO clock is deterministic per seed and caches its
  steps, so the federation reuses them and the plan is reproducible;
* the epoch time is the federation loop's own compute model
  (``compute_s_per_sample`` x the largest shard: the edge waits for its
  slowest vehicle), the pretraining time per sample ``pretrain_epochs`` x
  the same, and the wireline rate the run's ``[wireline]`` rate, so the
  plan and the loop assume the same seconds, as they charge the same bytes.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.links.clock import Clock, LinkSeries
from crchfl_sumo.planning.settings import AllocationConfig


def time_mean_rate_bps(series: LinkSeries, from_s: float, to_s: float) -> float:
    """Mean of a piecewise-constant rate over [from_s, to_s] (each sample holds until the next)."""
    if not to_s > from_s:
        raise ValueError(f"time_mean_rate_bps: empty window [{from_s}, {to_s}]")
    edges = np.clip(np.append(series.t_s, np.inf), from_s, to_s)
    return float(np.dot(series.rate_bps, np.diff(edges)) / (to_s - from_s))


def measured_rates_bps(
    clock: Clock, vehicles: Sequence[str], window_s: float, kind: str = "edge"
) -> dict[str, float]:
    """Each vehicle's time-mean link rate over the clock's first ``window_s`` seconds."""
    start, end = clock.start_s, clock.start_s + window_s
    return {v: time_mean_rate_bps(clock.series(v, kind, start, end), start, end) for v in vehicles}


def run_timing(
    config: AllocationConfig,
    *,
    samples_per_vehicle: Mapping[str, int],
    compute_s_per_sample: float,
    pretrain_epochs: int,
    rates_bps: Mapping[str, float],
    wireline_rate_bps: float,
) -> AllocationConfig:
    """``config`` with its timing replaced by the run's (see the module docstring)."""
    return dataclasses.replace(
        config,
        epoch_time_s=max(max(samples_per_vehicle.values()), 1) * compute_s_per_sample,
        pretrain_time_per_sample_s=pretrain_epochs * compute_s_per_sample,
        wireless_rate_bps=planning_rate_bps(rates_bps, config.rate_window_s),
        wireline_rate_bps=wireline_rate_bps,
    )


def planning_rate_bps(rates_bps: Mapping[str, float], window_s: float) -> float:
    """The plan's wireless rate: the mean over the federated vehicles (outages count as zero rate)."""
    rates = list(rates_bps.values())
    if not rates or max(rates) <= 0.0:
        raise CrchflError(
            f"allocation.rate_window_s: no federated vehicle had an edge link in the first {window_s:g} s "
            "of the scenario, so the plan has no wireless rate; check the edge sites and mobility.coverage_radius_m, "
            "or lengthen rate_window_s"
        )
    return float(np.mean(rates))


def scenario_rates_bps(scenario_name: str, seed: int, window_s: float, channel=None, mobility=None) -> dict[str, float]:
    """Time-mean edge-link rates of a scenario's data vehicles over its first ``window_s`` seconds."""
    from crchfl_sumo.links.channel import ChannelConfig
    from crchfl_sumo.links.clock import SumoClock
    from crchfl_sumo.links.mobility import MobilityConfig
    from crchfl_sumo.sumo.scenario import load_scenario

    mobility = mobility or MobilityConfig()
    scenario = load_scenario(scenario_name, None, mobility.coverage_radius_m)
    vehicles = [v for town in scenario.towns for v in town.data_vehicles]
    if not vehicles:
        raise CrchflError(
            f"plan --scenario {scenario_name}: the scenario names no data vehicles (scenario.toml data_vehicles), "
            "so there is no federated vehicle to measure; use a built-in scenario or drop --scenario"
        )
    with SumoClock(scenario, vehicles, seed, ("edge",), channel or ChannelConfig(), mobility) as clock:
        return measured_rates_bps(clock, vehicles, window_s)
