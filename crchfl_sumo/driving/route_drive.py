"""A named route driven by a model or the reference, its outputs written (what `crchfl-sumo drive` does).

It sits above drive.py (the loop) and plots.py (the pictures), so neither of
those imports the other's caller.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from crchfl_sumo.driving.drive import DriveConfig, drive, sumo_warnings
from crchfl_sumo.driving.drivers import driver_for, single_torch_thread
from crchfl_sumo.driving.named_routes import resolve_route
from crchfl_sumo.driving.plots import write_drive_outputs
from crchfl_sumo.learning.settings import DEFAULT_BRAKE_GAIN, DEFAULT_STEER_DECODING
from crchfl_sumo.sumo.outputs import sumo_output_files, sumo_output_options
from crchfl_sumo.sumo.route import read_net, route_geometry
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.vision.raster import Renderer
from crchfl_sumo.vision.world import build_world

SUMO_LOG_FILE = "sumo.log"  # SUMO's warnings of the drive, instead of the console


def drive_route(
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
    sumo_outputs: Sequence[str] = (),
) -> dict[str, Any]:
    """What `crchfl-sumo drive` does: drive a route, write metrics, trajectory, pictures; return the metrics.
    ``sumo_outputs``: SUMO's own files of the drive (sumo.outputs: fcd, tripinfo, summary) as OUT/sumo-NAME.xml.

    ``model_path`` None drives with the scripted RoutePolicy (the reference).
    Writes OUT/metrics.json, OUT/trajectory.csv, OUT/trajectory.png,
    OUT/frames/{red_light,green_light,t_junction_turn}.png (those that occur)
    and OUT/drive.mp4.
    """
    files = sumo_output_files(sumo_outputs, Path(out_dir))  # an unknown name is refused before the drive
    scenario_name, edges = resolve_route(route, scenario)
    loaded = load_scenario(scenario_name)
    net = read_net(Path(loaded.net_path))
    geometry = route_geometry(net, edges)
    driver = driver_for(model_path, steer_decoding, brake_gain)
    policy = driver.policy(geometry, net)
    # The pictures are drawn with the model's cameras; the reference, which reads no images, gets the defaults.
    renderer = driver.renderer(loaded.net_path) if driver.renders else Renderer(build_world(loaded.net_path))
    with single_torch_thread(driver.renders), sumo_output_options(files) as options:
        result = drive(
            loaded, geometry, policy, seed=seed, max_s=max_s, config=config,
            renderer=renderer if driver.renders else None, expert=driver.expert(),
            sumo_log=Path(out_dir) / SUMO_LOG_FILE, sumo_options=options,
        )
    label = driver.label if driver.renders else "route policy"
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
