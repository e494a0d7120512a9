import numpy as np

from crchfl_sumo.data.route_commands import CommandConfig, track_commands
from crchfl_sumo.data.recording import FUTURE_S
from crchfl_sumo.data.labels import FOLLOW, STRAIGHT
from crchfl_sumo.data.online import OnlineCollector
from crchfl_sumo.sumo.frame import make_frame
from crchfl_sumo.sumo.route import read_net
from crchfl_sumo.sumo.turns import choice_junctions
from crchfl_sumo.vision.camera import CameraConfig
from crchfl_sumo.vision.raster import RasterConfig

STEP_S = 0.25


def frames(seconds, stop_b_after_s):
    """'a' drives east along y = 0 at 8 m/s from x = 10 (through the grid's junction B0 at x = 200);
    'b' drives the same way from x = -190 but stops for good after ``stop_b_after_s``."""
    out = []
    for k in range(1, int(seconds / STEP_S) + 1):
        t = k * STEP_S
        b_x = -190.0 + 8.0 * min(t, stop_b_after_s)
        out.append(make_frame(t, ids=["a", "b"], x_m=[10.0 + 8.0 * t, b_x], y_m=[0.0, 0.0],
                              speed_mps=[8.0, 8.0 if t < stop_b_after_s else 0.0]))
    return out


def test_online_samples_carry_commands_and_speed_and_wait_for_the_path_ahead(grid_dir):
    net = grid_dir / "grid.net.xml"
    raster = RasterConfig(camera=CameraConfig(height_px=24, width_px=48))
    collector = OnlineCollector(net, ["a", "b"], {}, 0.5, STEP_S, raster=raster)
    run = frames(40.0, stop_b_after_s=5.0)
    for frame in run:
        collector.observe(frame)
    got = collector.collected("a", 40.0)
    times = np.arange(1, 61) * 0.5  # samples every 0.5 s up to 40 - FUTURE_S = 30 s
    assert len(got) == len(times) and 40.0 - FUTURE_S == 30.0
    assert got.speed_mps.tolist() == [8.0] * len(times)
    x = 10.0 + 8.0 * np.arange(1, len(run) + 1) * STEP_S
    expected = track_commands(x, np.zeros_like(x), choice_junctions(read_net(net)))
    rows = np.round(times / STEP_S).astype(int) - 1
    assert got.command.tolist() == expected[rows].tolist()
    # Straight across B0 from 25 m before its outline (x about 190) until the vehicle leaves it, else follow.
    x_at = 10.0 + 8.0 * times
    assert set(got.command[x_at < 160.0].tolist()) == {FOLLOW}
    assert set(got.command[(x_at > 170.0) & (x_at < 185.0)].tolist()) == {STRAIGHT}
    assert set(got.command[x_at > 215.0].tolist()) == {FOLLOW}
    # 'b' drove 40 m and stopped: 10 s have passed, but not the 65 m a command needs ahead.
    assert CommandConfig().path_ahead_m == 65.0
    assert collector.collected("b", 40.0) is None
