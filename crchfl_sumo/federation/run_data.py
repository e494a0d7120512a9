"""What a run reads and builds before it starts: the vehicles' data and the test set, each vehicle's home edge, and the clock (SUMO or constant) with its online collector.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.links.clock import Clock, ScriptedClock
from crchfl_sumo.sumo.sites import EdgeSite


@dataclass(frozen=True)
class RunData:
    """What a run reads before it starts: the vehicles' data, the test set, edges, sizes."""

    vehicles: tuple[str, ...]
    samples: Mapping[str, Samples]
    test: Samples
    edges: tuple[str, ...]
    home_site: Mapping[str, int]
    measured_sample_bytes: int | None
    root: Path | None = None  # the data set folder (the online mode reads its camera settings)
    drive_settings: dict | None = None  # Manifest.drive_settings: kept in the model files
    sites: tuple[EdgeSite, ...] = ()  # the edge sites on the SUMO clock; none on the constant clock
    towns: Mapping[str, str] | None = None  # vehicle -> the town its shard was recorded in (where [dagger] drives)


def read_inputs(config: RunConfig) -> RunData:
    """Load the data set (train shards per vehicle, test shards) and map vehicles to edge sites."""
    import torch

    from crchfl_sumo.data.dataset import load_samples, load_vehicle_samples, measured_sample_bytes
    from crchfl_sumo.data.manifest import read_manifest
    from crchfl_sumo.learning.model import check_signal_labels

    root = Path(config.dataset)
    manifest = read_manifest(root)
    if (manifest.image_height, manifest.image_width) != (config.model.image_height, config.model.image_width):
        raise CrchflError(
            f"model.image_height/image_width: {config.model.image_height} x {config.model.image_width} does not "
            f"match the data set's {manifest.image_height} x {manifest.image_width} ({root}); "
            "set them to the data's size"
        )
    manifest.check_model(config.model, str(root))
    samples = load_vehicle_samples(root, "train")
    if not samples:
        raise CrchflError(f"{root}: the data set has no train shards; generate it with `crchfl-sumo dataset`")
    check_signal_labels(config.model, torch.cat([s.signal_state for s in samples.values()]), str(root))
    test = load_samples(root, "test")
    if len(test) == 0:
        raise CrchflError(f"{root}: the data set has no test shards; the run evaluates on them")
    shards = {s.vehicle: s for s in manifest.select("train")}
    vehicles = tuple(shards)
    if config.clock.kind == "sumo":
        from crchfl_sumo.sumo.scenario import configured_scenario

        scenario = configured_scenario(config.scenario, config.sumo, config.mobility.coverage_radius_m)
        edges = tuple(site.name for site in scenario.edge_sites)
        sites = tuple(scenario.edge_sites)
        named = {v for town in scenario.towns for v in town.data_vehicles}
        unknown = sorted(set(vehicles) - named)
        if named and unknown:
            raise CrchflError(
                f"{root}: vehicle(s) {', '.join(unknown)} are not data vehicles of scenario {config.scenario!r} "
                f"({', '.join(sorted(named))}); use the scenario the data set was generated with"
            )
    else:
        edges = tuple(dict.fromkeys(s.edge for s in shards.values()))
        sites = ()
    home = {}
    if config.clock.kind == "sumo" and config.sumo.replaces_sites:
        home = nearest_sites(root, manifest, scenario.edge_sites)
    for v, shard in shards.items():
        if v in home:
            continue
        if shard.edge not in edges:
            raise CrchflError(
                f"{root}: vehicle {v} was recorded at edge {shard.edge!r}, which scenario {config.scenario!r} "
                f"does not have ({', '.join(edges)}); use the scenario the data set was generated with"
            )
        home[v] = edges.index(shard.edge)
    measured = measured_sample_bytes(manifest) if config.ledger.sample_size == "measured" else None
    settings = manifest.drive_settings(f"{root}/manifest.json")
    towns = {v: shard.town for v, shard in shards.items()}
    return RunData(vehicles, samples, test, edges, home, measured, root, settings, sites, towns)


def nearest_sites(root: Path, manifest, sites) -> dict[str, int]:
    """Each vehicle's home: the site nearest its first recorded sample (the run's sites are not the data set's)."""
    from crchfl_sumo.data.shards import read_shard

    xy = np.array([(site.x_m, site.y_m) for site in sites])
    home = {}
    for shard in manifest.select("train"):
        data = read_shard(root, shard, verify=False, images=False)
        first = int(np.argmin(data.t_s))
        home[shard.vehicle] = int(np.argmin(np.hypot(xy[:, 0] - data.x_m[first], xy[:, 1] - data.y_m[first])))
    return home


def make_clock(config: RunConfig, inputs: RunData):
    """The clock of ``config.clock`` (a context manager for SUMO; a plain object otherwise)."""
    if config.clock.kind == "constant":
        clock = ScriptedClock.constant(
            inputs.home_site,
            config.clock.constant_rate_bps,
            config.clock.constant_step_s,
            config.clock.constant_macro_rate_bps,
        )
        return _NoContext(clock)
    from crchfl_sumo.links.clock import SumoClock
    from crchfl_sumo.sumo.scenario import configured_scenario

    scenario = configured_scenario(config.scenario, config.sumo, config.mobility.coverage_radius_m)
    kinds = ("edge",) if config.federation.hierarchical else ("macro",)
    collector = online_collector(config, inputs, scenario) if config.data_mode == "online" else None
    return SumoClock(
        scenario,
        inputs.vehicles,
        config.federation.seed,
        kinds,
        config.channel,
        config.mobility,
        config.sfl_link,
        collector,
    )


def online_collector(config: RunConfig, inputs: RunData, scenario):
    """The online mode's collector, rendering and labelling exactly as the data set was made."""
    from crchfl_sumo.data.online import OnlineCollector
    from crchfl_sumo.data.route_commands import CommandConfig
    from crchfl_sumo.data.manifest import read_manifest
    from crchfl_sumo.data.shards import read_shard
    from crchfl_sumo.vision.raster import camera_settings

    manifest = read_manifest(inputs.root)
    where = f"{inputs.root}/manifest.json"
    raster, world = camera_settings(manifest.camera, f"{where}: camera")
    expert = manifest.expert(where)
    command = from_mapping(CommandConfig, manifest.labels.get("command", {}), f"{where}: labels.command")
    if (raster.camera.height_px, raster.camera.width_px) != (manifest.image_height, manifest.image_width):
        raise CrchflError(f"{where}: camera settings do not match the image size; regenerate the data set")
    # each vehicle goes on collecting after the last sample of its shard
    last_s = {
        s.vehicle: float(np.max(read_shard(inputs.root, s, verify=False, images=False).t_s, initial=-np.inf))
        for s in manifest.select("train")
    }
    return OnlineCollector(
        scenario.net_path,
        inputs.vehicles,
        last_s,
        manifest.sample_period_s,
        scenario.step_length_s,
        raster,
        world,
        expert,
        config.online,
        command,
    )


class _NoContext:
    def __init__(self, clock: Clock) -> None:
        self.clock = clock

    def __enter__(self) -> Clock:
        return self.clock

    def __exit__(self, *exc_info) -> None:
        return None
