"""The shard schema and the manifest checks: what a data set file may hold, refused before use with the file named."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.dataset import ShardDataset, load_samples, load_vehicle_samples
from crchfl_sumo.data.manifest import (
    MANIFEST_NAME,
    Manifest,
    read_manifest,
)
from crchfl_sumo.data.shards import (
    MAX_COMPRESSION_RATIO,
    DatasetWriter,
    ShardData,
    check_label_values,
    read_shard,
    sha256_file,
)
from crchfl_sumo.data.stats import dataset_stats, write_mosaic

H, W = 48, 64


def shard_data(n: int) -> ShardData:
    """n valid samples: steer class k of sample k, every command, pedals in [0, 1]."""
    zeros = np.zeros(n)
    return ShardData(
        np.full((n, 4, H, W, 3), 100, np.uint8),
        np.tile(np.array([[0.5, -0.25, 0.0]], np.float32), (n, 1)),
        np.arange(n) % 7,
        np.arange(n) % 4,
        np.full(n, 5.0, np.float32),
        np.full(n, 6.0, np.float32),
        np.zeros((n, 3), np.float32),
        np.arange(n) * 0.25,
        zeros,
        zeros,
        zeros,
    )


def make_dataset(root: Path, n: int = 3) -> Path:
    header = Manifest(scenario="paper", seed=0, sample_period_s=0.25, image_height=H, image_width=W, compression="none")
    writer = DatasetWriter(root, header)
    writer.add("a.h5", shard_data(n), vehicle="v0", town="town01", edge="e0", split="train")
    writer.add("b.h5", shard_data(2), vehicle="v1", town="town01", edge="e0", split="test")
    return root


def reseal(root: Path, shard: str = "a.h5", **changes) -> None:
    """Make the manifest entry of ``shard`` match the file on disk again (size, sha256), plus ``changes``:
    a shard whose checksum matches but whose content is wrong."""
    raw = json.loads((root / MANIFEST_NAME).read_text())
    for entry in raw["shards"]:
        if entry["file"] == shard:
            entry.update({"size_bytes": (root / shard).stat().st_size, "sha256": sha256_file(root / shard), **changes})
    (root / MANIFEST_NAME).write_text(json.dumps(raw))


def replace_dataset(root: Path, name: str, values, file: str = "a.h5") -> None:
    with h5py.File(root / file, "a") as f:
        del f[name]
        if values is not None:
            f.create_dataset(name, data=values)
    reseal(root, file)


@pytest.fixture
def data(tmp_path) -> Path:
    return make_dataset(tmp_path / "data")


def test_a_valid_data_set_loads(data):
    samples = load_samples(data)
    assert len(samples) == 5 and samples.image_hw == (H, W)
    assert dataset_stats(data)["train"]["steer_class_counts"] == [1, 1, 1, 0, 0, 0, 0]


@pytest.mark.parametrize(
    ("name", "values", "message"),
    [
        ("steer_class", np.array([0, 99, 2]), "steer_class holds 99; steer classes are 0..6"),
        ("steer_class", np.array([0, -1, 2]), "steer_class holds -1; steer classes are 0..6"),
        ("command", np.array([0, 1, 6]), "command holds 6; commands are 0..5"),
        ("actions", np.array([[0.5, 0, 0], [1.5, 0, 0], [0, 0, 0]], np.float32), "throttle holds 1.5; throttle lies in"),
        ("actions", np.array([[0.5, -2, 0], [0, 0, 0], [0, 0, 0]], np.float32), r"steer holds -2.0; steer lies in \[-1, 1\]"),
        ("actions", np.array([[0.5, 0, np.nan], [0, 0, 0], [0, 0, 0]], np.float32), "actions holds nan; labels must be finite"),
        ("speed_mps", np.array([1, np.inf, 0], np.float32), "speed_mps holds inf"),
        ("target_speed_mps", np.array([1, -3, 0], np.float32), "target_speed_mps holds -3.0; speeds are >= 0"),
        ("t_s", np.array([0, np.nan, 1]), "t_s holds nan"),
        ("steer_class", np.array([0, 1, 2], np.int32), r"steer_class is int32 \[3\], the format has int64 \[3\]"),
        ("actions", np.zeros((3, 2), np.float32), r"actions is float32 \[3, 2\], the format has float32 \[3, 3\]"),
        ("command", np.zeros(4, np.int64), r"command is int64 \[4\], the format has int64 \[3\]"),
        ("images", np.zeros((3, 4, H, W, 3), np.float32), "images is float32"),
        ("images", np.zeros((3, 4, 40, W, 3), np.uint8), r"images is uint8 \[3, 4, 40, 64, 3\], the format has uint8 \[3, 4, 48, 64, 3\]"),
        ("images", None, "shard has no images"),
        ("perturbation", None, "shard has no perturbation"),
    ],
)
def test_a_shard_whose_checksum_matches_but_content_is_wrong_is_refused(data, name, values, message):
    replace_dataset(data, name, values)
    for read in (load_samples, dataset_stats, load_vehicle_samples, ShardDataset):
        with pytest.raises(CrchflError, match=rf"a\.h5: {message}.*regenerate") as caught:
            read(data)
        assert "\n" not in str(caught.value)


def test_the_label_check_names_the_first_bad_value():
    labels = {"actions": np.array([[0.0, 0.0, 0.0]], np.float32), "steer_class": np.array([7]), "command": np.array([0]),
              "speed_mps": np.array([0.0], np.float32), "target_speed_mps": np.array([0.0], np.float32)}
    with pytest.raises(CrchflError, match="^x.h5: steer_class holds 7; steer classes are 0..6; FIX$"):
        check_label_values(labels, "x.h5", "FIX")
    check_label_values({**labels, "steer_class": np.array([6])}, "x.h5", "FIX")  # the edge class is valid


def test_a_declared_shape_larger_than_the_file_can_hold_is_refused_before_reading(data):
    # 10**6 samples of 48 x 64 x 4 x 3 bytes: 36.9 GB declared, in a file of a few KB (gzip'd zeros)
    n = 10**6
    with h5py.File(data / "a.h5", "w") as f:
        f.create_dataset("images", shape=(n, 4, H, W, 3), dtype=np.uint8, chunks=(1, 4, H, W, 3), compression="gzip")
        for name, column in dataclasses.asdict(shard_data(1)).items():
            if name != "images":
                f.create_dataset(name, shape=(n, *column.shape[1:]), dtype=column.dtype)
    reseal(data, samples=n)
    size = (data / "a.h5").stat().st_size
    assert n * 4 * H * W * 3 > size * MAX_COMPRESSION_RATIO  # what the check compares
    with pytest.raises(CrchflError, match=rf"a\.h5: .* declares \d+ bytes, more than a {size}-byte file can hold"):
        load_samples(data)


def test_a_manifest_entry_outside_the_folder_is_refused(data, tmp_path):
    outside = tmp_path / "outside.h5"
    outside.write_bytes((data / "a.h5").read_bytes())  # size and sha256 match the entry
    raw = json.loads((data / MANIFEST_NAME).read_text())
    raw["shards"][0]["file"] = "../outside.h5"
    (data / MANIFEST_NAME).write_text(json.dumps(raw))
    with pytest.raises(CrchflError, match=r"manifest.json: shard file '\.\./outside\.h5' is not a plain '<name>\.h5'"):
        load_samples(data)
    # a link out of the folder under a plain name
    raw["shards"][0]["file"] = "a.h5"
    (data / MANIFEST_NAME).write_text(json.dumps(raw))
    (data / "a.h5").unlink()
    (data / "a.h5").symlink_to(outside)
    with pytest.raises(CrchflError, match="lies outside the data set folder"):
        load_samples(data)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (b'{"format": "crchfl-sumo-dataset", "scenario": "\xff\xfe"}', r"not UTF-8 text \(byte 47\)"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"format": "crchfl-sumo-dataset", "version": 4, "scenario": "x"}', "malformed manifest"),
    ],
)
def test_an_unreadable_manifest_is_refused(tmp_path, text, message):
    (tmp_path / MANIFEST_NAME).write_bytes(text)
    with pytest.raises(CrchflError, match=rf"manifest\.json: {message}"):
        read_manifest(tmp_path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"image_height": 4096, "image_width": 8192}, "image size 4096 x 8192 lies outside 8 x 8 .. 1080 x 1920"),
        ({"image_height": "48"}, "image_height: expected an integer"),
        ({"seed": None}, "seed: expected an integer"),
        ({"camera": [1, 2]}, "camera must be a table"),
        ({"camera": {"raster": {"camera": {"height_px": 4096, "width_px": 8192}}}}, "4096x8192 is too large"),
        ({"camera": {"raster": 3}}, r"manifest\.json: camera\.raster: expected a table"),
        ({"shards": "a.h5"}, "shards: expected a list"),
        ({"shards": [{"file": "a.h5"}]}, "shards"),
        ({"sample_period_s": float("nan")}, r"manifest\.sample_period_s: nan is not allowed; give a finite number"),
        ({"sample_period_s": 0}, r"sample_period_s is 0.0, not a time in \(0, 60\] s"),
        ({"sample_period_s": 1e308}, r"sample_period_s is 1e\+308, not a time in \(0, 60\] s"),
        ({"labels": {"expert": 5}}, r"labels\.expert: expected a table"),
        ({"labels": {"expert": {"speed_horizon_s": "1"}}}, r"labels\.expert\.speed_horizon_s: expected a number"),
        ({"labels": {"expert": {"stop_speed_mps": -1}}},
         r"manifest\.json: labels\.expert\.stop_speed_mps: -1 is out of range; give m/s in \(0, 2\]; regenerate"),
        ({"labels": {"expert": {"wheelbase_m": 1e308}}},
         r"manifest\.json: labels\.expert\.wheelbase_m: 1e\+308 is out of range; give metres in \(0, 20\]; regenerate"),
    ],
)
def test_manifest_values_are_checked(data, change, message):
    raw = json.loads((data / MANIFEST_NAME).read_text())
    raw.update(change)
    (data / MANIFEST_NAME).write_text(json.dumps(raw))
    with pytest.raises(CrchflError, match=message):
        read_manifest(data)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"samples": -1}, "needs samples >= 0"),
        ({"sha256": "abc"}, "64 hex digits"),
        ({"png_bytes_per_sample": float("nan")}, r"shards\[0\]\.png_bytes_per_sample: nan is not allowed"),
        ({"png_bytes_per_sample": -1.0}, "png_bytes_per_sample >= 0"),
        ({"split": "val"}, "split 'val'"),
        ({"file": "a/b.h5"}, "not a plain"),
        ({"file": ".hidden.h5"}, "not a plain"),
        ({"samples": 2}, r"a\.h5: images is uint8 \[3, 4, 48, 64, 3\], the format has uint8 \[2, 4, 48, 64, 3\]"),
    ],
)
def test_shard_entries_are_checked(data, change, message):
    reseal(data, **change)
    with pytest.raises(CrchflError, match=message):
        load_samples(data)


def test_the_mosaic_reads_through_the_same_checks(data, tmp_path):
    write_mosaic(data, tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 0
    assert not list(tmp_path.glob(".m.png*"))  # written atomically, nothing left beside it
    replace_dataset(data, "steer_class", np.array([0, 99, 2]))
    with pytest.raises(CrchflError, match="steer_class holds 99"):
        write_mosaic(data, tmp_path / "m2.png")
    assert not (tmp_path / "m2.png").exists()


def test_read_shard_without_a_manifest_takes_any_image_size_within_bounds(data):
    entry = read_manifest(data).entry("a.h5")
    assert read_shard(data, entry).images.shape == (3, 4, H, W, 3)
    with pytest.raises(CrchflError, match=r"images is uint8 \[3, 4, 48, 64, 3\], the format has uint8 \[3, 4, 12, 16, 3\]"):
        read_shard(data, entry, image_hw=(12, 16))


def test_a_damaged_image_chunk_read_by_the_torch_dataset_is_refused(tmp_path):
    rng = np.random.default_rng(0)
    header = Manifest(scenario="paper", seed=0, sample_period_s=0.25, image_height=H, image_width=W, compression="lzf")
    data = dataclasses.replace(shard_data(3), images=rng.integers(0, 4, (3, 4, H, W, 3), dtype=np.uint8) * 60)
    DatasetWriter(tmp_path, header).add("a.h5", data, vehicle="v0", town="town01", edge="e0", split="train")
    with h5py.File(tmp_path / "a.h5", "r") as f:  # where sample 1's compressed chunk lies in the file
        offset, size = f["images"].id.get_chunk_info(1).byte_offset, f["images"].id.get_chunk_info(1).size
    raw = bytearray((tmp_path / "a.h5").read_bytes())
    raw[offset : offset + size] = b"\xff" * size
    (tmp_path / "a.h5").write_bytes(bytes(raw))
    reseal(tmp_path)  # the labels are intact: the dataset opens
    dataset = ShardDataset(tmp_path)
    assert dataset[0][0].shape == (4, H, W, 3)
    with pytest.raises(CrchflError, match=r"a\.h5: unreadable sample 1 .*regenerate the data set"):
        dataset[1]
    dataset.close()
    with pytest.raises(CrchflError, match=r"a\.h5: unreadable shard"):
        load_samples(tmp_path)


def test_images_that_do_not_fit_in_memory_are_an_error_not_a_traceback(data, monkeypatch):
    real_empty = np.empty

    def no_memory(shape, dtype=float):
        if len(shape) == 5:  # the images' array; what 10**6 gzip'd shards of zeros could declare
            raise MemoryError
        return real_empty(shape, dtype)

    monkeypatch.setattr(np, "empty", no_memory)
    with pytest.raises(CrchflError, match=r"data: the selected shards' images take 0\.0 GiB, more memory"):
        load_samples(data)


def test_an_unreadable_shard_file_is_an_error_naming_it(data, monkeypatch):
    from crchfl_sumo.data import shards

    def denied(path, block_bytes=0):  # what a file without read permission gives (these tests run as root)
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(shards, "sha256_file", denied)
    with pytest.raises(CrchflError, match=r"a\.h5: shard cannot be read \(Permission denied\); check its permissions"):
        load_samples(data)
