import dataclasses

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.dataset import load_samples
from crchfl_sumo.data.settings import DatasetConfig, shard_plan
from crchfl_sumo.data.generation import assign_vehicles, generate_dataset, nearest_site
from crchfl_sumo.data.labels import digitize_steer
from crchfl_sumo.data.manifest import read_manifest
from crchfl_sumo.data.shards import read_shard
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.sites import EdgeSite
from crchfl_sumo.vision.camera import CameraConfig
from crchfl_sumo.vision.raster import RasterConfig

SIZES = {"towns": [{"town": "town01", "train_samples": [6, 5], "test_samples": [4]}]}
RASTER = RasterConfig(camera=CameraConfig(height_px=24, width_px=48))


def paper_scenario():
    return load_scenario("paper")


class Stop(Exception):
    pass


def test_vehicles_come_from_the_scenario_towns():
    scenario = paper_scenario()
    sizes = from_mapping(DatasetConfig, SIZES)
    assert list(assign_vehicles(scenario, shard_plan(sizes)).values()) == ["t01_data_0", "t01_data_1", "t01_test_0"]
    too_many = from_mapping(DatasetConfig, {"towns": [{"town": "town01", "train_samples": [1, 1, 1]}]})
    with pytest.raises(CrchflError, match="3 train vehicles wanted, scenario 'paper' names 2 in its town's data_vehicles; ask for fewer"):
        assign_vehicles(scenario, shard_plan(too_many))
    with pytest.raises(CrchflError, match="no town 'Town9'"):
        assign_vehicles(scenario, shard_plan(from_mapping(DatasetConfig, {"towns": [{"town": "Town9", "train_samples": [1]}]})))


def test_a_plain_sumocfg_gets_data_vehicles_and_a_split_of_its_own(tmp_path):
    """A .sumocfg without a scenario.toml has one town, the whole network, with vehicles added to it."""
    import shutil

    from crchfl_sumo.data.settings import PAPER_TOWNS
    from crchfl_sumo.data.generation import DEFAULT_TEST_SAMPLES, DEFAULT_TRAIN_SAMPLES, sizes_for
    from crchfl_sumo.sumo.injection import InjectConfig

    town01 = load_scenario("town01")
    shutil.copy(town01.net_path, tmp_path / "grid.net.xml")
    (tmp_path / "grid.sumocfg").write_text(
        '<configuration><input><net-file value="grid.net.xml"/></input></configuration>'
    )
    plain = load_scenario(tmp_path / "grid.sumocfg")
    # the default sizes (the paper's towns, which it lacks) become 5 data and 1 test vehicle of its one town
    sizes = sizes_for(DatasetConfig(), plain)
    assert [(t.town, t.train_samples, t.test_samples) for t in sizes.towns] == [
        ("grid", (DEFAULT_TRAIN_SAMPLES,) * 5, (DEFAULT_TEST_SAMPLES,))]
    assert sorted(assign_vehicles(plain, shard_plan(sizes)).values()) == [
        "grid_data_0", "grid_data_1", "grid_data_2", "grid_data_3", "grid_data_4", "grid_test_0"]
    assert sizes_for(DatasetConfig(), paper_scenario()).towns == PAPER_TOWNS  # a scenario that has them keeps them
    many = from_mapping(DatasetConfig, {"towns": [{"town": "grid", "train_samples": [5] * 6}]})
    with pytest.raises(CrchflError, match=r"6 train vehicles wanted, scenario 'grid' names 5 .*\[sumo\] data_vehicles"):
        assign_vehicles(plain, shard_plan(many))
    none = load_scenario(tmp_path / "grid.sumocfg", inject=InjectConfig(0, 0))
    with pytest.raises(CrchflError, match=r"names 0 .* scenario.toml beside grid.sumocfg"):
        assign_vehicles(none, shard_plan(from_mapping(DatasetConfig, {"towns": [{"town": "grid", "train_samples": [5]}]})))


@pytest.mark.slow
def test_dataset_of_a_plain_multi_lane_sumocfg_needs_no_hand_written_file(tmp_path):
    import subprocess

    from crchfl_sumo.cli import main
    from crchfl_sumo.sumo.installation import sumo_binary

    subprocess.run([sumo_binary("netgenerate"), "--grid", "--grid.number=3", "--grid.length=200",
                    "--default.lanenumber=2", "--default-junction-type=traffic_light", "--no-turnarounds=true",
                    "-o", str(tmp_path / "city.net.xml")], check=True, capture_output=True)
    (tmp_path / "city.sumocfg").write_text('<configuration><input><net-file value="city.net.xml"/></input>'
                                          '<time><step-length value="0.25"/></time></configuration>')
    (tmp_path / "small.toml").write_text('[dataset]\nsample_period_s = 1.0\n[raster.camera]\nheight_px = 24\nwidth_px = 48\n')
    # the config names no towns: each added vehicle gets the default split's samples
    assert main(["dataset", str(tmp_path / "city.sumocfg"), "--out", str(tmp_path / "E"), "--config",
                 str(tmp_path / "small.toml")]) == 0
    manifest = read_manifest(tmp_path / "E")
    assert sorted(s.vehicle for s in manifest.shards) == [f"city_data_{i}" for i in range(5)] + ["city_test_0"]
    assert all(s.samples == (500 if s.split == "train" else 250) for s in manifest.shards)


def test_a_failed_first_run_leaves_no_manifest_that_blocks_a_mended_rerun(tmp_path, monkeypatch):
    from crchfl_sumo.data import generation

    scenario = paper_scenario()
    sizes = from_mapping(DatasetConfig, SIZES)
    odd_period = dataclasses.replace(sizes, sample_period_s=0.3)  # the paper scenario steps 0.25 s
    with pytest.raises(CrchflError, match="not a multiple of the scenario's step length 0.25 s"):
        generate_dataset(scenario, tmp_path / "odd", sizes=odd_period, raster=RASTER)
    assert not (tmp_path / "odd").exists()  # refused before the folder was made

    # A run that fails in the simulation, after its manifest and before any shard ...
    def vehicle_left(*args, **kwargs):
        raise CrchflError("vehicle 't01_data_0' left the network")

    monkeypatch.setattr(generation, "record_run", vehicle_left)
    with pytest.raises(CrchflError, match="left the network"):
        generate_dataset(scenario, tmp_path / "data", seed=3, sizes=sizes, raster=RASTER)
    assert read_manifest(tmp_path / "data").shards == ()
    monkeypatch.undo()
    # ... does not block a rerun with other settings in that folder.
    fewer = from_mapping(DatasetConfig, {"towns": [{"town": "town01", "train_samples": [3], "test_samples": [2]}]})
    manifest = generate_dataset(scenario, tmp_path / "data", seed=4, sizes=fewer, raster=RASTER)
    assert manifest.seed == 4 and [s.samples for s in manifest.shards] == [2, 3]
    # Once a shard is written, other settings are refused as before.
    with pytest.raises(CrchflError, match="other settings"):
        generate_dataset(scenario, tmp_path / "data", seed=5, sizes=fewer, raster=RASTER)


def test_nearest_site_takes_the_majority():
    sites = (EdgeSite("a", 0.0, 0.0), EdgeSite("b", 100.0, 0.0))
    assert nearest_site(sites, np.array([10.0, 90.0, 95.0]), np.zeros(3)) == "b"
    assert nearest_site((), np.zeros(1), np.zeros(1)) == ""


@pytest.mark.slow
def test_generate_then_resume_after_interruption_is_identical(tmp_path):
    scenario = paper_scenario()
    sizes = from_mapping(DatasetConfig, SIZES)
    stages: dict[str, float] = {}
    full = generate_dataset(scenario, tmp_path / "full", seed=3, sizes=sizes, raster=RASTER, timings_s=stages)
    assert set(stages) == {"simulate", "world", "label", "render", "write"}
    assert all(seconds > 0 for seconds in stages.values())
    assert [(s.vehicle, s.split, s.samples, s.edge) for s in full.shards] == [
        ("t01_test_0", "test", 4, "edge01"),
        ("t01_data_0", "train", 6, "edge01"),
        ("t01_data_1", "train", 5, "edge01"),
    ]
    data = read_shard(tmp_path / "full", full.entry("town01-train-0.h5"))
    assert np.allclose(np.diff(data.t_s), 0.25)
    assert data.images.shape == (6, 4, 24, 48, 3) and data.images.std() > 10  # not blank
    assert np.array_equal(data.steer_class, digitize_steer(data.actions[:, 1]))
    # Inserted at rest at 0.25 s, off a whole second: that standing step is not sampled (standing_sample_every
    # 4: 0, 1, 2 ... s), so the first sample already pulls away (it stands there with standing_sample_every 1).
    assert data.t_s[0] == 0.5 and data.actions[0, 0] == 1.0
    assert data.speed_mps.dtype == np.float32 and np.all(data.speed_mps > 0)
    assert data.command.dtype == np.int64 and set(data.command.tolist()) <= {0, 1, 2, 3}
    # Default recovery share 0.25 of the moving samples (all 6 here): round(1.5) = 2.
    perturbed = np.flatnonzero(np.any(data.perturbation != 0, axis=1))
    assert len(perturbed) == 2
    assert np.all(np.abs(data.perturbation[perturbed, 0]) <= 1.0) and np.all(np.abs(data.perturbation[perturbed, 1]) <= 15.0)
    assert full.labels["recovery"] == {"share": 0.25, "lateral_m": 1.0, "yaw_deg": 15.0, "queue_share": 0.0,
                                       "red_share": 0.5}
    assert full.labels["standing_sample_every"] == 4
    assert full.labels["command"]["lookahead_m"] == 25.0
    assert full.png_bytes_per_sample > 0

    def stop_after_first_shard(update):
        if update.stage == "write" and update.done >= 4:
            raise Stop

    with pytest.raises(Stop):
        generate_dataset(scenario, tmp_path / "cut", seed=3, sizes=sizes, raster=RASTER, progress=stop_after_first_shard)
    assert [s.file for s in read_manifest(tmp_path / "cut").shards] == ["town01-train-0.h5"]
    resumed = generate_dataset(scenario, tmp_path / "cut", seed=3, sizes=sizes, raster=RASTER)
    assert resumed == full
    for entry in full.shards:
        assert (tmp_path / "cut" / entry.file).read_bytes() == (tmp_path / "full" / entry.file).read_bytes()
    assert len(load_samples(tmp_path / "cut", split="train")) == 11
    with pytest.raises(CrchflError, match="other settings .*they differ in seed: "):
        generate_dataset(scenario, tmp_path / "cut", seed=4, sizes=sizes, raster=RASTER)


def test_generate_config_from_toml(tmp_path):
    from crchfl_sumo.data.generation import load_generate_config

    path = tmp_path / "gen.toml"
    path.write_text(
        "seed = 5\n[dataset]\ncompression = 'gzip'\n"
        "[[dataset.towns]]\ntown = 'town01'\ntrain_samples = [10]\n"
        "[raster.camera]\nheight_px = 32\nwidth_px = 64\n[expert]\nmax_steer_angle_deg = 35.0\n"
    )
    config = load_generate_config(path)
    assert config.seed == 5 and config.dataset.towns[0].train_samples == (10,)
    assert config.raster.camera.width_px == 64 and config.expert.max_steer_angle_deg == 35.0
    assert load_generate_config(path, seed=9).seed == 9
    path.write_text("[expert]\nlook_ahead = 3\n")
    with pytest.raises(CrchflError, match="expert.*look_ahead"):
        load_generate_config(path)


@pytest.mark.slow
def test_label_signs_follow_sumo_turns():
    from crchfl_sumo.data.expert import expert_labels, tracks_from_frames
    from crchfl_sumo.data.recording import record_run

    frames, _ = record_run(paper_scenario(), 1, {"t02_data_1": 240, "t01_data_0": 240}, 0.25)
    turns = {"left": 0, "right": 0}
    for vehicle in ("t02_data_1", "t01_data_0"):
        track = tracks_from_frames(frames)[vehicle]
        actions, classes = expert_labels(track)
        yaw_rate = np.gradient(np.unwrap(track.heading_rad), track.t_s)
        left, right = yaw_rate > 0.3, yaw_rate < -0.3
        # (At a turn's end the leading label is already back near 0, class 0.)
        assert np.all(actions[left, 1] < 0) and not np.isin(classes[left], [1, 2, 3]).any()
        assert np.all(actions[right, 1] > 0) and not np.isin(classes[right], [4, 5, 6]).any()
        turns["left"] += int(left.sum())
        turns["right"] += int(right.sum())
    assert turns["left"] > 3 and turns["right"] > 3


def test_neighbourhood_frames_render_what_full_frames_render():
    """record_run keeps only the sampled vehicles and their neighbourhood: their images must not change."""
    from crchfl_sumo.data.recording import record_run
    from crchfl_sumo.sumo.simulation import Simulation
    from crchfl_sumo.vision.raster import Renderer, neighbourhood_m
    from crchfl_sumo.vision.world import WorldConfig, build_world

    scenario = load_scenario("town01")
    raster = RasterConfig(camera=CameraConfig(height_px=32, width_px=64))
    needed = {"t01_data_0": 30, "t01_data_1": 30}
    frames, sampled = record_run(scenario, 5, needed, 1.0, around_m=neighbourhood_m(raster))
    with Simulation(scenario, seed=5) as sim:
        full = [sim.step() for _ in range(len(frames))]
    renderer = Renderer(build_world(scenario.net_path, WorldConfig()), raster)
    drawn_others = 0
    for vehicle, rows in sampled.items():
        assert len(rows) == 30
        for i in rows:
            assert full[i].t_s == frames[i].t_s and len(frames[i]) < len(full[i])
            np.testing.assert_array_equal(renderer.render(frames[i], [vehicle]), renderer.render(full[i], [vehicle]))
            alone = frames[i].select(frames[i].ids == vehicle)
            drawn_others += int(not np.array_equal(renderer.render(alone, [vehicle]), renderer.render(frames[i], [vehicle])))
    assert drawn_others >= 3  # some images did show other vehicles (5 of 60 with this seed)


def test_sample_labels_perturb_only_moving_samples_and_relabel_their_steer():
    from crchfl_sumo.data.route_commands import CommandConfig
    from crchfl_sumo.data.expert import ExpertConfig, Track
    from crchfl_sumo.data.generation import sample_labels
    from crchfl_sumo.data.labels import FOLLOW, LEFT
    from crchfl_sumo.sumo.turns import Junction

    # East along y = 0 at 5 m/s for 40 steps, after standing 10 steps; a junction square at x = 100.
    n = 60
    speed = np.where(np.arange(n) < 10, 0.0, 5.0)
    x = np.concatenate([[0.0], np.cumsum(speed[1:] * 0.25)]) + 70.0
    track = Track("v", np.arange(n) * 0.25, x, np.zeros(n), np.zeros(n), speed, np.zeros(n),
                  np.full(n, 2.6), np.full(n, 4.5))
    square = Junction("J", np.array([[100.0, -6.0], [112.0, -6.0], [112.0, 6.0], [100.0, 6.0]]))
    rows = np.arange(0, 40, 2)
    sizes = DatasetConfig(recovery_share=1.0, recovery_queue_share=1.0)

    labels = sample_labels(track, rows, [square], sizes, ExpertConfig(), CommandConfig(), np.random.default_rng(1))
    standing = speed[rows] == 0
    assert not labels.perturbation[standing].any() and np.all(labels.perturbation[~standing, :2] != 0)
    assert not labels.perturbation[:, 2].any()  # no leader: no queue sample
    # Each perturbed label steers towards the unperturbed target (x + L, 0) on the straight track: right (> 0)
    # when the target lies to the right of the perturbed heading (alpha < 0), left otherwise.
    lateral, yaw = labels.perturbation[:, 0], np.radians(labels.perturbation[:, 1])
    lookahead = np.maximum(5.0, 0.8 * speed[rows])
    alpha = np.arctan2(-lateral, lookahead) - yaw  # straight road: target (L, 0) seen from (0, lateral)
    assert np.all(np.sign(labels.actions[~standing, 1]) == -np.sign(alpha[~standing]))
    assert np.array_equal(labels.steer_class, digitize_steer(labels.actions[:, 1]))
    assert labels.speed_mps.dtype == np.float32 and labels.speed_mps.tolist() == speed[rows].tolist()
    # Target speed: the speed 1 s (4 steps) later, perturbed or not: 0 for rows 0 to 4, 5 m/s once the
    # pull-away at step 10 lies within the 1 s.
    assert labels.target_speed_mps.tolist() == speed[np.minimum(rows + 4, n - 1)].tolist()
    assert labels.target_speed_mps[rows == 4] == 0 and labels.target_speed_mps[rows == 6] == 5.0
    # The path runs straight through the square: STRAIGHT from 25 m before x = 100, FOLLOW before.
    assert labels.command[x[rows] < 100.0 - 25.5].tolist() == [FOLLOW] * int(np.sum(x[rows] < 74.5))
    assert set(labels.command[x[rows] > 75.5].tolist()) == {3}
    assert LEFT not in labels.command
    again = sample_labels(track, rows, [square], sizes, ExpertConfig(), CommandConfig(), np.random.default_rng(1))
    assert np.array_equal(again.perturbation, labels.perturbation)

    # A standing leader 2.5 m ahead of every sample: the standing samples become queue samples, moved
    # 0.5 to 2 m from it, labelled to stay (target speed 0, the standing pedals); the moving ones do not.
    queued = sample_labels(track, rows, [square], sizes, ExpertConfig(), CommandConfig(), np.random.default_rng(1),
                           gap_m=np.full(len(rows), 2.5))
    forward = queued.perturbation[:, 2]
    assert np.all((forward[standing] >= 0.5) & (forward[standing] <= 2.0)) and not forward[~standing].any()
    assert not queued.target_speed_mps[standing].any()
    assert queued.target_speed_mps[~standing].tolist() == labels.target_speed_mps[~standing].tolist()
    assert np.array_equal(queued.actions, labels.actions)  # standing: throttle 0, steer 0, the hold brake
    assert np.array_equal(queued.perturbation[:, :2], labels.perturbation[:, :2])  # drawn first, unchanged

    # A red line 1 m ahead of every sample: with red-line samples, the standing ones move 1 to 6 m back from it,
    # labelled to stay; the moving ones keep their labels; with queue samples too, a queue sample stays one.
    red = dataclasses.replace(sizes, recovery_queue_share=0.0, recovery_red_share=1.0)
    backed = sample_labels(track, rows, [square], red, ExpertConfig(), CommandConfig(), np.random.default_rng(1),
                           red_line_m=np.full(len(rows), 1.0))
    back = backed.perturbation[:, 2]
    assert np.all((back[standing] >= -6.0) & (back[standing] <= -1.0)) and not back[~standing].any()
    assert not backed.target_speed_mps[standing].any()
    assert backed.target_speed_mps[~standing].tolist() == labels.target_speed_mps[~standing].tolist()
    both = sample_labels(track, rows, [square], dataclasses.replace(red, recovery_queue_share=1.0), ExpertConfig(),
                         CommandConfig(), np.random.default_rng(1), gap_m=np.full(len(rows), 2.5),
                         red_line_m=np.full(len(rows), 1.0))
    assert np.array_equal(both.perturbation, queued.perturbation)


def test_a_frames_samples_rendered_together_are_those_rendered_one_by_one():
    """render_samples draws a frame's samples in one call; each image must equal that of the sample alone,
    drawn from a frame in which only its own vehicle's pose is perturbed."""
    from crchfl_sumo.data.recording import record_run
    from crchfl_sumo.data.recovery import camera_pose
    from crchfl_sumo.data.rendering import RenderJob, render_samples
    from crchfl_sumo.vision.raster import Renderer, neighbourhood_m
    from crchfl_sumo.vision.world import WorldConfig, build_world

    scenario = load_scenario("town01")
    raster = RasterConfig(camera=CameraConfig(height_px=32, width_px=64))
    needed = {"t01_data_0": 12, "t01_data_1": 12, "t01_test_0": 12}
    frames, sampled = record_run(scenario, 5, needed, 1.0, around_m=neighbourhood_m(raster))
    rng = np.random.default_rng(0)
    jobs = []
    for vehicle, rows in sampled.items():
        perturbation = rng.uniform([-1.0, -15.0, 0.0], [1.0, 15.0, 2.0], (len(rows), 3)).astype(np.float32)
        perturbation[::3] = 0.0  # every third sample on the track
        jobs.append(RenderJob(vehicle, rows, perturbation))
    shared = {int(i) for i in sampled["t01_data_0"]} & {int(i) for i in sampled["t01_data_1"]}
    assert len(shared) >= 5  # the vehicles are sampled at the same frames: the calls hold several samples

    renderer = Renderer(build_world(scenario.net_path, WorldConfig()), raster)
    together = render_samples(renderer, frames, jobs)
    one_by_one = render_samples(renderer, frames, jobs, vehicles_per_call=1)
    for job, images, alone in zip(jobs, together, one_by_one):
        np.testing.assert_array_equal(images, alone)
        for k, i in enumerate(job.frame_rows[:6]):
            frame = frames[i]
            row = frame.index_of(job.vehicle)
            x, y, heading = (getattr(frame, c).copy() for c in ("x_m", "y_m", "heading_rad"))
            x[row], y[row], heading[row] = camera_pose(frame, job.vehicle, *job.perturbation[k])
            moved = dataclasses.replace(frame, x_m=x, y_m=y, heading_rad=heading)
            np.testing.assert_array_equal(images[k], renderer.render(moved, [job.vehicle])[0])


def test_render_groups_hold_the_shards_whose_images_fit_the_budget():
    from crchfl_sumo.data.settings import PlannedShard
    from crchfl_sumo.data.rendering import render_groups

    shards = [PlannedShard(f"s{i}.h5", "town01", "train", i, n) for i, n in enumerate([3, 4, 2, 9, 1])]
    # 10 bytes a sample, 60 bytes a group: 3+4 = 7 samples would be 70 bytes.
    groups = [[s.samples for s in group] for group in render_groups(shards, (2, 5), budget_bytes=60)]
    assert groups == [[3], [4, 2], [9], [1]]  # a shard over the budget still forms its own group


def test_a_data_set_writes_sumos_own_fcd_of_its_run(grid_dir, tmp_path):
    import sumolib

    from crchfl_sumo.cli import main

    (tmp_path / "small.toml").write_text(
        '[dataset]\nsample_period_s = 1.0\ntowns = [{town = "grid", train_samples = [2, 2, 2, 2, 2], '
        'test_samples = [2]}]\n[raster.camera]\nheight_px = 24\nwidth_px = 48\n')
    out = tmp_path / "D"
    assert main(["dataset", str(grid_dir / "grid.sumocfg"), "--out", str(out), "--config", str(tmp_path / "small.toml"),
                 "--sumo-output", "fcd"]) == 0
    fcd = {v.id for v in sumolib.xml.parse_fast(str(out / "sumo-fcd.xml"), "vehicle", ["id"])}
    assert {s.vehicle for s in read_manifest(out).shards} <= fcd  # every data and test vehicle of the run
