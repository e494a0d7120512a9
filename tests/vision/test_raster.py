"""Rasterizer tests on a synthetic straight road (no SUMO needed except the netconvert test).

The road runs east-west along y = 0: an eastbound lane centred at y = -1.75 and a
westbound lane at y = +1.75, each 3.5 m wide; a yellow centre line at y = 0,
white edge lines at y = -3.25 and +3.25; a signal for the eastbound lane with
its stop line at x = 50.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import subprocess
import zlib

import numpy as np
import pytest

from crchfl_sumo.core.config import to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.frame import make_frame
from crchfl_sumo.vision.camera import CameraConfig, project_vehicle_points
from crchfl_sumo.vision.objects import (
    LAMP_GREEN_RGB,
    LAMP_HEIGHTS_M,
    LAMP_PERMISSIVE_RGB,
    LAMP_RED_RGB,
    PERMISSIVE_LAMP,
    VEHICLE_PALETTE_RGB,
    lit_lamps,
)
from crchfl_sumo.vision.raster import RasterConfig, Renderer, camera_settings
from crchfl_sumo.vision.world import (
    SKY_RGB,
    WHITE_RGB,
    YELLOW_RGB,
    Marking,
    RoadGeometry,
    SignalHead,
    WorldConfig,
    dash_segments,
    lane_polygon,
    offset_polyline,
    paint_world,
    road_geometry_from_net,
)

CAM_H, CAM_F, CAM_L, CAM_R = range(4)
STOP_X = 50.0
LANE_Y = -1.75


def straight_geometry() -> RoadGeometry:
    east = np.array([[-100.0, LANE_Y], [STOP_X, LANE_Y]])
    west = np.array([[150.0, -LANE_Y], [-100.0, -LANE_Y]])
    east_after = np.array([[STOP_X, LANE_Y], [150.0, LANE_Y]])
    return RoadGeometry(
        road_polygons=[lane_polygon(east, 3.5), lane_polygon(west, 3.5), lane_polygon(east_after, 3.5)],
        markings=[
            Marking(np.array([[-100.0, -3.25], [150.0, -3.25]]), False, WHITE_RGB),
            Marking(np.array([[-100.0, 0.0], [150.0, 0.0]]), False, YELLOW_RGB),
            Marking(np.array([[-100.0, 3.25], [150.0, 3.25]]), False, WHITE_RGB),
        ],
        stop_lines=[np.array([[STOP_X, 0.0], [STOP_X, -3.5]])],
        signal_heads=[SignalHead(STOP_X, -3.9, 0.0, "J", 0)],
    )


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return Renderer(paint_world(straight_geometry(), WorldConfig()), RasterConfig())


def ego_and(others: dict[str, tuple[float, float, float]], ego=(0.0, LANE_Y, 0.0), tls="r"):
    """A frame with the ego 'ego' and other vehicles id -> (x, y, heading)."""
    ids = ["ego"] + list(others)
    poses = [ego] + list(others.values())
    return make_frame(
        ids=ids,
        x_m=[p[0] for p in poses],
        y_m=[p[1] for p in poses],
        heading_rad=[p[2] for p in poses],
        tls_states={"J": tls},
    )


def changed(renderer, others, ego=(0.0, LANE_Y, 0.0)) -> np.ndarray:
    """[4, H, W] mask of pixels the other vehicles change in the ego's cameras."""
    with_them = renderer.render(ego_and(others, ego), ["ego"])[0]
    without = renderer.render(ego_and({}, ego), ["ego"])[0]
    return (with_them != without).any(axis=-1)


def bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    rows, cols = np.nonzero(mask)
    return cols.min(), rows.min(), cols.max(), rows.max()


def test_output_shape_dtype_and_sky(renderer):
    images = renderer.render(ego_and({"a": (30.0, LANE_Y, 0.0)}), ["ego", "a"])
    assert images.shape == (2, 4, 64, 128, 3) and images.dtype == np.uint8
    assert (images[:, CAM_H, 0] == SKY_RGB).all()  # CamH sees sky at the top
    assert not (images[:, CAM_F] == SKY_RGB).all(axis=-1).any()  # CamF looks down: no sky


def test_vehicle_ten_metres_ahead_lands_where_projected(renderer):
    config = renderer.config.camera
    mask = changed(renderer, {"a": (10.0, LANE_Y, 0.0)})[CAM_H]
    # Its rear face: 10 - 4.5/2 m ahead of the ego's centre, 1.8 m wide, 0..1.5 m high.
    rear = np.array([[7.75, 0.9, 0.0], [7.75, -0.9, 0.0], [7.75, 0.9, 1.5], [7.75, -0.9, 1.5]])
    pixels, _ = project_vehicle_points(config, CAM_H, rear)
    expected = (pixels[:, 0].min(), pixels[:, 1].min(), pixels[:, 0].max(), pixels[:, 1].max())
    np.testing.assert_allclose(bbox(mask), expected, atol=2.0)


def test_vehicle_grows_as_it_gets_closer(renderer):
    areas = [changed(renderer, {"a": (x, LANE_Y, 0.0)})[CAM_H].sum() for x in (40.0, 20.0, 10.0, 7.0)]
    assert areas[0] > 0
    assert all(a < b for a, b in zip(areas, areas[1:]))


def test_vehicle_on_the_left_shows_in_cam_l_only(renderer):
    mask = changed(renderer, {"a": (1.0, -LANE_Y, math.pi)})
    assert mask[CAM_L].sum() > 100
    assert not mask[CAM_R].any()


def test_vehicle_on_the_right_shows_in_cam_r_only(renderer):
    mask = changed(renderer, {"a": (1.0, LANE_Y - 3.5, 0.0)})
    assert mask[CAM_R].sum() > 100
    assert not mask[CAM_L].any()


def test_vehicle_behind_shows_in_no_front_camera(renderer):
    mask = changed(renderer, {"a": (-12.0, LANE_Y, 0.0)})
    assert not mask[CAM_H].any() and not mask[CAM_F].any()


def test_vehicle_alongside_is_clipped_at_the_near_plane(renderer):
    # Its right side is 0.1 m from CamL; the face crosses the camera plane.
    mask = changed(renderer, {"a": (1.0, LANE_Y + 2.2, 0.0)})
    assert mask[CAM_L].mean() > 0.3
    assert not mask[CAM_R].any()


def ids_with_distinct_colours(n: int) -> list[str]:
    seen, out = set(), []
    for i in range(100):
        vid = f"v{i}"
        colour = zlib.crc32(vid.encode()) % len(VEHICLE_PALETTE_RGB)
        if colour not in seen:
            seen.add(colour)
            out.append(vid)
        if len(out) == n:
            return out
    raise AssertionError("palette too small")


def test_nearer_vehicle_occludes_farther_one(renderer):
    near_id, far_id = ids_with_distinct_colours(2)
    frame_both = ego_and({near_id: (10.0, LANE_Y, 0.0), far_id: (14.0, LANE_Y - 0.5, 0.0)})
    frame_near = ego_and({near_id: (10.0, LANE_Y, 0.0)})
    both = renderer.render(frame_both, ["ego"])[0, CAM_H]
    near_only = renderer.render(frame_near, ["ego"])[0, CAM_H]
    near_mask = changed(renderer, {near_id: (10.0, LANE_Y, 0.0)})[CAM_H]
    far_mask = changed(renderer, {far_id: (14.0, LANE_Y - 0.5, 0.0)})[CAM_H]
    assert (near_mask & far_mask).sum() > 10  # they overlap in the image
    np.testing.assert_array_equal(both[near_mask], near_only[near_mask])


def test_lane_markings_project_to_predicted_lines(renderer):
    """Every row the centre and edge lines cross holds the marking colour within 1.5 px of the projection.

    Out to 25 m ahead in CamH: far rows sample coarser texture levels, whose lines
    are wider than the pixel spacing, so the lines do not break up with distance.
    """
    config = renderer.config.camera
    image = renderer.render(ego_and({}), ["ego"])[0]
    checked, hit = 0, 0
    for cam, ahead in ((CAM_F, np.linspace(3.0, 12.0, 41)), (CAM_H, np.linspace(4.0, 25.0, 61))):
        for lateral_m, rgb in ((-LANE_Y, YELLOW_RGB), (-1.5, WHITE_RGB)):  # centre line, right edge line
            points = np.stack([ahead, np.full_like(ahead, lateral_m), np.zeros_like(ahead)], 1)
            pixels, depth = project_vehicle_points(config, cam, points)
            for (u, v), d in zip(pixels, depth):
                row = int(round(v))
                if d <= 0 or not (0 <= row < config.height_px and 2 <= u < config.width_px - 2):
                    continue
                cols = np.flatnonzero((image[cam, row] == rgb).all(axis=-1))
                cols = cols[np.abs(cols - u) <= 4]  # the other lines of that colour are farther off
                checked += 1
                if len(cols):
                    assert np.abs(cols - u).min() <= 1.5, (cam, lateral_m, row, u, cols)
                    hit += 1
    assert checked >= 60
    assert hit == checked


def lamp_pixels(config: CameraConfig, ego_x: float, lamp: int) -> np.ndarray:
    """Where a lamp of the test signal projects in CamH for an eastbound ego at ego_x."""
    point = np.array([[STOP_X - 0.16 - ego_x, -3.9 - LANE_Y, LAMP_HEIGHTS_M[lamp]]])
    return project_vehicle_points(config, CAM_H, point)[0][0]


@pytest.mark.parametrize("decel_mps2", [4.5, 2.5])
def test_red_and_green_differ_at_the_lamp_from_stop_distance(renderer, decel_mps2):
    stop_distance_m = 13.89**2 / (2 * decel_mps2)  # 21.4 m hard, 38.6 m comfortable
    ego_x = STOP_X - stop_distance_m - 4.5 / 2  # front bumper at the stop distance
    red = renderer.render(ego_and({}, (ego_x, LANE_Y, 0.0), tls="r"), ["ego"])[0]
    green = renderer.render(ego_and({}, (ego_x, LANE_Y, 0.0), tls="G"), ["ego"])[0]
    differ = (red != green).any(axis=-1)
    assert not differ[[CAM_F, CAM_L, CAM_R]].any()
    rows, cols = np.nonzero(differ[CAM_H])
    assert len(rows) > 0
    config = renderer.config.camera
    reach_px = renderer.config.lamp_min_radius_px + 1.0  # at this distance the lamp is drawn at its minimum radius
    for image, lamp, rgb in ((red, 0, LAMP_RED_RGB), (green, 2, LAMP_GREEN_RGB)):
        u, v = lamp_pixels(config, ego_x, lamp)
        lit = np.argwhere((image[CAM_H] == rgb).all(axis=-1))
        assert len(lit) > 0
        assert np.abs(lit[:, 1] - u).max() <= reach_px and np.abs(lit[:, 0] - v).max() <= reach_px


def test_a_permissive_green_is_drawn_at_the_green_lamp_in_its_own_colour(renderer):
    ego_x = STOP_X - 20.0
    frames = {tls: ego_and({}, (ego_x, LANE_Y, 0.0), tls=tls) for tls in ("G", "g")}
    marking = Renderer(renderer.world, dataclasses.replace(renderer.config, mark_permissive=True))
    protected, permissive = (marking.render(frames[tls], ["ego"])[0, CAM_H] for tls in ("G", "g"))
    u, v = lamp_pixels(renderer.config.camera, ego_x, 2)
    lit = np.argwhere((permissive == LAMP_PERMISSIVE_RGB).all(axis=-1))
    assert len(lit) > 0 and np.abs(lit[:, 1] - u).max() <= 4 and np.abs(lit[:, 0] - v).max() <= 4
    assert not (permissive == LAMP_GREEN_RGB).all(axis=-1).any()
    # Only the lamp's colour differs: the same pixels are lit green under a protected green.
    np.testing.assert_array_equal((protected == LAMP_GREEN_RGB).all(axis=-1), (permissive == LAMP_PERMISSIVE_RGB).all(axis=-1))
    # Unmarked (the default), a permissive green is plain green.
    np.testing.assert_array_equal(renderer.render(frames["g"], ["ego"])[0, CAM_H], protected)
    assert camera_settings({"raster": {"mark_permissive": True}, "world": {}}, "data")[0].mark_permissive is True


def test_route_signal_lights_only_the_routes_head_of_a_lanes_two(renderer):
    # one lane, two links (0: straight, 1: a turn), heads 0.4 m apart: state "Gr", straight green, turn red
    geometry = dataclasses.replace(straight_geometry(), signal_heads=[
        SignalHead(STOP_X, -3.9, 0.0, "J", 0, "e_0"), SignalHead(STOP_X, -4.3, 0.0, "J", 1, "e_0")])
    world = paint_world(geometry, WorldConfig())
    ego_x = STOP_X - 20.0

    def lit(config, link):
        frame = make_frame(ids=["ego"], x_m=[ego_x], y_m=[LANE_Y], tls_states={"J": "Gr"}, tls_ahead_id=["J"],
                           tls_ahead_link=[link])
        image = Renderer(world, config).render(frame, ["ego"])[0, CAM_H]
        return [int((image == rgb).all(axis=-1).sum()) for rgb in (LAMP_RED_RGB, LAMP_GREEN_RGB)]

    every = RasterConfig(route_signal=False)
    both = lit(every, 1)
    assert both[0] > 0 and both[1] > 0  # every head: both lamps drawn, 0.7 px apart at 20 m, overlapping
    assert lit(every, 0) == both  # the route does not matter
    route = RasterConfig()  # the default
    turn, straight = lit(route, 1), lit(route, 0)
    assert turn[0] > 0 and turn[1] == 0  # turning: only the red head lights
    assert straight[0] == 0 and straight[1] > 0  # going straight: only the green one
    # a vehicle with no signal ahead (or another signal's link) sees both
    assert lit(route, -1) == both
    # heads that name no lane (a hand-built geometry) are never grouped: both light
    world = paint_world(dataclasses.replace(geometry, signal_heads=[
        dataclasses.replace(h, lane_id="") for h in geometry.signal_heads]), WorldConfig())
    assert lit(route, 1) == both
    assert camera_settings({"raster": {"route_signal": True}, "world": {}}, "data")[0].route_signal is True
    # a camera block written before the key existed drew every head; a new one always names it
    assert camera_settings({"raster": {}, "world": {}}, "data")[0].route_signal is False
    assert to_mapping(RasterConfig())["route_signal"] is True


def test_lamps_face_the_approaching_traffic_only(renderer):
    ego = (70.0, -LANE_Y, math.pi)  # westbound, looking at the back of the head
    red = renderer.render(ego_and({}, ego, tls="r"), ["ego"])[0]
    green = renderer.render(ego_and({}, ego, tls="G"), ["ego"])[0]
    np.testing.assert_array_equal(red, green)


def test_batch_equals_one_by_one(renderer):
    frame = ego_and({"a": (10.0, LANE_Y, 0.0), "b": (20.0, -LANE_Y, math.pi)})
    together = renderer.render(frame, ["ego", "a", "b"])
    for i, vid in enumerate(["ego", "a", "b"]):
        np.testing.assert_array_equal(together[i], renderer.render(frame, [vid])[0])


def test_unknown_vehicle_and_too_small_margin():
    world = paint_world(straight_geometry(), WorldConfig(margin_m=10.0))
    with pytest.raises(CrchflError, match="margin_m"):
        Renderer(world, RasterConfig())
    with pytest.raises(KeyError):
        Renderer(world, RasterConfig(max_ground_distance_m=5.0)).render(ego_and({}), ["nobody"])


def test_lit_lamps_follow_sumo_letters():
    world = paint_world(straight_geometry())
    assert lit_lamps(world, {"J": "r"}) == [(0,)]
    assert lit_lamps(world, {"J": "y"}) == [(1,)]
    assert lit_lamps(world, {"J": "G"}) == [(2,)]
    assert lit_lamps(world, {"J": "g"}) == [(2,)]
    assert lit_lamps(world, {"J": "g"}, mark_permissive=True) == [(PERMISSIVE_LAMP,)]
    assert lit_lamps(world, {"J": "G"}, mark_permissive=True) == [(2,)]
    assert lit_lamps(world, {"J": "u"}) == [(0, 1)]
    assert lit_lamps(world, {"J": "O"}) == [()]
    assert lit_lamps(world, {}) == [()]


def test_offset_polyline_and_dashes():
    line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    left = offset_polyline(line, 1.0)
    np.testing.assert_allclose(left, [[0, 1], [9, 1], [9, 10]], atol=1e-12)
    dashes = dash_segments(np.array([[0.0, 0.0], [20.0, 0.0]]), 3.0, 6.0)
    starts = [d[0, 0] for d in dashes]
    ends = [d[-1, 0] for d in dashes]
    assert starts == [0.0, 9.0, 18.0] and ends == [3.0, 12.0, 20.0]


@pytest.mark.skipif(shutil.which("netconvert") is None, reason="needs SUMO's netconvert")
def test_world_from_a_sumo_network(tmp_path):
    (tmp_path / "n.nod.xml").write_text(
        '<nodes><node id="A" x="-100" y="0"/><node id="B" x="0" y="0" type="traffic_light"/>'
        '<node id="C" x="100" y="0"/></nodes>'
    )
    (tmp_path / "e.edg.xml").write_text(
        '<edges><edge id="AB" from="A" to="B" numLanes="2"/><edge id="BA" from="B" to="A" numLanes="2"/>'
        '<edge id="BC" from="B" to="C" numLanes="2"/><edge id="CB" from="C" to="B" numLanes="2"/></edges>'
    )
    net = tmp_path / "t.net.xml"
    subprocess.run(
        ["netconvert", "-n", str(tmp_path / "n.nod.xml"), "-e", str(tmp_path / "e.edg.xml"), "-o", str(net),
         "--no-turnarounds"],
        check=True, capture_output=True,
    )
    geometry = road_geometry_from_net(net)
    assert len(geometry.stop_lines) == 4  # two incoming edges at B, two lanes each
    assert {h.tls_id for h in geometry.signal_heads} == {"B"}
    assert len({h.link_index for h in geometry.signal_heads}) == len(geometry.signal_heads)
    yellow = [m for m in geometry.markings if m.rgb == YELLOW_RGB]
    lane_lines = [m for m in geometry.markings if m.dashed]
    assert len(yellow) == 4 and not any(m.dashed for m in yellow)  # one per edge; no overtaking lanes
    assert len(lane_lines) == 4  # between the two lanes of every edge
    world = paint_world(geometry)
    assert (world.texture == YELLOW_RGB).all(axis=-1).any()
    with pytest.raises(CrchflError, match="not found"):
        road_geometry_from_net(tmp_path / "missing.net.xml")


def test_render_run_writes_mosaics_and_video(renderer, tmp_path):
    import cv2

    from crchfl_sumo.vision.mosaic import render_run

    frames = [ego_and({"a": (20.0 + i, LANE_Y, 0.0)}, ego=(float(i), LANE_Y, 0.0)) for i in range(5)]
    frames.append(make_frame(ids=["a"], x_m=[30.0], y_m=[LANE_Y]))  # the ego has left
    result = render_run(frames, renderer, "ego", tmp_path / "out", every_n=2, scale=2)
    assert [p.name for p in result.png_paths] == ["step_000000.png", "step_000002.png", "step_000004.png"]
    assert result.frames_seen == 6
    picture = cv2.imread(str(result.png_paths[0]))
    # 2 x 2 cameras at scale 2 (256 x 512) plus a square map of the grid's height.
    assert picture.shape == (256, 512 + 256, 3)
    assert result.video_path is not None and result.video_path.stat().st_size > 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "run.mp4", "step_000000.png", "step_000002.png", "step_000004.png"
    ]
    with pytest.raises(CrchflError, match=r"'nobody' is in none of the 6 steps \(ids in the last step: a\)"):
        render_run(frames, renderer, "nobody", tmp_path / "none")
    assert not any((tmp_path / "none").iterdir())  # no empty video left behind


def test_the_top_down_view_draws_a_permissive_green_as_the_cameras_do(renderer):
    from crchfl_sumo.vision.mosaic import top_down_view

    frames = {tls: ego_and({}, (STOP_X - 20.0, LANE_Y, 0.0), tls=tls) for tls in ("G", "g")}
    marking = Renderer(renderer.world, dataclasses.replace(renderer.config, mark_permissive=True))
    protected, permissive = (top_down_view(marking, frames[tls], "ego") for tls in ("G", "g"))
    lamp = (protected == LAMP_GREEN_RGB).all(axis=-1)  # the disc's inside (its rim is antialiased)
    assert lamp.sum() >= 4  # a disc of 0.6 m at the view's 0.23 m a pixel
    assert (permissive[lamp] == LAMP_PERMISSIVE_RGB).all()
    assert not (permissive == LAMP_GREEN_RGB).all(axis=-1).any()
    # Unmarked (the default), a permissive green is plain green, as in the cameras.
    np.testing.assert_array_equal(top_down_view(renderer, frames["g"], "ego"), protected)


def test_cheap_visibility_test_never_drops_a_box_a_camera_shows(renderer):
    """CameraReach.may_see is a pre-filter: every camera image a box changes must be flagged."""
    from crchfl_sumo.vision.camera_reach import CameraReach

    reach = CameraReach.of(renderer.config.camera, renderer.config.max_object_distance_m)
    radius = 0.5 * math.hypot(4.5, 1.8)
    rng = np.random.default_rng(3)
    flagged_somewhere = 0
    for _ in range(40):
        forward, left, heading = rng.uniform(-12, 25), rng.uniform(-6, 6), rng.uniform(-math.pi, math.pi)
        if abs(forward) < 3.5 and abs(left) < 2.5:
            continue  # would overlap the ego
        mask = changed(renderer, {"a": (forward, LANE_Y + left, heading)})
        flags = reach.may_see(np.array([[forward, left]]), np.array([radius]))[0]
        assert not (mask.any(axis=(1, 2)) & ~flags).any(), (forward, left, mask.any(axis=(1, 2)), flags)
        flagged_somewhere += flags.any()
    assert flagged_somewhere > 10


def test_world_without_signals_and_a_lone_vehicle():
    geometry = straight_geometry()
    world = paint_world(RoadGeometry(geometry.road_polygons, markings=geometry.markings))
    images = Renderer(world).render(ego_and({}), ["ego"])
    assert images.shape == (1, 4, 64, 128, 3)
    assert Renderer(world).render(ego_and({}), []).shape == (0, 4, 64, 128, 3)


def test_settings_round_trip_through_toml_mappings():
    from crchfl_sumo.core.config import from_mapping, to_mapping

    raster = RasterConfig(camera=CameraConfig(height_px=48, width_px=96), interpolation="linear")
    assert from_mapping(RasterConfig, to_mapping(raster), "raster") == raster
    assert from_mapping(WorldConfig, {"metres_per_pixel": 0.2, "levels": 2}, "world").levels == 2
    with pytest.raises(CrchflError, match="levels"):
        WorldConfig(levels=0)
    with pytest.raises(CrchflError, match="interpolation"):
        from_mapping(RasterConfig, {"interpolation": "cubic"}, "raster")


def test_too_large_a_ground_texture_is_refused_with_a_resolution_that_fits():
    geometry = straight_geometry()
    small = WorldConfig(max_texture_mpx=0.05)
    with pytest.raises(CrchflError, match=r"world.metres_per_pixel: .* over world.max_texture_mpx = 0.05") as info:
        paint_world(geometry, small)
    suggested = float(info.value.args[0].split("metres_per_pixel = ")[1].split(" ")[0])
    world = paint_world(geometry, WorldConfig(metres_per_pixel=suggested, max_texture_mpx=0.05))
    assert world.textures[0].shape[0] * world.textures[0].shape[1] <= 0.05e6
