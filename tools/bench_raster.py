"""Benchmark of the rasterizer: four-camera sets per second on one core, beside a memory-copy bound.

    python tools/bench_raster.py [--net PATH] [--vehicles 40] [--repeats 30]

Places ``--vehicles`` cars on random lanes of the network (seeded), gives every
signal a random state, and renders the whole frame (one set per vehicle) again
and again. In the same run it times copying the same number of output bytes,
the floor any renderer that writes its output must pay. OpenCV is held to one
thread so the figure is per core.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import sumolib

from crchfl_sumo.sumo.frame import make_frame
from crchfl_sumo.vision.camera import CameraConfig
from crchfl_sumo.vision.raster import RasterConfig, Renderer
from crchfl_sumo.vision.world import build_world

DEFAULT_NET = Path(__file__).resolve().parent.parent / "scenarios/town01/town01.net.xml"


def random_frame(net_path: Path, n_vehicles: int, seed: int):
    """Vehicles at random points of random passenger lanes, heading along the lane."""
    net = sumolib.net.readNet(str(net_path), withInternal=True, withPrograms=True)
    rng = np.random.default_rng(seed)
    edges = net.getEdges(withInternal=False)
    lanes = [lane for edge in edges for lane in edge.getLanes() if lane.allows("passenger")]
    xs, ys, headings = [], [], []
    for _ in range(n_vehicles):
        shape = np.asarray(lanes[rng.integers(len(lanes))].getShape())
        k = rng.integers(len(shape) - 1)
        a, b = shape[k], shape[k + 1]
        point = a + rng.random() * (b - a)
        xs.append(point[0])
        ys.append(point[1])
        headings.append(np.arctan2(b[1] - a[1], b[0] - a[0]))
    states = {
        tls.getID(): "".join(rng.choice(list("rGy"), size=max(len(tls.getConnections()), 1)))
        for tls in net.getTrafficLights()
    }
    ids = [f"veh{i:03d}" for i in range(n_vehicles)]
    return make_frame(ids=ids, x_m=xs, y_m=ys, heading_rad=headings, tls_states=states)


def best_and_median(fn, repeats: int) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--net", type=Path, default=DEFAULT_NET, help="SUMO .net.xml (default: built-in Town01)")
    parser.add_argument("--vehicles", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--height", type=int, default=CameraConfig().height_px)
    parser.add_argument("--width", type=int, default=CameraConfig().width_px)
    parser.add_argument("--interpolation", choices=("nearest", "linear"), default="nearest")
    args = parser.parse_args()
    if not args.net.is_file():
        parser.error(f"{args.net}: network not found; pass --net PATH")
    cv2.setNumThreads(1)

    start = time.perf_counter()
    world = build_world(args.net)
    build_s = time.perf_counter() - start
    config = RasterConfig(camera=CameraConfig(height_px=args.height, width_px=args.width),
                          interpolation=args.interpolation)
    renderer = Renderer(world, config)
    frame = random_frame(args.net, args.vehicles, args.seed)
    ids = frame.ids.tolist()
    out = renderer.render(frame, ids)  # warm-up
    render_best, render_median = best_and_median(lambda: renderer.render(frame, ids), args.repeats)
    source = np.random.default_rng(0).integers(0, 256, size=out.shape, dtype=np.uint8)
    target = np.empty_like(source)
    copy_best, copy_median = best_and_median(lambda: np.copyto(target, source), args.repeats)

    n = len(ids)
    print(f"network            {args.net}")
    texture_mib = sum(t.nbytes for t in world.textures) / 2**20
    height_px, width_px = world.texture.shape[:2]
    print(f"world texture      {width_px} x {height_px} px, {len(world.textures)} levels "
          f"({texture_mib:.1f} MiB in all), built in {build_s:.2f} s")
    print(f"frame              {n} vehicles, {len(world.heads)} signal heads; "
          f"image {args.height} x {args.width}, {args.interpolation}")
    print(f"output per set     {out[0].nbytes} bytes")
    print(f"render             {n / render_best:9.0f} sets/s (best)  {n / render_median:9.0f} sets/s (median)  "
          f"{render_best / n * 1e6:7.1f} us/set")
    print(f"memory copy bound  {n / copy_best:9.0f} sets/s (best)  {n / copy_median:9.0f} sets/s (median)")
    print(f"ratio render/copy  {copy_best / render_best:.4f} (best over best)")
    print(f"target 2000 sets/s {'met' if n / render_median >= 2000 else 'NOT met'} (median)")


if __name__ == "__main__":
    main()
