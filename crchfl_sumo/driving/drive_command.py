"""The `crchfl-sumo drive` command: load a model or the reference, drive a named route, write the outputs.

It sits above drive.py (the loop) and plots.py (the pictures), so neither of
those imports the other's caller.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

from crchfl_sumo.data.commands import RouteCommands
from crchfl_sumo.data.expert import ExpertConfig, expert_from_labels
from crchfl_sumo.driving.drive import DriveConfig, drive, sumo_warnings
from crchfl_sumo.driving.named_routes import resolve_route
from crchfl_sumo.driving.plots import write_drive_outputs
from crchfl_sumo.driving.policies import ModelPolicy, Policy, RoutePolicy
from crchfl_sumo.learning.settings import DEFAULT_BRAKE_GAIN, DEFAULT_STEER_DECODING
from crchfl_sumo.sumo.route import read_net, route_geometry
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.turns import choice_junctions
from crchfl_sumo.vision.camera import CameraConfig
from crchfl_sumo.vision.raster import RasterConfig, Renderer, camera_settings
from crchfl_sumo.vision.world import build_world


SUMO_LOG_FILE = "sumo.log"  # SUMO's warnings of the drive, instead of the console


def drive_command(
    model_path: str | Path | None,
    scenario: str | None,
    route: str,
    out_dir: str | Path,
    seed: int = 0,
    max_s: float = 120.0,
    config: DriveConfig = DriveConfig(),
    video: bool = True,
    steer_decoding: str = DEFAULT_STEER_DECODING,
    brake_gain: float = DEFAULT_BRAKE_GAIN,
) -> dict[str, Any]:
    """The `crchfl-sumo drive` body: drive a route, write metrics, trajectory, pictures; return the metrics.

    ``model_path`` None drives with the scripted RoutePolicy (the reference).
    Writes OUT/metrics.json, OUT/trajectory.csv, OUT/trajectory.png,
    OUT/frames/{red_light,green_light,t_junction_turn}.png (those that occur)
    and OUT/drive.mp4.
    """
    scenario_name, edges = resolve_route(route, scenario)
    loaded = load_scenario(scenario_name)
    net = read_net(Path(loaded.net_path))
    geometry = route_geometry(net, edges)
    if model_path is None:
        policy: Policy = RoutePolicy(geometry)
        renderer = Renderer(build_world(loaded.net_path))
        label = "route policy"
        expert = ExpertConfig()
    else:
        from crchfl_sumo.learning.checkpoint import checkpoint_model, load_checkpoint

        checkpoint = load_checkpoint(model_path)
        model = checkpoint_model(checkpoint, model_path)
        policy = ModelPolicy(
            model, RouteCommands(geometry, choice_junctions(net)), steer_decoding=steer_decoding, brake_gain=brake_gain,
            source=str(model_path),
        )
        renderer = model_renderer(loaded.net_path, model.config, checkpoint.extra, str(model_path))
        expert = model_expert(checkpoint.extra, str(model_path))
        label = Path(model_path).stem
    with single_torch_thread(model_path is not None):
        result = drive(
            loaded, geometry, policy, seed=seed, max_s=max_s, config=config,
            renderer=renderer if model_path is not None else None, expert=expert,
            sumo_log=Path(out_dir) / SUMO_LOG_FILE,
        )
    metrics = {
        "sumo_warnings": sumo_warnings(Path(out_dir) / SUMO_LOG_FILE),
        "route": route,
        "scenario": scenario_name,
        "edges": list(edges),
        "model": str(model_path) if model_path is not None else "",
        "seed": int(seed),
        "vehicle_length_m": result.vehicle_length_m,
        "vehicle_width_m": result.vehicle_width_m,
        **result.metrics,
    }
    write_drive_outputs(result, loaded, renderer, Path(out_dir), metrics, label, video=video)
    return metrics


def model_renderer(net_path: str | Path, model_config, extra: dict[str, Any], where: str) -> Renderer:
    """A model's cameras as its training data drew them: the data set's raster and world settings
    (a checkpoint's extra "camera", copied from the manifest), or today's defaults at the model's image
    size for a checkpoint written without them."""
    camera = extra.get("camera")
    if not camera:  # written without it (or from a data set that recorded none)
        size = CameraConfig(height_px=model_config.image_height, width_px=model_config.image_width)
        raster = RasterConfig(camera=size)
        return Renderer(build_world(net_path), raster)
    raster, world = camera_settings(camera, f"{where}: extra.camera")
    return Renderer(build_world(net_path, world), raster)


def model_expert(extra: dict[str, Any], where: str) -> ExpertConfig:
    """The expert settings a model's data set was labelled with (a checkpoint's extra "expert", copied from
    the manifest): the drive's dynamics steer through the same rack. A checkpoint written without them
    was labelled with the linear rack of the time (data.expert.LINEAR_RACK)."""
    return expert_from_labels(extra.get("expert", {}), f"{where}: extra.expert")


@contextlib.contextmanager
def single_torch_thread(active: bool):
    """One torch thread while a model drives: one sample a step gains nothing from more, and on a
    busy machine the threads' spinning made a step 100 times slower (docs/drive.md)."""
    if not active:
        yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
