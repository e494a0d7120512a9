"""Pictures of a run for people: camera mosaics with a top-down view, PNG and MP4 files.

    render_run(frames, renderer, "veh0", out_dir)   the `crchfl-sumo render` body

Images are RGB in memory (as the rasterizer makes them); OpenCV's files want
BGR, so the writers convert. Files are written to a temporary name in the
target directory and moved into place.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from crchfl_sumo.core.atomic import atomic_write_bytes, temporary_beside
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation
from crchfl_sumo.vision.camera import CAMERA_NAMES, ground_rays
from crchfl_sumo.vision.objects import LAMP_RGB, lit_lamps, vehicle_rgb
from crchfl_sumo.vision.raster import Renderer
from crchfl_sumo.vision.world import SKY_RGB, build_world

log = logging.getLogger(__name__)

EGO_RGB = (255, 255, 255)
FOOTPRINT_RGB = ((255, 80, 80), (255, 220, 0), (0, 200, 255), (255, 0, 255))  # CamH, CamF, CamL, CamR
UNLIT_HEAD_RGB = (20, 20, 20)
LABEL_RGB = (255, 255, 255)


def top_down_view(
    renderer: Renderer, frame: Frame, vehicle_id: str, size_px: int = 256, range_m: float = 30.0
) -> np.ndarray:
    """RGB [size, size, 3] map around a vehicle, heading up, ``range_m`` from centre to edge.

    Shows the ground texture, other vehicles (their camera colours), signal heads
    (lit lamp colour or black), the ego (white outline) and the ground each
    camera sees (outlines in FOOTPRINT_RGB order).
    """
    world = renderer.world
    row = frame.index_of(vehicle_id)
    metres_per_px = 2.0 * range_m / size_px
    centre = (size_px - 1) / 2.0
    c, s = math.cos(frame.heading_rad[row]), math.sin(frame.heading_rad[row])
    # view pixel (u, v) -> vehicle (forward, left) -> world -> texture pixel
    vehicle_from_view = np.array(
        [[0.0, -metres_per_px, centre * metres_per_px], [-metres_per_px, 0.0, centre * metres_per_px], [0, 0, 1]]
    )
    world_from_vehicle = np.array([[c, -s, frame.x_m[row]], [s, c, frame.y_m[row]], [0, 0, 1]])
    # The coarsest texture level still at least as fine as the view's pixels.
    texels_m = world.config.metres_per_pixel * 2.0 ** np.arange(len(world.textures))
    level = int(np.flatnonzero(texels_m <= metres_per_px + 1e-12)[-1]) if texels_m[0] <= metres_per_px else 0
    texture_from_view = world.raster_from_world_at(level) @ world_from_vehicle @ vehicle_from_view
    view = cv2.warpAffine(
        world.textures[level], texture_from_view, (size_px, size_px),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=SKY_RGB,
    )
    view_from_world = np.linalg.inv(world_from_vehicle @ vehicle_from_view)[:2]

    def to_view(points_world: np.ndarray) -> np.ndarray:
        return np.round((points_world @ view_from_world[:, :2].T + view_from_world[:, 2]) * 16).astype(np.int32)

    for i, vid in enumerate(frame.ids.tolist()):
        outline = _rectangle(frame.x_m[i], frame.y_m[i], frame.heading_rad[i], frame.length_m[i], frame.width_m[i])
        if i == row:
            cv2.polylines(view, [to_view(outline)], True, EGO_RGB, 1, cv2.LINE_AA, 4)
        else:
            cv2.fillConvexPoly(view, to_view(outline), vehicle_rgb(vid), cv2.LINE_AA, 4)
    lamps = lit_lamps(world, frame.tls_states, renderer.config.mark_permissive)  # as the cameras draw them
    for head, lit in zip(world.heads, lamps):
        rgb = LAMP_RGB[lit[-1]] if lit else UNLIT_HEAD_RGB
        centre_px = to_view(np.array([head.x_m, head.y_m]))
        radius = max(1, int(0.6 / metres_per_px)) * 16
        cv2.circle(view, tuple(int(v) for v in centre_px), radius, rgb, -1, cv2.LINE_AA, 4)
    camera = renderer.config.camera
    for k, rgb in enumerate(FOOTPRINT_RGB):
        ground, hits = ground_rays(camera, k, renderer.config.max_ground_distance_m)
        if not hits.any():
            continue
        hull = cv2.convexHull(ground[hits].astype(np.float32))[:, 0, :].astype(np.float64)
        hull_world = hull @ world_from_vehicle[:2, :2].T + world_from_vehicle[:2, 2]
        cv2.polylines(view, [to_view(hull_world)], True, rgb, 1, cv2.LINE_AA, 4)
    return view


def _rectangle(x_m, y_m, heading_rad, length_m, width_m) -> np.ndarray:
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length_m / 2, width_m / 2]
    return corners @ np.array([[c, s], [-s, c]]) + [x_m, y_m]


def mosaic(camera_images: np.ndarray, top_down: np.ndarray, scale: int = 3) -> np.ndarray:
    """RGB picture: the four cameras in a labelled 2 x 2 grid (enlarged ``scale`` x), the map to the right."""
    if camera_images.shape[0] != len(CAMERA_NAMES):
        raise ValueError(f"expected {len(CAMERA_NAMES)} camera images, got {camera_images.shape[0]}")
    tiles = []
    for name, image in zip(CAMERA_NAMES, camera_images):
        tile = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        cv2.putText(tile, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, LABEL_RGB, 1, cv2.LINE_AA)
        tiles.append(tile)
    grid = np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])])
    side = grid.shape[0]
    top_down = cv2.resize(top_down, (side, side), interpolation=cv2.INTER_NEAREST)
    return np.hstack([grid, top_down])


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write an RGB image as PNG (temporary file, then moved into place)."""
    path = Path(path)
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise CrchflError(f"{path}: OpenCV could not encode the PNG")
    atomic_write_bytes(path, encoded.tobytes())


class VideoWriter:
    """MP4 (mp4v) writer for equal-sized RGB frames; use as a context manager.

    The file appears at ``path`` only when the writer is closed without error.
    """

    def __init__(self, path: str | Path, fps: float):
        self.path = Path(path)
        self.fps = fps
        self._temp: Path | None = None
        self._writer = None
        self.frames_written = 0

    def write(self, rgb: np.ndarray) -> None:
        if self._writer is None:
            self._temp = temporary_beside(self.path)
            height, width = rgb.shape[:2]
            fourcc = cv2.VideoWriter_fourcc(*"mp4v")
            self._writer = cv2.VideoWriter(str(self._temp), fourcc, self.fps, (width, height))
            if not self._writer.isOpened():
                self._temp.unlink(missing_ok=True)
                raise CrchflError(f"{self.path}: OpenCV cannot write MP4 (mp4v) here; use the PNGs instead")
        self._writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        self.frames_written += 1

    def close(self, keep: bool = True) -> None:
        if self._writer is None:
            return
        self._writer.release()
        self._writer = None
        if keep:
            os.replace(self._temp, self.path)
        else:
            self._temp.unlink(missing_ok=True)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(keep=exc_type is None)


@dataclass(frozen=True)
class RunPictures:
    """What render_run wrote."""

    png_paths: tuple[Path, ...]
    video_path: Path
    frames_seen: int


def render_run(
    frames: Iterable[Frame],
    renderer: Renderer,
    vehicle_id: str,
    out_dir: str | Path,
    every_n: int = 1,
    fps: float = 4.0,
    scale: int = 3,
) -> RunPictures:
    """Mosaic PNG for frames 0, every_n, 2 every_n ... that hold ``vehicle_id``, and an MP4 of them all.

    Frames without the vehicle (not yet departed, or arrived) are skipped; a
    vehicle in no frame at all is a CrchflError (a wrong id, most likely).
    PNGs are named step_<frame index>.png; the video is run.mp4 at ``fps``.
    """
    if every_n < 1:
        raise CrchflError(f"every_n: {every_n} must be >= 1")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    seen = 0
    last_ids = np.array([], dtype=str)
    video_path = out_dir / "run.mp4"
    with VideoWriter(video_path, fps) as video:
        for index, frame in enumerate(frames):
            seen += 1
            last_ids = frame.ids
            if index % every_n or vehicle_id not in set(frame.ids.tolist()):
                continue
            images = renderer.render(frame, [vehicle_id])[0]
            picture = mosaic(images, top_down_view(renderer, frame, vehicle_id), scale)
            path = out_dir / f"step_{index:06d}.png"
            write_png(path, picture)
            video.write(picture)
            paths.append(path)
    if not paths:
        some = ", ".join(last_ids[:5].tolist()) if seen else "none"
        raise CrchflError(
            f"vehicle '{vehicle_id}' is in none of the {seen} steps (ids in the last step: {some}); "
            "pick one of those ids or run longer"
        )
    log.info("wrote %d mosaics of %s and %s", len(paths), vehicle_id, video_path)
    return RunPictures(tuple(paths), video_path, seen)


def render_vehicle(
    scenario_name: str, vehicle_id: str, duration_s: float, out_dir: str | Path, every_n: int = 1, seed: int = 0,
    scale: int = 3,
) -> RunPictures:
    """What `crchfl-sumo render` does: simulate ``scenario_name`` and draw ``vehicle_id``'s four cameras
    with a top-down view every ``every_n``-th step into ``out_dir`` (step_*.png, run.mp4)."""
    scenario = load_scenario(scenario_name)
    renderer = Renderer(build_world(scenario.net_path))
    with Simulation(scenario, seed=seed, watch=[vehicle_id]) as sim:
        return render_run(
            sim.run(duration_s), renderer, vehicle_id, out_dir, every_n=every_n,
            fps=1.0 / (scenario.step_length_s * every_n), scale=scale,
        )
