import json

import h5py
import numpy as np
import pytest
import torch

from crchfl_sumo.core.atomic import TMP_MARK
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.dataset import ShardDataset, load_samples, load_vehicle_samples, measured_sample_bytes
from crchfl_sumo.data.settings import DatasetConfig, shard_plan
from crchfl_sumo.data.labels import digitize_steer
from crchfl_sumo.data.manifest import (
    MANIFEST_NAME,
    NOMINAL_SAMPLE_BYTES,
    Manifest,
    label_schema,
    read_manifest,
)
from crchfl_sumo.data.shards import (
    DatasetWriter,
    ShardData,
    png_bytes_per_sample,
    read_shard,
    sha256_file,
    write_shard,
)

H, W = 12, 16


def fake_shard(n, seed):
    rng = np.random.default_rng(seed)
    images = np.zeros((n, 4, H, W, 3), np.uint8)
    images[:, :, H // 2 :] = rng.integers(0, 255, size=(n, 4, H - H // 2, W, 3), dtype=np.uint8)
    actions = np.stack([rng.random(n), rng.uniform(-1, 1, n), rng.random(n)], axis=1).astype(np.float32)
    t_s = np.arange(n) * 0.25
    return ShardData(
        images=images,
        actions=actions,
        steer_class=digitize_steer(actions[:, 1]),
        command=rng.integers(0, 4, size=n),
        speed_mps=np.where(rng.random(n) < 0.3, 0.0, 8.0).astype(np.float32),
        target_speed_mps=rng.uniform(0, 14, n).astype(np.float32),
        perturbation=np.stack([rng.uniform(-1, 1, n), rng.uniform(-15, 15, n), rng.uniform(0, 2, n)], axis=1)
        .astype(np.float32)
        * (rng.random(n) < 0.5)[:, None],
        t_s=t_s,
        x_m=t_s * 8.0,
        y_m=np.zeros(n),
        heading_rad=np.zeros(n),
    )


def header(seed=7, **changes):
    fields = dict(scenario="paper", seed=seed, sample_period_s=0.25, image_height=H, image_width=W)
    fields["camera"] = {"width_px": W, "height_px": H, "fov_deg": 120.0, "poses": [[1.5, 0.0, 1.5]]}
    fields.update(changes)
    return Manifest(**fields)



def small_config():
    return from_mapping(
        DatasetConfig,
        {"towns": [{"town": "Town01", "train_samples": [5, 4], "test_samples": [3]},
                   {"town": "Town02", "train_samples": [6]}]},
    )


class Interrupted(Exception):
    pass


def generate(root, config, seed, fail_after=None):
    """A stand-in for the generation pipeline: deterministic shards from the seed, resumable."""
    writer = DatasetWriter(root, header(seed))
    written = []
    for k, planned in enumerate(shard_plan(config)):
        if writer.is_done(planned.file):
            continue
        if fail_after is not None and len(written) == fail_after:
            raise Interrupted
        data = fake_shard(planned.samples, seed * 100 + k)
        writer.add(planned.file, data, vehicle=f"veh{k}", town=planned.town, edge=f"edge-{planned.town}",
                   split=planned.split)
        written.append(planned.file)
    return written


def test_paper_split_is_the_default():
    plan = shard_plan(DatasetConfig())
    train = [(p.town, p.samples) for p in plan if p.split == "train"]
    test = [(p.town, p.samples) for p in plan if p.split == "test"]
    assert train == [("town01", 2928), ("town01", 2928), ("town02", 2586), ("town02", 2587), ("town02", 1555)]
    assert test == [("town01", 1061), ("town02", 1020)]
    assert len({p.file for p in plan}) == len(plan)
    assert DatasetConfig().sample_period_s == 0.25


def test_config_rejects_bad_values():
    with pytest.raises(CrchflError, match="train_samples"):
        from_mapping(DatasetConfig, {"towns": [{"town": "Town01", "train_samples": [0]}]})
    with pytest.raises(CrchflError, match="compression"):
        from_mapping(DatasetConfig, {"compression": "zstd"})
    with pytest.raises(CrchflError, match="once"):
        from_mapping(DatasetConfig, {"towns": [{"town": "A", "train_samples": [1]}] * 2})


def test_shard_round_trip_readable_with_plain_h5py(tmp_path):
    data = fake_shard(6, 1)
    entry = write_shard(tmp_path / "a.h5", data, vehicle="v1", town="Town01", edge="e1", split="train")
    assert entry.samples == 6 and entry.sha256 == sha256_file(tmp_path / "a.h5")
    back = read_shard(tmp_path, entry)
    for name in ("images", "actions", "steer_class", "command", "speed_mps", "perturbation", "t_s", "x_m", "y_m"):
        np.testing.assert_array_equal(getattr(back, name), getattr(data, name))
    with h5py.File(tmp_path / "a.h5", "r") as f:
        assert f["images"].shape == (6, 4, H, W, 3) and f["images"].chunks == (1, 4, H, W, 3)
        assert f["actions"].dtype == np.float32 and f["steer_class"].dtype == np.int64
        assert f["command"].dtype == np.int64 and f["speed_mps"].dtype == np.float32
        assert f["perturbation"].dtype == np.float32 and f["perturbation"].shape == (6, 3)
        assert (f.attrs["vehicle"], f.attrs["town"], f.attrs["edge"], f.attrs["split"]) == ("v1", "Town01", "e1", "train")
    assert not list(tmp_path.glob(".*"))  # no temporary left behind


def test_same_samples_give_identical_bytes(tmp_path):
    data = fake_shard(4, 2)
    a = write_shard(tmp_path / "a.h5", data, vehicle="v", town="t", edge="e", split="test")
    b = write_shard(tmp_path / "b.h5", data, vehicle="v", town="t", edge="e", split="test")
    assert a.sha256 == b.sha256


def test_manifest_round_trip(tmp_path):
    generate(tmp_path, small_config(), seed=3)
    manifest = read_manifest(tmp_path)
    raw = json.loads((tmp_path / MANIFEST_NAME).read_text())
    assert raw["scenario"] == "paper" and raw["seed"] == 3 and raw["camera"]["fov_deg"] == 120.0
    assert raw["labels"]["steer_class_values"] == pytest.approx([0, 0.125, 0.275, 0.425, -0.125, -0.275, -0.425])
    # Sorted by file name: Town01-test-0, Town01-train-0, Town01-train-1, Town02-train-0.
    assert [s["samples"] for s in raw["shards"]] == [3, 5, 4, 6]
    assert {"vehicle", "town", "edge", "split", "samples", "sha256", "file"} <= set(raw["shards"][0])
    assert raw["samples"] == 18 and raw["nominal_bytes_per_sample"] == NOMINAL_SAMPLE_BYTES
    assert Manifest.from_json(manifest.to_json(), "x") == manifest
    assert [s.vehicle for s in manifest.select("train")] == ["veh0", "veh1", "veh3"]
    for entry in manifest.shards:
        assert sha256_file(tmp_path / entry.file) == entry.sha256


def test_corrupt_shard_is_refused(tmp_path):
    generate(tmp_path, small_config(), seed=3)
    entry = read_manifest(tmp_path).entry("Town01-train-1.h5")
    path = tmp_path / entry.file
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(CrchflError, match=f"{entry.file}.*corrupt.*rerun"):
        load_samples(tmp_path)
    with pytest.raises(CrchflError, match="corrupt"):
        ShardDataset(tmp_path)
    load_samples(tmp_path, vehicles=["veh0"])  # the intact shards still load


def test_truncated_or_missing_shard_is_refused(tmp_path):
    generate(tmp_path, small_config(), seed=3)
    path = tmp_path / "Town01-train-0.h5"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(CrchflError, match="Town01-train-0.h5.*truncated"):
        load_samples(tmp_path, split="train")
    (tmp_path / "Town01-test-0.h5").unlink()
    with pytest.raises(CrchflError, match="missing"):
        load_samples(tmp_path, split="test")


def test_resume_after_interruption_gives_identical_shards(tmp_path):
    config = small_config()
    full = generate(tmp_path / "full", config, seed=5)
    with pytest.raises(Interrupted):
        generate(tmp_path / "cut", config, seed=5, fail_after=2)
    (tmp_path / "cut" / f".Town02-train-0.h5{TMP_MARK}999.h5").write_bytes(b"half a file")  # a crash's leftover
    first = read_manifest(tmp_path / "cut").shards
    assert len(first) == 2
    kept_mtime = (tmp_path / "cut" / first[0].file).stat().st_mtime_ns
    rest = generate(tmp_path / "cut", config, seed=5)
    assert rest == full[2:]  # finished shards are not redone
    assert (tmp_path / "cut" / first[0].file).stat().st_mtime_ns == kept_mtime
    assert read_manifest(tmp_path / "cut") == read_manifest(tmp_path / "full")
    for entry in read_manifest(tmp_path / "full").shards:
        assert (tmp_path / "cut" / entry.file).read_bytes() == (tmp_path / "full" / entry.file).read_bytes()
    assert not list((tmp_path / "cut").glob(".*"))
    assert generate(tmp_path / "cut", config, seed=5) == []  # a complete folder: nothing to do


def test_resume_regenerates_a_damaged_shard(tmp_path):
    config = small_config()
    generate(tmp_path, config, seed=5)
    before = read_manifest(tmp_path)
    (tmp_path / before.shards[0].file).write_bytes(b"garbage")
    assert generate(tmp_path, config, seed=5) == [before.shards[0].file]
    assert read_manifest(tmp_path) == before


def test_other_settings_cannot_share_a_folder(tmp_path):
    generate(tmp_path, small_config(), seed=5)
    with pytest.raises(CrchflError, match="other settings"):
        generate(tmp_path, small_config(), seed=6)
    with pytest.raises(CrchflError, match="no data set manifest"):
        read_manifest(tmp_path / "nowhere")


def test_fast_path_and_torch_dataset_agree(tmp_path):
    generate(tmp_path, small_config(), seed=9)
    samples = load_samples(tmp_path, split="train")
    assert len(samples) == 15 and samples.images.dtype == torch.uint8
    assert samples.images.shape[1:] == (4, H, W, 3)
    dataset = ShardDataset(tmp_path, split="train")
    assert len(dataset) == 15
    for i in (0, 4, 5, 8, 9, 14, -1):
        images, actions, steer_class, command, speed_mps, target_speed_mps = dataset[i]
        assert torch.equal(images, samples.images[i])
        assert torch.equal(actions, samples.actions[i])
        assert int(steer_class) == int(samples.steer_class[i])
        assert int(command) == int(samples.command[i]) and float(speed_mps) == float(samples.speed_mps[i])
        assert float(target_speed_mps) == float(samples.target_speed_mps[i])
    with pytest.raises(IndexError):
        dataset[15]
    batch = next(iter(torch.utils.data.DataLoader(dataset, batch_size=6)))
    assert batch[0].shape == (6, 4, H, W, 3) and batch[2].dtype == torch.int64
    dataset.close()
    per_vehicle = load_vehicle_samples(tmp_path, "train")
    assert {k: len(v) for k, v in per_vehicle.items()} == {"veh0": 5, "veh1": 4, "veh3": 6}
    assert torch.equal(per_vehicle["veh3"].actions, samples.actions[9:])
    assert torch.equal(per_vehicle["veh3"].command, samples.command[9:])
    with pytest.raises(CrchflError, match="vehicle"):
        load_samples(tmp_path, vehicles=["nobody"])


def test_measured_sample_bytes_is_the_mean_png_size(tmp_path):
    generate(tmp_path, small_config(), seed=2)
    manifest = read_manifest(tmp_path)
    measured = measured_sample_bytes(manifest)
    expected = np.mean(np.concatenate(
        [[png_bytes_per_sample(read_shard(tmp_path, s).images[i : i + 1]) for i in range(s.samples)]
         for s in manifest.shards]))
    assert measured == pytest.approx(expected, abs=1)
    assert 4 * 67 < measured < 4 * (H * W * 3 + 200)  # four PNGs: headers plus some of the raw pixels
    assert NOMINAL_SAMPLE_BYTES == 1800 * 1024
    with pytest.raises(CrchflError, match="measured"):
        measured_sample_bytes(header())


def test_dataset_stats_counts_and_files(tmp_path):
    import cv2

    from crchfl_sumo.data.stats import PEDAL_BINS, pick_examples, write_dataset_stats

    generate(tmp_path / "data", small_config(), seed=4)
    stats = write_dataset_stats(tmp_path / "data", tmp_path / "out")
    train = load_samples(tmp_path / "data", split="train")
    assert stats["samples"] == 18 and stats["train"]["samples"] == 15 and stats["test"]["samples"] == 3
    assert stats["train"]["steer_class_counts"] == np.bincount(train.steer_class.numpy(), minlength=7).tolist()
    assert stats["train"]["throttle_hist"] == np.histogram(train.actions[:, 0].numpy(), PEDAL_BINS)[0].tolist()
    assert sum(stats["all"]["brake_hist"]) == 18
    assert stats["train"]["command_counts"] == np.bincount(train.command.numpy(), minlength=6).tolist()
    assert stats["train"]["standing_share"] == pytest.approx(float((train.speed_mps < 0.1).float().mean()), abs=1e-4)
    assert stats["train"]["speed_mean"] == pytest.approx(float(train.speed_mps.mean()), abs=1e-4)
    perturbed = [np.any(read_shard(tmp_path / "data", e).perturbation != 0, axis=1) for e in read_manifest(tmp_path / "data").shards]
    assert stats["all"]["recovery_share"] == pytest.approx(float(np.concatenate(perturbed).mean()), abs=1e-4)
    assert 0 < stats["all"]["recovery_share"] < 1 and 0 < stats["train"]["standing_share"] < 1
    assert [r["samples"] for r in stats["per_vehicle"]] == [3, 5, 4, 6]
    assert json.loads((tmp_path / "out" / "dataset_stats.json").read_text())["samples"] == 18
    mosaic = cv2.imread(stats["files"]["mosaic"])
    examples = pick_examples(tmp_path / "data")
    classes_present = np.unique(train.steer_class.numpy())
    assert len(examples) == len(classes_present)
    scale = int(np.ceil(200 / W))
    assert mosaic.shape == (len(examples) * (22 + H * scale), 4 * W * scale, 3)
    assert cv2.imread(stats["files"]["figure"]) is not None


def test_torch_dataset_survives_pickling_for_workers(tmp_path):
    import pickle

    generate(tmp_path, small_config(), seed=9)
    dataset = ShardDataset(tmp_path, split="test")
    first = dataset[0]  # opens a file handle
    clone = pickle.loads(pickle.dumps(dataset))  # what a DataLoader worker receives
    assert torch.equal(clone[0][0], first[0]) and len(clone) == 3
    dataset.close()
    clone.close()


def test_malformed_manifest_is_refused(tmp_path):
    (tmp_path / MANIFEST_NAME).write_text("{not json")
    with pytest.raises(CrchflError, match="not valid JSON"):
        read_manifest(tmp_path)
    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(CrchflError, match="not a crchfl-sumo data set"):
        read_manifest(tmp_path)
    with pytest.raises(CrchflError, match="other settings|not a crchfl-sumo"):
        DatasetWriter(tmp_path, header())


def test_shard_without_the_new_datasets_is_refused(tmp_path):
    entry = write_shard(tmp_path / "old.h5", fake_shard(3, 1), vehicle="v", town="t", edge="e", split="train")
    with h5py.File(tmp_path / "old.h5", "a") as f:  # what a version-1 shard lacks
        del f["command"], f["speed_mps"]
    with pytest.raises(CrchflError, match=r"old\.h5.*command, speed_mps.*regenerate the data set"):
        read_shard(tmp_path, entry, verify=False)


def test_version_1_manifest_is_refused_for_reading_and_resuming(tmp_path):
    generate(tmp_path, small_config(), seed=3)
    raw = json.loads((tmp_path / MANIFEST_NAME).read_text())
    raw["version"] = 1
    (tmp_path / MANIFEST_NAME).write_text(json.dumps(raw))
    with pytest.raises(CrchflError, match="version 1.*regenerate the data set"):
        load_samples(tmp_path)
    with pytest.raises(CrchflError, match="version 1"):
        DatasetWriter(tmp_path, header(3))


def test_a_manifest_refuses_a_model_of_another_target_speed_horizon():
    manifest = Manifest("paper", 0, 0.25, 48, 64, labels={**label_schema(), "expert": {"speed_horizon_s": 2.0}})
    assert manifest.speed_horizon_s == 2.0
    manifest.check_horizon(2.0, "DIR")
    with pytest.raises(CrchflError, match="set model.speed_horizon_s = 2.0"):
        manifest.check_horizon(1.0, "DIR")
    assert Manifest("paper", 0, 0.25, 48, 64).speed_horizon_s == 1.0  # the expert's default


def test_label_summary_tells_queue_samples_from_red_line_samples():
    from crchfl_sumo.data.stats import _label_summary

    n = 4
    perturbation = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0, 1.5], [0, 0, -3.0]], dtype=np.float32)  # on track, lateral, queue, red line
    summary = _label_summary(np.zeros((n, 3)), np.zeros(n), np.zeros(n), np.zeros(n), perturbation, 0.1)
    assert (summary["recovery_share"], summary["queue_share"], summary["red_line_share"]) == (0.25, 0.25, 0.25)


def test_junction_commands_count_turn_samples_at_the_nearest_junction_and_name_the_missing():
    from crchfl_sumo.core.resources import scenarios_dir
    from crchfl_sumo.data.labels import FOLLOW, LEFT, STRAIGHT
    from crchfl_sumo.data.stats import junction_commands
    from crchfl_sumo.sumo.route import read_net

    net = read_net(scenarios_dir() / "town02" / "town02.net.xml")
    # Town02: eight T-junctions (A to H), each offering left, right and straight; its four corners offer none
    empty = junction_commands(net, np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    assert empty["offered"] == 24 and len(empty["missing"]) == 24
    assert sorted(empty["junctions"]) == list("ABCDEFGH")
    gx, gy = net.getNode("G").getCoord()
    x = np.array([gx, gx + 10.0, gx, 0.0])
    y = np.array([gy, gy, gy - 10.0, 0.0])  # three samples at G, one at the corner SW (0, 0)
    got = junction_commands(net, x, y, np.array([STRAIGHT, STRAIGHT, LEFT, FOLLOW]))
    assert got["junctions"]["G"] == {"left": 1, "right": 0, "straight": 2, "offered": ["left", "right", "straight"]}
    assert "G right" in got["missing"] and "G straight" not in got["missing"] and "G left" not in got["missing"]
    assert len(got["missing"]) == 22
