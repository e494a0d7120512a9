"""The `crchfl-sumo plan` command and the file reading around problem P.

problem.py is maths only; this module reads the config tables and the
calibration file, measures a scenario's rate (timing.py), and prints the plan.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from crchfl_sumo.accounting.ledger import GIB, LedgerConfig
from crchfl_sumo.core.config import load_tables
from crchfl_sumo.links.channel import ChannelConfig
from crchfl_sumo.links.mobility import MobilityConfig
from crchfl_sumo.planning.problem import Plan, make_plan
from crchfl_sumo.planning.settings import AllocationConfig, calibrated
from crchfl_sumo.planning.timing import planning_rate_bps, scenario_rates_bps


def format_plan(plan: Plan) -> str:
    """Human-readable plan for ``crchfl-sumo plan``."""
    gib = plan.budget_bytes / GIB
    lines = [
        f"CRCHFL plan: budget {gib:g} GB ({plan.budget_bytes} bytes), {plan.rule!r} accounting",
        f"  pretrain_batch  {plan.pretrain_batch}",
        f"  edge_interval   {plan.edge_interval}",
        f"  cloud_interval  {plan.cloud_interval}",
        f"  cloud_rounds    {plan.cloud_rounds}",
        f"  objective       {plan.objective:.1f}",
        "  stage bytes:",
    ]
    for key in ("I", "II", "III"):
        lines.append(f"    {key:<6}{plan.stage_bytes[key] / 2**20:12.1f} MB  {plan.stage_percent[key]:5.1f} %")
    unused = plan.budget_bytes - sum(plan.stage_bytes.values())
    lines.append(f"    {'unused':<6}{unused / 2**20:12.1f} MB  {plan.stage_percent['unused']:5.1f} %")
    lines.append(
        f"  one cloud round: {plan.round_bytes / 2**20:.1f} MB (M = {plan.transfers_per_round:g}), "
        f"{plan.round_time_s:.0f} s; training {plan.training_time_s:.0f} s "
        f"(epoch {plan.epoch_time_s:.1f} s, wireless {plan.wireless_rate_bps / 1e6:.2f} Mbit/s)"
    )
    lines.append(
        f"  solver: {plan.pairs_searched} pairs, compile {plan.compile_s * 1e3:.1f} ms, "
        f"solve {plan.solve_s * 1e3:.1f} ms, search {plan.search_s * 1e3:.1f} ms"
    )
    return "\n".join(lines)


def load_plan_configs(config_path: str | Path | None) -> tuple[AllocationConfig, LedgerConfig]:
    """Read the ``[allocation]`` and ``[ledger]`` tables of a TOML file (other tables are left to their owners)."""
    tables = load_tables(config_path, {"allocation": AllocationConfig, "ledger": LedgerConfig})
    return tables["allocation"], tables["ledger"]


def plan_command(
    budget_gb: float | None = None,
    config_path: str | Path | None = None,
    as_json: bool = False,
    fix_edge_interval: int | None = None,
    scenario: str | None = None,
    seed: int = 0,
) -> str | dict[str, Any]:
    """``crchfl-sumo plan [--budget-gb G] [--config CONFIG] [--json] [--fix-edge-interval N] [--scenario S]``.

    Returns the printable text, or with ``as_json`` a JSON-ready dict.
    Command-line values override the config file. With ``scenario`` the
    wireless rate is measured on that scenario's mobility (its data vehicles'
    edge links over ``rate_window_s``, seeded by ``seed``, with the config's
    ``[channel]`` and ``[mobility]``) instead of read from the config.
    """
    types = {"allocation": AllocationConfig, "ledger": LedgerConfig}
    if scenario is not None:  # the links the measured rate is taken on
        types |= {"channel": ChannelConfig, "mobility": MobilityConfig}
    tables = load_tables(config_path, types)
    allocation, ledger = calibrated(tables["allocation"]), tables["ledger"]
    if budget_gb is not None:
        ledger = dataclasses.replace(ledger, budget_gb=budget_gb)
    if fix_edge_interval is not None:
        allocation = dataclasses.replace(allocation, fix_edge_interval=fix_edge_interval)
    if scenario is not None:
        rates = scenario_rates_bps(scenario, seed, allocation.rate_window_s, tables["channel"], tables["mobility"])
        allocation = dataclasses.replace(allocation, wireless_rate_bps=planning_rate_bps(rates, allocation.rate_window_s))
    plan = make_plan(allocation, ledger)
    if as_json:
        return json.loads(json.dumps(plan.to_dict()))
    return format_plan(plan)
