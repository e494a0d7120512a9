"""Data set settings (split sizes, sample period, recovery share, bytes per sample) and the readers.

Two ways to read a data set written by dataset_io:
- ``ShardDataset``: a torch Dataset reading one sample at a time from the
  HDF5 shards (small memory, works with DataLoader workers);
- ``load_samples`` / ``load_vehicle_samples``: the fast path, whole shards
  read into in-memory ``Samples`` (uint8 images) once.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import torch

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.manifest import Manifest, ShardEntry, read_manifest
from crchfl_sumo.data.samples import FIELDS, Samples
from crchfl_sumo.data.shards import (
    LABEL_DATASETS,
    LABEL_SHAPES,
    open_shard,
    read_shard,
)
from crchfl_sumo.vision.camera import CAMERA_NAMES

SAMPLE_LABELS = FIELDS[1:]  # what a Samples holds besides the images, each a shard dataset of that name




def measured_sample_bytes(manifest: Manifest) -> int:
    """Measured size of one sample [bytes]: the data set's mean PNG size of its four images.

    This is what ``ledger.resolve_sizes(..., measured_sample_bytes=...)`` takes
    when ``ledger.sample_size = "measured"``; the nominal alternative is the
    paper's 1800 KB (manifest.NOMINAL_SAMPLE_BYTES).
    """
    if manifest.samples == 0:
        raise CrchflError("ledger.sample_size = 'measured' needs a data set with samples; generate it first")
    return int(round(manifest.png_bytes_per_sample))


def _selected(root: Path, split: str | None, vehicles: list[str] | None) -> tuple[Manifest, tuple[ShardEntry, ...]]:
    manifest = read_manifest(root)
    shards = manifest.select(split, vehicles)
    if vehicles is not None:
        missing = sorted(set(vehicles) - {s.vehicle for s in shards})
        if missing:
            raise CrchflError(f"{root}: no {split or ''} shard for vehicle(s) {', '.join(missing)}")
    return manifest, shards


def load_samples(
    root: str | Path, split: str | None = None, vehicles: list[str] | None = None, verify: bool = True
) -> Samples:
    """Fast path: the selected shards' samples, concatenated in manifest order, in memory."""
    root = Path(root)
    manifest, shards = _selected(root, split, vehicles)
    image_hw = (manifest.image_height, manifest.image_width)
    for entry in shards:  # every shard checked (sha256, schema, values) before the images' memory is taken
        read_shard(root, entry, verify, images=False, image_hw=image_hw)
    n = sum(s.samples for s in shards)
    # Read straight into one preallocated array: no second copy of the images.
    try:
        images = np.empty((n, len(CAMERA_NAMES), *image_hw, 3), np.uint8)
    except MemoryError:
        raise CrchflError(
            f"{root}: the selected shards' images take {n * len(CAMERA_NAMES) * image_hw[0] * image_hw[1] * 3 / 2**30:.1f} "
            "GiB, more memory than this machine can give; select fewer vehicles or a smaller data set"
        ) from None
    columns = {name: np.empty((n, *LABEL_SHAPES.get(name, ())), LABEL_DATASETS[name]) for name in SAMPLE_LABELS}
    start = 0
    for entry in shards:
        end = start + entry.samples
        with open_shard(root, entry, verify=False, image_hw=image_hw) as (f, labels):
            for name, column in columns.items():
                column[start:end] = labels[name]
            if entry.samples:
                f["images"].read_direct(images, dest_sel=np.s_[start:end])
        start = end
    return Samples.from_numpy(images, **columns)


def load_vehicle_samples(root: str | Path, split: str = "train", verify: bool = True) -> dict[str, Samples]:
    """Fast path per vehicle: vehicle id -> its in-memory Samples (one vehicle, one client)."""
    root = Path(root)
    manifest, shards = _selected(root, split, None)
    image_hw = (manifest.image_height, manifest.image_width)
    return {s.vehicle: _to_samples(read_shard(root, s, verify, image_hw=image_hw)) for s in shards}


def _to_samples(data) -> Samples:
    return Samples.from_numpy(data.images, **{name: getattr(data, name) for name in SAMPLE_LABELS})


class ShardDataset(torch.utils.data.Dataset):
    """Per-sample reads from the shards: item i -> (images uint8 [4,H,W,3], actions f32 [3], steer_class i64,
    command i64, speed_mps f32, target_speed_mps f32).

    Checksums and the shard schema (shards.open_shard) are checked once, when
    the dataset is built. Files are opened lazily in each process (safe with
    DataLoader workers).
    """

    def __init__(
        self, root: str | Path, split: str | None = None, vehicles: list[str] | None = None, verify: bool = True
    ):
        self.root = Path(root)
        self.manifest, self.shards = _selected(self.root, split, vehicles)
        if verify:
            image_hw = (self.manifest.image_height, self.manifest.image_width)
            for entry in self.shards:
                read_shard(self.root, entry, images=False, image_hw=image_hw)
        self._ends = np.cumsum([s.samples for s in self.shards], dtype=np.int64)
        self._files: dict[int, h5py.File] = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return int(self._ends[-1]) if len(self._ends) else 0

    def __getitem__(self, index: int) -> tuple[torch.Tensor, ...]:
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(index)
        shard = int(np.searchsorted(self._ends, index, side="right"))
        row = index - (int(self._ends[shard - 1]) if shard else 0)
        f = self._file(shard)
        try:
            return (
                torch.from_numpy(f["images"][row]),
                torch.from_numpy(f["actions"][row]),
                torch.tensor(int(f["steer_class"][row]), dtype=torch.int64),
                torch.tensor(int(f["command"][row]), dtype=torch.int64),
                torch.tensor(float(f["speed_mps"][row]), dtype=torch.float32),
                torch.tensor(float(f["target_speed_mps"][row]), dtype=torch.float32),
            )
        except (OSError, KeyError, ValueError, RuntimeError) as exc:  # a damaged chunk (checks off, or changed since)
            path = self.root / self.shards[shard].file
            raise CrchflError(f"{path}: unreadable sample {row} ({' '.join(str(exc).split())}); regenerate the data set") from None

    def _file(self, shard: int) -> h5py.File:
        if self._pid != os.getpid():  # forked into a worker: handles are not shareable
            self._files, self._pid = {}, os.getpid()
        if shard not in self._files:
            self._files[shard] = h5py.File(self.root / self.shards[shard].file, "r")
        return self._files[shard]

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files = {}

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_files"] = {}
        return state
