"""Problem P of the paper (Section IV): split the byte budget between stage I and stages II/III.

    max  alpha * x + gamma * (1 - d / (I_e * I_c * T)) * y
    s.t. x <= u1 / D,   0 < T <= u2 / (2 E M),   0 < I_c < I_e,
         x >= 0, y >= 0, u1 >= 0, u2 > 0,   u1 + u2 = U_sum

x = pretrain_batch (samples uploaded in stage I), I_e = edge_interval (local
epochs between edge aggregations), I_c = cloud_interval (edge aggregations
between cloud aggregations), T = cloud_rounds. The choices the paper leaves
open, all documented in docs/allocation.md:

* D, E, M come from the ledger's schedule (``crchfl_sumo.accounting.ledger``), so the
  plan and the ledger agree on bytes: D = bytes stage I charges per sample,
  2 E M = bytes of one cloud round (I_c edge aggregations and one cloud
  aggregation), plus any fixed stage I cost (the pretrained-model release
  under the ``physical`` rule).
* y = s * T with s = sum_k |T_nk| (all local samples): each cloud round brings
  the distributed data set into the global model once. Then
  gamma * (1 - d / (I_e I_c T)) * y = gamma * s * T - gamma * s * d / (I_e I_c):
  linear in T for a fixed pair, so P is an LP per pair (DCP, and DPP with
  the pair-dependent numbers as ``cp.Parameter``).
* x <= s: vehicles cannot upload more samples than they hold.
* Local epochs are not free: a wall-clock budget W bounds the whole training,
  T * round_time(I_e, I_c) + stage_one_time(x) <= W. In a run, the epoch time
  is the loop's compute model and the wireless rate is measured on the run's
  mobility (planning/timing.py); `plan --scenario` measures the rate the same way.
* T >= 1 stands for the paper's 0 < T (T is an integer).

Solution, the paper's way: search every integer pair (I_e, I_c) within the
bounds, solve the continuous problem in (x, T, u1, u2) with one compiled
CVXPY problem whose parameters change per pair, round (floor T and try its
neighbours, each with the largest x that still fits) and keep the best.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Any, Mapping

import cvxpy as cp

from crchfl_sumo.accounting.ledger import GIB, Ledger, LedgerConfig, replay, resolve_sizes
from crchfl_sumo.accounting.schedules import (
    ByteSizes,
    Topology,
    cloud_round_schedule,
    schedule_bytes,
    stage_one_schedule,
)
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.planning.settings import AllocationConfig

log = logging.getLogger(__name__)

SCHEME = "crchfl"


@dataclass(frozen=True)
class Costs:
    """Bytes and seconds of the plan's building blocks, read off the ledger's schedule."""

    sample_bytes: int  # D: stage I charge per pretraining sample
    stage_one_fixed_bytes: int  # charged once if any sample is uploaded (physical: model release)
    model_bytes: int  # E
    budget_bytes: int  # U_sum
    sample_time_s: float  # stage I wall-clock per sample (upload + pretraining compute)
    stage_one_fixed_time_s: float  # stage I wall-clock charged once (release of the pretrained model)
    wireless_hop_s: float  # one model over one wireless hop
    wireline_hop_s: float  # one model over one wireline hop


@dataclass(frozen=True)
class Plan:
    """The optimizer's answer and what it costs; ``stage_bytes`` come from replaying it through the Ledger."""

    rule: str
    pretrain_batch: int
    edge_interval: int
    cloud_interval: int
    cloud_rounds: int
    objective: float
    effective_samples: float  # y = s * T
    budget_bytes: int
    stage_bytes: dict[str, int]
    stage_percent: dict[str, float]  # of the budget; key "unused" for the rest
    model_bytes: int  # E
    sample_bytes: int  # D
    round_bytes: int  # 2 E M
    transfers_per_round: float  # M
    round_time_s: float
    training_time_s: float
    epoch_time_s: float  # the timing the wall-clock bound assumed
    wireless_rate_bps: float
    pairs_searched: int
    compile_s: float
    solve_s: float
    search_s: float

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def costs_for(config: AllocationConfig, rule: str, topology: Topology, sizes: ByteSizes) -> Costs:
    """D, the fixed stage I cost and the hop times, from the same schedule the ledger charges."""
    first = topology.all_vehicles[0]
    one = schedule_bytes(stage_one_schedule(rule, SCHEME, topology, {first: 1}, sizes))
    two = schedule_bytes(stage_one_schedule(rule, SCHEME, topology, {first: 2}, sizes))
    per_sample = two - one  # every byte of stage I is either per sample or fixed
    model_bits = 8.0 * sizes.model_bytes
    sample_bits = 8.0 * sizes.sample_bytes
    vehicles = len(topology.all_vehicles)
    edges = len(topology.active())
    wireless_hop_s = model_bits / config.wireless_rate_bps
    wireline_hop_s = model_bits / config.wireline_rate_bps
    # vehicles upload their shares in parallel, edges relay theirs in parallel
    sample_time_s = (
        sample_bits / (vehicles * config.wireless_rate_bps)
        + sample_bits / (edges * config.wireline_rate_bps)
        + config.pretrain_time_per_sample_s
    )
    return Costs(
        sample_bytes=per_sample,
        stage_one_fixed_bytes=one - per_sample,
        model_bytes=sizes.model_bytes,
        budget_bytes=sizes.budget_bytes,
        sample_time_s=sample_time_s,
        stage_one_fixed_time_s=wireline_hop_s + wireless_hop_s,
        wireless_hop_s=wireless_hop_s,
        wireline_hop_s=wireline_hop_s,
    )


def round_time_s(config: AllocationConfig, costs: Costs, edge_interval: int, cloud_interval: int) -> float:
    """Wall-clock of one cloud round, timed physically whatever the accounting rule.

    Each edge aggregation: I_e epochs and one wireless upload; all but the last
    send the edge model down (one wireless hop); the cloud aggregation: edge ->
    cloud and cloud -> edge (wireline) and edge -> vehicle (wireless).
    = I_c * I_e * epoch + 2 * I_c * wireless_hop + 2 * wireline_hop.
    """
    return (
        cloud_interval * edge_interval * config.epoch_time_s
        + 2 * cloud_interval * costs.wireless_hop_s
        + 2 * costs.wireline_hop_s
    )


def split_pretrain_batch(total: int, local_samples: Mapping[str, int]) -> dict[str, int]:
    """Split ``total`` uploaded samples over vehicles in proportion to their data (largest remainder).

    The bytes do not depend on the split: every sample crosses one wireless
    and one wireline hop whichever vehicle sends it.
    """
    available = sum(local_samples.values())
    if total < 0 or total > available:
        raise CrchflError(f"pretrain_batch {total} must lie in [0, {available}] (the samples the vehicles hold)")
    if total == 0:
        return {v: 0 for v in local_samples}
    exact = {v: total * n / available for v, n in local_samples.items()}
    share = {v: math.floor(q) for v, q in exact.items()}
    order = sorted(local_samples, key=lambda v: (share[v] - exact[v], v))
    for v in order[: total - sum(share.values())]:
        share[v] += 1
    return share


class _Relaxation:
    """Problem P for one (I_e, I_c) pair, continuous in (x, T, u1, u2); compiled once, re-solved per pair.

    Bytes are scaled to model transfers (E = 1) and time to the wall-clock
    budget (W = 1) so that the solver sees numbers near 1.
    """

    def __init__(self, config: AllocationConfig, costs: Costs, usable_bytes: int, usable_time_s: float) -> None:
        E, W = costs.model_bytes, config.training_time_budget_s
        self.x = cp.Variable(name="x")
        self.T = cp.Variable(name="T")
        self.u1 = cp.Variable(name="u1")
        self.u2 = cp.Variable(name="u2")
        self.round_bytes = cp.Parameter(nonneg=True, name="two_E_M")  # 2 E M / E
        self.round_time = cp.Parameter(nonneg=True, name="round_time")  # / W
        self.discount = cp.Parameter(nonneg=True, name="discount")  # gamma * s * d / (I_e I_c)
        s = config.local_samples
        objective = config.alpha * self.x + config.gamma * s * self.T - self.discount
        constraints = [
            (costs.sample_bytes / E) * self.x <= self.u1,
            self.round_bytes * self.T <= self.u2,
            self.u1 + self.u2 == usable_bytes / E,
            (costs.sample_time_s / W) * self.x + self.round_time * self.T <= usable_time_s / W,
            self.x >= 0,
            self.x <= s,
            self.T >= 1,
            self.u1 >= 0,
            self.u2 >= 0,
        ]
        self.problem = cp.Problem(cp.Maximize(objective), constraints)
        assert self.problem.is_dcp(dpp=True)
        self.solver = config.solver
        self.E, self.W = E, W

    def compile(self, round_bytes: int, round_time_s: float) -> None:
        self._set(round_bytes, round_time_s, 0.0)
        self.problem.get_problem_data(self.solver)

    def _set(self, round_bytes: int, round_time_s: float, discount: float) -> None:
        self.round_bytes.value = round_bytes / self.E
        self.round_time.value = round_time_s / self.W
        self.discount.value = discount

    def solve(self, round_bytes: int, round_time_s: float, discount: float) -> tuple[float, float, float] | None:
        """(objective, x, T) of the relaxation, or None if the solver finds no solution."""
        self._set(round_bytes, round_time_s, discount)
        try:
            self.problem.solve(solver=self.solver)
        except cp.error.SolverError:
            return None
        if self.problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return None
        return float(self.problem.value), float(self.x.value), float(self.T.value)


def _largest_x(config: AllocationConfig, costs: Costs, rounds: int, round_bytes: int, round_s: float) -> int | None:
    """The most pretraining samples that fit next to ``rounds`` cloud rounds; None if the rounds alone do not fit."""
    left_bytes = costs.budget_bytes - rounds * round_bytes
    left_s = config.training_time_budget_s - rounds * round_s
    if left_bytes < 0 or left_s < 0:
        return None
    by_bytes = (left_bytes - costs.stage_one_fixed_bytes) // costs.sample_bytes
    by_time = math.floor((left_s - costs.stage_one_fixed_time_s) / costs.sample_time_s)
    x = min(config.local_samples, by_bytes, by_time)
    return x if x >= 1 else 0


def objective_value(config: AllocationConfig, x: float, edge_interval: int, cloud_interval: int, rounds: float) -> float:
    """alpha x + gamma (1 - d / (I_e I_c T)) y with y = s T."""
    y = config.local_samples * rounds
    return config.alpha * x + config.gamma * (1.0 - config.d / (edge_interval * cloud_interval * rounds)) * y


def make_plan(
    config: AllocationConfig,
    ledger_config: LedgerConfig,
    *,
    real_model_bytes: int | None = None,
    measured_sample_bytes: int | None = None,
    fractions: tuple[float, float] = (1.0, 1.0),
) -> Plan:
    """Solve problem P for the planning topology of ``config`` under the ledger's rule and sizes.

    ``fractions``: (every model transfer's, a vehicle upload's) encoded size over the raw one under an
    update codec (federation.run.codec_fractions): the costs E and M shrink with them, so the plan
    makes more rounds of the same budget.
    """
    sizes = resolve_sizes(ledger_config, real_model_bytes, measured_sample_bytes, *fractions)
    rule = ledger_config.rule
    topology = Topology.from_counts(config.vehicles_per_edge)
    costs = costs_for(config, rule, topology, sizes)
    if costs.sample_bytes <= 0 or costs.model_bytes <= 0:
        raise CrchflError(f"sample size D = {costs.sample_bytes} and model size E = {costs.model_bytes} bytes must be > 0")
    t_start = time.perf_counter()

    pairs = [(ie, ic) for ie in config.edge_intervals() for ic in config.cloud_intervals(ie)]
    if not pairs:
        raise CrchflError("allocation: no (edge_interval, cloud_interval) pair satisfies 0 < cloud_interval < edge_interval")
    round_bytes = {ic: schedule_bytes(cloud_round_schedule(rule, SCHEME, topology, sizes, ic)) for _, ic in pairs}
    feasible = [
        (ie, ic)
        for ie, ic in pairs
        if round_bytes[ic] <= costs.budget_bytes and round_time_s(config, costs, ie, ic) <= config.training_time_budget_s
    ]
    if not feasible:
        _raise_infeasible(config, ledger_config, costs, pairs, round_bytes)

    # The relaxation assumes pretraining happens, so it reserves stage I's fixed cost;
    # the rounding below also tries x = 0, which frees it.
    usable_bytes = max(costs.budget_bytes - costs.stage_one_fixed_bytes, 0)
    usable_s = max(config.training_time_budget_s - costs.stage_one_fixed_time_s, 0.0)
    t_compile = time.perf_counter()
    relaxation = _Relaxation(config, costs, usable_bytes, usable_s)
    ie0, ic0 = feasible[0]
    relaxation.compile(round_bytes[ic0], round_time_s(config, costs, ie0, ic0))
    compile_s = time.perf_counter() - t_compile

    solve_s = 0.0
    best: tuple[float, int, int, int, int] | None = None  # (objective, x, I_e, I_c, T)
    for ie, ic in feasible:
        rb, rs = round_bytes[ic], round_time_s(config, costs, ie, ic)
        t_star = 1.0  # also when only x = 0 leaves room for a round: the rounding tries T = 1 .. t_max
        if rb <= usable_bytes and rs <= usable_s:
            t0 = time.perf_counter()
            relaxed = relaxation.solve(rb, rs, config.gamma * config.local_samples * config.d / (ie * ic))
            solve_s += time.perf_counter() - t0
            if relaxed is None:
                log.warning("allocation: %s found no solution for (I_e, I_c) = (%d, %d)", config.solver, ie, ic)
            else:
                t_star = relaxed[2]
        t_max = min(costs.budget_bytes // rb, math.floor(config.training_time_budget_s / rs))
        candidates = {math.floor(t_star) + k for k in (-1, 0, 1)} | {t_max}
        for rounds in sorted(t for t in candidates if 1 <= t <= t_max):
            x = _largest_x(config, costs, rounds, rb, rs)
            if x is None:
                continue
            value = objective_value(config, x, ie, ic, rounds)
            if best is None or value > best[0] + 1e-9:
                best = (value, x, ie, ic, rounds)
    assert best is not None  # every feasible pair has T = 1, x = 0
    value, x, ie, ic, rounds = best
    search_s = time.perf_counter() - t_start

    ledger = Ledger(sizes)
    shares = split_pretrain_batch(x, _even_local_samples(topology, config.local_samples))
    done = replay(
        ledger,
        stage_one_schedule(rule, SCHEME, topology, shares, sizes),
        cloud_round_schedule(rule, SCHEME, topology, sizes, ic),
        max_rounds=rounds,
    )
    if done != rounds:
        raise RuntimeError(f"plan does not replay: {done} of {rounds} cloud rounds fit")  # a bug, not user input
    stage_bytes = ledger.totals("stage")
    percent = {k: 100.0 * v / sizes.budget_bytes for k, v in stage_bytes.items()}
    percent["unused"] = 100.0 * ledger.remaining_bytes / sizes.budget_bytes
    rs = round_time_s(config, costs, ie, ic)
    stage_one_s = x * costs.sample_time_s + (costs.stage_one_fixed_time_s if x else 0.0)
    plan = Plan(
        rule=rule,
        pretrain_batch=x,
        edge_interval=ie,
        cloud_interval=ic,
        cloud_rounds=rounds,
        objective=value,
        effective_samples=float(config.local_samples * rounds),
        budget_bytes=sizes.budget_bytes,
        stage_bytes=stage_bytes,
        stage_percent=percent,
        model_bytes=sizes.model_bytes,
        sample_bytes=costs.sample_bytes,
        round_bytes=round_bytes[ic],
        transfers_per_round=round_bytes[ic] / (2 * sizes.model_bytes),
        round_time_s=rs,
        training_time_s=rounds * rs + stage_one_s,
        epoch_time_s=config.epoch_time_s,
        wireless_rate_bps=config.wireless_rate_bps,
        pairs_searched=len(feasible),
        compile_s=compile_s,
        solve_s=solve_s,
        search_s=search_s,
    )
    log.info("plan: %s", plan)
    return plan


def _even_local_samples(topology: Topology, total: int) -> dict[str, int]:
    """Planning only needs a split of s over the vehicles; spread it evenly."""
    vehicles = topology.all_vehicles
    base, extra = divmod(total, len(vehicles))
    return {v: base + (1 if i < extra else 0) for i, v in enumerate(vehicles)}


def _raise_infeasible(config: AllocationConfig, ledger_config: LedgerConfig, costs: Costs, pairs, round_bytes) -> None:
    cheapest_bytes = min(round_bytes[ic] for _, ic in pairs)
    if cheapest_bytes > costs.budget_bytes:
        raise CrchflError(
            f"ledger.budget_gb = {ledger_config.budget_gb:g} cannot carry one cloud round ({cheapest_bytes} bytes "
            f"under the {ledger_config.rule!r} rule); set budget_gb to at least {cheapest_bytes / GIB:.4f}"
        )
    fastest_s = min(round_time_s(config, costs, ie, ic) for ie, ic in pairs)
    raise CrchflError(
        f"allocation.training_time_budget_s = {config.training_time_budget_s:g} cannot hold one cloud round "
        f"({fastest_s:.1f} s); set it to at least {math.ceil(fastest_s)} or lower the edge interval"
    )
