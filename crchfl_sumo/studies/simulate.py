"""`crchfl-sumo simulate`: run a scenario with the link model and write what mobility did.

DIR/trace.csv      per step and vehicle: t_s, vehicle, x_m, y_m, speed_mps, edge, rate_bps
DIR/handovers.csv  every change of serving edge (t_s, vehicle, from, to; '' = no coverage)
DIR/summary.json   vehicles, steps, handovers, ping_pongs, mean_rate_bps, coverage_fraction, ...
DIR/map.png        network, edge sites with coverage circles, trajectories coloured by edge
DIR/rate.png       rate over time: each edge's mean and the named data vehicles
DIR/sumo-NAME.xml  with --sumo-output NAME,...: SUMO's own output (fcd, tripinfo, summary), for sumolib
(summary.json also holds the settings used, under "config".)

The run itself (``simulate``) returns a ``Trace`` of arrays; summarising is a
pure function of it; writing is the edge.
"""

from __future__ import annotations

import csv
import dataclasses
import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.config import from_mapping, read_toml, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.figures import pyplot, save_figure
from crchfl_sumo.core.json_files import write_json
from crchfl_sumo.core.numbers import MAX_SIMULATED_S, check_range
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.core.result_files import SUMMARY_FILE
from crchfl_sumo.links.channel import ChannelConfig
from crchfl_sumo.links.mobility import NO_SITE, LinkModel, MobilityConfig, ping_pongs
from crchfl_sumo.sumo.maps import draw_network
from crchfl_sumo.sumo.outputs import sumo_output_files, sumo_output_options
from crchfl_sumo.sumo.scenario import Scenario, load_scenario
from crchfl_sumo.sumo.simulation import Simulation
from crchfl_sumo.sumo.sites import EdgeSite
from crchfl_sumo.sumo.sumocfg import write_sumocfg

DEFAULT_DURATION_S = 300.0  # simulated seconds of a scenario whose configuration sets no end


@dataclass(frozen=True)
class SimulateConfig:
    """Settings of a mobility run (TOML: top-level ``seed``, ``[[edge_sites]]``, ``[channel]``, ``[mobility]``)."""

    seed: int = 0
    edge_sites: tuple[EdgeSite, ...] | None = None  # None: the scenario's own, or placed automatically
    channel: ChannelConfig = field(default_factory=ChannelConfig)
    mobility: MobilityConfig = field(default_factory=MobilityConfig)


def load_simulate_config(path: str | Path | None, seed: int | None = None) -> SimulateConfig:
    cfg = SimulateConfig() if path is None else from_mapping(SimulateConfig, read_toml(path), where=str(path))
    return cfg if seed is None else dataclasses.replace(cfg, seed=seed)


@dataclass(frozen=True)
class Trace:
    """Flat per-(step, vehicle) columns of a run, plus its handovers and counters."""

    t_s: np.ndarray
    vehicle: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    speed_mps: np.ndarray
    site: np.ndarray  # serving site index, -1 none
    rate_bps: np.ndarray
    handovers: tuple  # snapshots.Handover records
    steps: int
    teleports: int
    collisions: int


def simulate(
    scenario: Scenario,
    duration_s: float,
    cfg: SimulateConfig,
    progress: Progress | None = None,
    sumo_outputs: Mapping[str, Path] | None = None,
) -> Trace:
    """Run ``scenario`` for ``duration_s`` with the link model stepping on every frame; ``sumo_outputs``
    (sumo_output_files) are SUMO's own files written as well."""
    links = LinkModel(scenario.edge_sites, cfg.channel, cfg.mobility, seed=cfg.seed)
    cell_users = np.full(len(scenario.edge_sites), float(cfg.mobility.cell_background_users))
    columns: dict[str, list[np.ndarray]] = {k: [] for k in ("t_s", "vehicle", "x_m", "y_m", "speed_mps", "site", "rate_bps")}
    handovers = []
    total_steps = int(round(duration_s / scenario.step_length_s))
    # Positions and speeds are all the links and the trace read: no lanes, signals ahead or signal states.
    with sumo_output_options(sumo_outputs) as options, Simulation(
        scenario, seed=cfg.seed, watch=(), signals=False, extra_options=options
    ) as sim:
        for frame in sim.run(duration_s):
            # every vehicle here is a user already: of the background load only the cells' other users
            snapshot = links.step(frame, background_users=cell_users)
            columns["t_s"].append(np.full(len(frame), frame.t_s))
            columns["vehicle"].append(frame.ids)
            columns["x_m"].append(frame.x_m)
            columns["y_m"].append(frame.y_m)
            columns["speed_mps"].append(frame.speed_mps)
            columns["site"].append(snapshot.site)
            columns["rate_bps"].append(snapshot.rate_bps)
            handovers.extend(snapshot.handovers)
            report(progress, "simulate", len(columns["t_s"]), total_steps)
        stats = sim.stats()
    joined = {
        k: np.concatenate(v) if v else np.zeros(0, dtype=str if k == "vehicle" else float) for k, v in columns.items()
    }
    return Trace(
        **joined,
        handovers=tuple(handovers),
        steps=stats.steps,
        teleports=stats.teleports,
        collisions=stats.collisions,
    )


def summarize(trace: Trace, scenario: Scenario, duration_s: float, cfg: SimulateConfig) -> dict:
    """The figures of a run: plain JSON-ready values."""
    covered = trace.site != NO_SITE
    samples = len(trace.site)
    per_site = {
        site.name: {
            "samples": int(np.sum(trace.site == i)),
            "mean_rate_bps": float(trace.rate_bps[trace.site == i].mean()) if np.any(trace.site == i) else 0.0,
        }
        for i, site in enumerate(scenario.edge_sites)
    }
    # Handovers proper: from one edge to another (attach/detach to no coverage counted apart).
    between_sites = sum(1 for h in trace.handovers if h.from_site != NO_SITE and h.to_site != NO_SITE)
    return {
        "scenario": scenario.name,
        "sumocfg": str(scenario.sumocfg_path),
        "seed": cfg.seed,
        "duration_s": duration_s,
        "steps": trace.steps,
        "step_length_s": scenario.step_length_s,
        "vehicles": int(len(np.unique(trace.vehicle))),
        "handovers": between_sites,
        "ping_pongs": ping_pongs(trace.handovers),  # of those, undone within mobility.PING_PONG_S
        "coverage_changes": len(trace.handovers) - between_sites,
        "mean_rate_bps": float(trace.rate_bps[covered].mean()) if covered.any() else 0.0,
        "coverage_fraction": float(covered.mean()) if samples else 0.0,
        "teleports": trace.teleports,
        "collisions": trace.collisions,
        "edge_sites": [to_mapping(s) for s in scenario.edge_sites],
        "per_edge": per_site,
        "config": to_mapping(cfg),
    }


def write_outputs(trace: Trace, scenario: Scenario, summary: dict, out_dir: Path) -> None:
    """trace.csv, handovers.csv, summary.json and the two plots, each written atomically."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = np.array([s.name for s in scenario.edge_sites] + [""], dtype=object)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["t_s", "vehicle", "x_m", "y_m", "speed_mps", "edge", "rate_bps"])
    writer.writerows(
        zip(
            np.round(trace.t_s, 3).tolist(),
            trace.vehicle.tolist(),
            np.round(trace.x_m, 3).tolist(),
            np.round(trace.y_m, 3).tolist(),
            np.round(trace.speed_mps, 3).tolist(),
            names[trace.site].tolist(),
            np.round(trace.rate_bps, 1).tolist(),
        )
    )
    atomic_write_text(out_dir / "trace.csv", buffer.getvalue())
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["t_s", "vehicle", "from_edge", "to_edge"])
    writer.writerows((h.t_s, h.vehicle_id, names[h.from_site], names[h.to_site]) for h in trace.handovers)
    atomic_write_text(out_dir / "handovers.csv", buffer.getvalue())
    write_json(out_dir / SUMMARY_FILE, summary)
    plot_map(trace, scenario, summary, out_dir / "map.png")
    plot_rates(trace, scenario, out_dir / "rate.png")


def plot_map(trace: Trace, scenario: Scenario, summary: dict, path: Path) -> None:
    plt = pyplot()
    from matplotlib.patches import Circle

    fig, ax = plt.subplots(figsize=(8, 6))
    draw_network(ax, scenario.net_path)
    colours = plt.get_cmap("tab10")
    radius_m = summary["config"]["mobility"]["coverage_radius_m"]
    for i, site in enumerate(scenario.edge_sites):
        colour = colours(i % 10)
        ax.add_patch(Circle((site.x_m, site.y_m), radius_m, fill=False, ls="--", color=colour, alpha=0.6))
        ax.plot(site.x_m, site.y_m, marker="^", ms=12, color=colour, mec="k", zorder=4)
        ax.annotate(site.name, (site.x_m, site.y_m), textcoords="offset points", xytext=(6, 6), zorder=5)
        served = trace.site == i
        ax.scatter(trace.x_m[served], trace.y_m[served], s=1, color=colour, zorder=2)
    lost = trace.site == NO_SITE
    ax.scatter(trace.x_m[lost], trace.y_m[lost], s=1, color="k", zorder=2, label="no coverage")
    ax.set_title(
        f"{scenario.name}: {summary['vehicles']} vehicles, {summary['handovers']} handovers, "
        f"coverage {100 * summary['coverage_fraction']:.1f}%"
    )
    ax.autoscale_view()
    save_figure(fig, path)


def plot_rates(trace: Trace, scenario: Scenario, path: Path) -> None:
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(9, 4))
    times = np.unique(trace.t_s)
    step_index = np.searchsorted(times, trace.t_s)
    for i, site in enumerate(scenario.edge_sites):
        served = trace.site == i
        total = np.bincount(step_index[served], weights=trace.rate_bps[served], minlength=len(times))
        count = np.bincount(step_index[served], minlength=len(times))
        with np.errstate(invalid="ignore", divide="ignore"):
            ax.plot(times, total / count / 1e6, lw=1.5, label=f"{site.name} mean")
    for vehicle in [v for town in scenario.towns for v in town.data_vehicles][:5]:
        rows = trace.vehicle == vehicle
        if rows.any():
            ax.plot(trace.t_s[rows], trace.rate_bps[rows] / 1e6, lw=0.6, alpha=0.7, label=vehicle)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("rate [Mbit/s]")
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path)


def run_simulate_command(
    scenario_name: str,
    duration_s: float | None,
    out_dir: Path,
    seed: int | None,
    config_path: Path | None,
    progress: Progress | None = None,
    sumo_outputs: Sequence[str] = (),
    net: Path | None = None,
    routes: Sequence[Path] = (),
) -> dict:
    """What `crchfl-sumo simulate` does; returns the summary. ``sumo_outputs``: SUMO's own files to write
    as well (sumo.outputs.SUMO_OUTPUTS' names). ``net`` (and ``routes``) instead of ``scenario_name``: a bare network,
    run through a .sumocfg written into ``out_dir`` for it (sumocfg.write_sumocfg).

    ``duration_s`` None: the scenario's own length (its configuration's end), else DEFAULT_DURATION_S.
    """
    files = sumo_output_files(sumo_outputs, out_dir)  # refused before anything runs
    if net is not None:
        scenario_name = str(write_sumocfg(out_dir, net, routes))
    cfg = load_simulate_config(config_path, seed)
    scenario = load_scenario(scenario_name, cfg.edge_sites, cfg.mobility.coverage_radius_m)
    if duration_s is None:
        duration_s = scenario.length_s or DEFAULT_DURATION_S
    check_range(duration_s, "simulate --duration-s", 0.0, MAX_SIMULATED_S, "simulated seconds", lo_open=True)
    if duration_s < scenario.step_length_s:
        raise CrchflError(
            f"simulate --duration-s: {duration_s:g} s is shorter than one step of {scenario.name} "
            f"({scenario.step_length_s:g} s); simulate at least one step"
        )
    trace = simulate(scenario, duration_s, cfg, progress=progress, sumo_outputs=files)
    summary = summarize(trace, scenario, duration_s, cfg)
    write_outputs(trace, scenario, summary, out_dir)
    return summary
