"""On-disk data set: one HDF5 shard per vehicle, its checksum, and DatasetWriter (resume).

Layout of a data set folder::

    DIR/manifest.json     header (scenario, seed, cameras, label schema, image
                          size) + one entry per finished shard (sha256 included;
                          data/manifest.py)
    DIR/<name>.h5         one vehicle's samples: datasets images uint8
                          [N,4,H,W,3] (one chunk per sample), actions float32
                          [N,3], steer_class int64 [N], command int64 [N],
                          speed_mps, target_speed_mps float32 [N], perturbation float32 [N,3]
                          (lateral_m, yaw_deg, forward_m of a recovery sample's pose), t_s,
                          x_m, y_m, heading_rad float64 [N], signal_state int8 [N]
                          (labels.SIGNAL_NAMES), signal_distance_m, yield_gap_m
                          float32 [N] (inf: none; format 5); command codes 4 and 5, the
                          lane changes, from format 6; attributes
                          vehicle, town, edge, split

Both files are plain formats (h5py / json suffice to read them). Every file is
written under a temporary name in DIR, then renamed, so a crash leaves either
the old file or the new one. The manifest is rewritten after each shard, so an
interrupted generation knows which shards are finished and a rerun skips them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Literal

import cv2
import h5py
import numpy as np

from crchfl_sumo.core.atomic import atomic_path, remove_stale_temporaries
from crchfl_sumo.core.config import changed_keys_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.labels import (
    ACTION_NAMES, COMMAND_NAMES, NUM_COMMANDS, NUM_STEER_CLASSES, SIGNAL_NAMES, SIGNAL_UNKNOWN,
)
from crchfl_sumo.data.manifest import (
    MANIFEST_NAME, SPLITS, Manifest, ShardEntry, is_plain_shard_name, read_manifest, write_manifest,
)
from crchfl_sumo.data.recovery import PERTURBATION_NAMES
from crchfl_sumo.vision.camera import CAMERA_NAMES, MAX_HEIGHT_PX, MAX_WIDTH_PX

log = logging.getLogger(__name__)

# Per-sample datasets beyond the images, with their dtypes (what a shard of this version must hold).
LABEL_DATASETS = {
    "actions": np.float32,
    "steer_class": np.int64,
    "command": np.int64,
    "speed_mps": np.float32,
    "target_speed_mps": np.float32,
    "perturbation": np.float32,
    "t_s": np.float64,
    "x_m": np.float64,
    "y_m": np.float64,
    "heading_rad": np.float64,
    "signal_state": np.int8,
    "signal_distance_m": np.float32,
    "yield_gap_m": np.float32,
}
# Datasets format 5 added, and what a format-4 shard's samples read as (signal unknown, no gap known).
ADDED_IN_5 = {"signal_state": SIGNAL_UNKNOWN, "signal_distance_m": np.inf, "yield_gap_m": np.inf}
# Distances where inf means "none": finite otherwise, never NaN.
INF_IS_NONE = ("signal_distance_m", "yield_gap_m")
LABEL_SHAPES = {"actions": (len(ACTION_NAMES),), "perturbation": (len(PERTURBATION_NAMES),)}  # per sample; others []
# Deflate cannot shrink data by more than about 1032:1 (LZF by less): a shard file of n bytes holds at most
# this many times n bytes of a compressed dataset. A larger declared shape is refused before any allocation.
MAX_COMPRESSION_RATIO = 1100

Compression = Literal["lzf", "gzip", "none"]


@dataclass(frozen=True)
class ShardData:
    """One vehicle's samples as numpy arrays (N samples, images H x W)."""

    images: np.ndarray  # uint8 [N, 4, H, W, 3], cameras in CAMERA_NAMES order, RGB
    actions: np.ndarray  # float32 [N, 3] (throttle, steer, brake)
    steer_class: np.ndarray  # int64 [N]
    command: np.ndarray  # int64 [N], labels.COMMAND_NAMES
    speed_mps: np.ndarray  # float32 [N]
    target_speed_mps: np.ndarray  # float32 [N], data/expert.py's target_speeds
    perturbation: np.ndarray  # float32 [N, 3] (lateral_m, yaw_deg, forward_m); all 0 = rendered on the track
    t_s: np.ndarray  # float64 [N] simulated time of each sample
    x_m: np.ndarray  # float64 [N] vehicle centre
    y_m: np.ndarray
    heading_rad: np.ndarray
    # the next signal on the route (labels.SIGNAL_NAMES) and its stop line's distance, the gap of the nearest
    # junction foe to yield to (sim.yield_gap_m); None: unknown for every sample (int8 / float32 [N], inf: none)
    signal_state: np.ndarray | None = None
    signal_distance_m: np.ndarray | None = None
    yield_gap_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.images)
        for name, unknown in ADDED_IN_5.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(n, unknown, dtype=LABEL_DATASETS[name]))
        shape = self.images.shape
        if self.images.dtype != np.uint8 or len(shape) != 5 or shape[1] != len(CAMERA_NAMES) or shape[4] != 3:
            raise ValueError(f"images must be uint8 [N, 4, H, W, 3], got {self.images.dtype} {self.images.shape}")
        if self.actions.shape != (n, len(ACTION_NAMES)):
            raise ValueError(f"actions must be [{n}, 3], got {self.actions.shape}")
        if self.perturbation.shape != (n, len(PERTURBATION_NAMES)):
            raise ValueError(f"perturbation must be [{n}, {len(PERTURBATION_NAMES)}], got {self.perturbation.shape}")
        for name in ("steer_class", "command", "speed_mps", "target_speed_mps", "t_s", "x_m", "y_m", "heading_rad",
                     *ADDED_IN_5):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must be [{n}], got {getattr(self, name).shape}")

    def __len__(self) -> int:
        return len(self.images)


def sha256_file(path: Path, block_bytes: int = 1 << 22) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(block_bytes):
            digest.update(block)
    return digest.hexdigest()


def png_bytes_per_sample(images: np.ndarray) -> float:
    """Mean over samples of the summed PNG size (OpenCV, default level 3) of the four RGB images."""
    if len(images) == 0:
        return 0.0
    total = 0
    for sample in images:
        for image in sample:
            ok, encoded = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            if not ok:
                raise RuntimeError("OpenCV failed to PNG-encode an image")
            total += len(encoded)
    return total / len(images)


def write_shard(
    path: Path,
    data: ShardData,
    *,
    vehicle: str,
    town: str,
    edge: str,
    split: str,
    compression: str = "lzf",
) -> ShardEntry:
    """Write ``data`` atomically as an HDF5 shard at ``path``; return its manifest entry.

    The file bytes depend only on the arguments (no timestamps), so the same
    samples always give the same sha256.
    """
    if split not in SPLITS:
        raise CrchflError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    path = Path(path)
    options = _compression_options(compression)
    n, _, height, width, _ = data.images.shape
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.create_dataset(
                "images",
                data=data.images,
                chunks=(1, len(CAMERA_NAMES), height, width, 3) if n else None,
                **(options if n else {}),
            )
            for name, dtype in LABEL_DATASETS.items():
                f.create_dataset(name, data=getattr(data, name).astype(dtype))
            for key, value in (("vehicle", vehicle), ("town", town), ("edge", edge), ("split", split)):
                f.attrs[key] = value
            f.attrs["cameras"] = ",".join(CAMERA_NAMES)
            f.attrs["actions"] = ",".join(ACTION_NAMES)
            f.attrs["commands"] = ",".join(COMMAND_NAMES)
            f.attrs["perturbation"] = ",".join(PERTURBATION_NAMES)
            f.attrs["signals"] = ",".join(SIGNAL_NAMES)
    return ShardEntry(
        file=path.name,
        vehicle=vehicle,
        town=town,
        edge=edge,
        split=split,
        samples=int(n),
        size_bytes=path.stat().st_size,
        sha256=sha256_file(path),
        png_bytes_per_sample=round(png_bytes_per_sample(data.images), 1),
    )


def _compression_options(compression: str) -> dict[str, Any]:
    if compression == "lzf":
        return {"compression": "lzf"}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 4}
    if compression == "none":
        return {}
    raise CrchflError(f"dataset.compression must be 'lzf', 'gzip' or 'none', got {compression!r}")


def verify_shard(root: Path, entry: ShardEntry) -> Path:
    """Path of ``entry``'s file after checking its size and sha256; CrchflError if it is bad."""
    path = shard_path(root, entry)
    fix = regenerate_fix(root, path)
    if not path.is_file():
        raise CrchflError(f"{path}: shard listed in {MANIFEST_NAME} is missing; {fix}")
    size = path.stat().st_size
    if size != entry.size_bytes:
        raise CrchflError(
            f"{path}: shard is truncated or altered ({size} bytes, manifest says {entry.size_bytes}); {fix}"
        )
    try:
        digest = sha256_file(path)
    except OSError as exc:
        raise CrchflError(f"{path}: shard cannot be read ({exc.strerror}); check its permissions") from None
    if digest != entry.sha256:
        raise CrchflError(f"{path}: shard is corrupt (sha256 differs from {MANIFEST_NAME}); {fix}")
    return path


def regenerate_fix(root: Path, path: Path) -> str:
    return (
        f"delete {path} and rerun the same `crchfl-sumo dataset` command with --out {root}: "
        "it regenerates only missing or damaged shards"
    )


def shard_path(root: Path, entry: ShardEntry) -> Path:
    """Where ``entry``'s file lies: inside ``root``, or a CrchflError (a manifest naming ../x.h5, a link out)."""
    root = Path(root)
    path = root / entry.file
    if not is_plain_shard_name(entry.file) or (path.exists() and path.resolve().parent != root.resolve()):
        raise CrchflError(
            f"{root / MANIFEST_NAME}: shard {entry.file!r} lies outside the data set folder {root}; "
            "a shard must be a plain file in it: regenerate the data set"
        )
    return path


@contextlib.contextmanager
def open_shard(
    root: Path, entry: ShardEntry, verify: bool = True, image_hw: tuple[int, int] | None = None
) -> Iterator[tuple[h5py.File, dict[str, np.ndarray]]]:
    """The one way a shard is opened: (the open file, its label arrays), checked against the schema.

    Checked, in this order, before any image is read: size and sha256
    (``verify``), that every dataset of the format is there as a plain dataset
    of this file, its dtype and shape ([N, 4, H, W, 3] uint8 images of the
    manifest's ``image_hw``, N = the manifest's sample count; labels as
    LABEL_DATASETS and LABEL_SHAPES), that the file can hold what the shapes
    declare, then the labels' values (finite; pedals in [0, 1], steer in
    [-1, 1], steer classes 0..6, commands 0..3, speeds >= 0). Whatever h5py
    raises on a damaged file, here or in the caller's block, becomes a CrchflError.
    """
    path = verify_shard(root, entry) if verify else shard_path(root, entry)
    fix = regenerate_fix(root, path)
    try:
        with h5py.File(path, "r") as f:
            present = _check_layout(f, path, entry, image_hw, fix)
            labels = {
                name: f[name][()] if name in present else np.full(entry.samples, ADDED_IN_5[name], LABEL_DATASETS[name])
                for name in LABEL_DATASETS
            }
            check_label_values(labels, str(path), fix)
            yield f, labels
    except CrchflError:
        raise
    except MemoryError:
        raise CrchflError(f"{path}: the shard's arrays need more memory than this machine can give; {fix}") from None
    except (OSError, KeyError, ValueError, TypeError, RuntimeError, AttributeError) as exc:
        raise CrchflError(f"{path}: unreadable shard ({_one_line(exc)}); {fix}") from None


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _check_layout(
    f: h5py.File, path: Path, entry: ShardEntry, image_hw: tuple[int, int] | None, fix: str
) -> tuple[str, ...]:
    """Names, dtypes and shapes of the shard's datasets, and what the file can hold; reads no data.
    Returns the label datasets present (a format-4 shard lacks those of ADDED_IN_5)."""
    optional = [] if all(name in f for name in ADDED_IN_5) else list(ADDED_IN_5)  # all of them, or none
    missing = [name for name in ("images", *LABEL_DATASETS) if name not in f and name not in optional]
    if missing:
        raise CrchflError(
            f"{path}: shard has no {', '.join(missing)} (written by an older version of crchfl-sumo or damaged); "
            "regenerate the data set into a new folder with `crchfl-sumo dataset`"
        )
    n = entry.samples
    expected = {name: (np.dtype(dtype), (n, *LABEL_SHAPES.get(name, ()))) for name, dtype in LABEL_DATASETS.items()}
    present = tuple(name for name in LABEL_DATASETS if name not in optional)
    for name in ("images", *present):
        link = f.get(name, getlink=True)
        ds = f.get(name)
        if not isinstance(link, h5py.HardLink) or not isinstance(ds, h5py.Dataset) or ds.is_virtual or ds.external:
            raise CrchflError(f"{path}: {name} is not a plain dataset stored in this file; {fix}")
        if name == "images":
            ok = ds.dtype == np.uint8 and ds.ndim == 5 and ds.shape[0] == n and ds.shape[1] == len(CAMERA_NAMES)
            ok = ok and ds.shape[4] == 3 and (image_hw is None or tuple(ds.shape[2:4]) == tuple(image_hw))
            ok = ok and ds.shape[2] <= MAX_HEIGHT_PX and ds.shape[3] <= MAX_WIDTH_PX
            want = f"uint8 [{n}, {len(CAMERA_NAMES)}, {'H, W' if image_hw is None else ', '.join(map(str, image_hw))}, 3]"
        else:
            dtype, shape = expected[name]
            ok = ds.dtype == dtype and ds.shape == shape
            want = f"{dtype} {list(shape)}"
        if not ok:
            raise CrchflError(f"{path}: {name} is {ds.dtype} {list(ds.shape or ())}, the format has {want}; {fix}")
        declared = int(np.prod(ds.shape, dtype=np.float64) * ds.dtype.itemsize)
        stored = path.stat().st_size * (MAX_COMPRESSION_RATIO if ds.compression else 1)
        if declared > stored:
            raise CrchflError(
                f"{path}: {name} declares {declared} bytes, more than a {path.stat().st_size}-byte file can hold; {fix}"
            )
    return present


def check_label_values(labels: dict[str, np.ndarray], where: str, fix: str) -> None:
    """Refuse label values a sample cannot have: NaN or inf anywhere, pedals outside [0, 1], steer outside
    [-1, 1], steer classes outside 0..6, commands outside 0..3, negative speeds."""
    for name, values in labels.items():
        if name in INF_IS_NONE:  # inf says "none"
            if np.isnan(values).any() or (values == -np.inf).any():
                raise CrchflError(f"{where}: {name} holds NaN or -inf; distances are finite, or inf for none; {fix}")
            continue
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            raise CrchflError(f"{where}: {name} holds {values[~np.isfinite(values)][0]}; labels must be finite; {fix}")
    ranges = (
        ("throttle", labels["actions"][:, 0], 0.0, 1.0, "throttle lies in [0, 1]"),
        ("steer", labels["actions"][:, 1], -1.0, 1.0, "steer lies in [-1, 1]"),
        ("brake", labels["actions"][:, 2], 0.0, 1.0, "brake lies in [0, 1]"),
        ("steer_class", labels["steer_class"], 0, NUM_STEER_CLASSES - 1, f"steer classes are 0..{NUM_STEER_CLASSES - 1}"),
        ("command", labels["command"], 0, NUM_COMMANDS - 1, f"commands are 0..{NUM_COMMANDS - 1}"),
        ("speed_mps", labels["speed_mps"], 0.0, np.inf, "speeds are >= 0"),
        ("target_speed_mps", labels["target_speed_mps"], 0.0, np.inf, "speeds are >= 0"),
    ) + tuple(
        (name, labels[name], low, high, rule)
        for name, low, high, rule in (
            ("signal_state", 0, len(SIGNAL_NAMES) - 1, f"signal codes are 0..{len(SIGNAL_NAMES) - 1}"),
            ("signal_distance_m", 0.0, np.inf, "distances to a stop line are >= 0"),
        )
        if name in labels
    )
    for name, values, low, high, rule in ranges:
        bad = values[(values < low) | (values > high)]
        if len(bad):
            raise CrchflError(f"{where}: {name} holds {bad[0]}; {rule}; {fix}")


def read_shard(
    root: Path, entry: ShardEntry, verify: bool = True, images: bool = True, image_hw: tuple[int, int] | None = None
) -> ShardData:
    """Read one shard through ``open_shard`` (checked against the manifest first unless ``verify`` is False).

    ``images=False`` skips the image array (returned with zero samples' worth
    of pixels: shape [N, 4, 0, 0, 3]) for statistics that need only labels.
    ``image_hw``: the manifest's image size, which the images must have.
    """
    with open_shard(root, entry, verify, image_hw) as (f, labels):
        if images:
            pixels = f["images"][()]
        else:
            pixels = np.zeros((entry.samples, len(CAMERA_NAMES), 0, 0, 3), np.uint8)
    return ShardData(images=pixels, **labels)


class DatasetWriter:
    """Fills a data set folder shard by shard, resuming an earlier, interrupted run.

    A folder that already holds a manifest with the same header (scenario,
    seed, cameras, labels, image size, compression) is resumed: shards whose
    file still matches its checksum and the shard schema count as done and are kept; the rest are
    dropped from the manifest and written again. A different header is an
    error, so two data sets never mix in one folder, unless that manifest
    lists no shard: a run that failed before its first shard (a vehicle that
    left the network, say) leaves nothing to mix, and a rerun with mended
    settings starts afresh there.
    """

    def __init__(self, root: Path, header: Manifest):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        for path in remove_stale_temporaries(self.root):
            log.info("removed %s left by an interrupted run", path)
        header = dataclasses.replace(header, shards=())
        kept: list[ShardEntry] = []
        if (self.root / MANIFEST_NAME).is_file():
            old = read_manifest(self.root)
            if old.header() != header.header():
                if old.shards:
                    raise CrchflError(
                        f"{self.root / MANIFEST_NAME}: this folder holds a data set made with other settings "
                        f"(scenario {old.scenario!r}, seed {old.seed}; they differ in "
                        f"{changed_keys_text(old.header(), header.header())}: a default may have changed since); "
                        "choose another --out folder or delete this one"
                    )
                log.info("%s: replacing the manifest of an earlier run that wrote no shard", self.root)
            for entry in old.shards:
                try:
                    read_shard(self.root, entry, images=False, image_hw=(header.image_height, header.image_width))
                    kept.append(entry)
                except CrchflError as exc:
                    log.warning("will regenerate: %s", exc)
        self.manifest = dataclasses.replace(header, shards=tuple(kept))
        write_manifest(self.root, self.manifest)

    def is_done(self, file: str) -> bool:
        """True if shard ``file`` was finished (by this run or one before it)."""
        return self.manifest.entry(file) is not None

    def add(self, file: str, data: ShardData, *, vehicle: str, town: str, edge: str, split: str) -> ShardEntry:
        """Write shard ``file`` and record it in the manifest (both atomically)."""
        if not is_plain_shard_name(file):
            raise ValueError(f"shard file name must be a plain '<name>.h5', got {file!r}")
        if data.images.shape[2:4] != (self.manifest.image_height, self.manifest.image_width) and len(data):
            raise ValueError(
                f"shard {file}: images are {data.images.shape[2:4]}, the data set's are "
                f"{(self.manifest.image_height, self.manifest.image_width)}"
            )
        entry = write_shard(
            self.root / file,
            data,
            vehicle=vehicle,
            town=town,
            edge=edge,
            split=split,
            compression=self.manifest.compression,
        )
        # Sorted by file name, so the manifest does not depend on what a resume redid.
        shards = sorted([s for s in self.manifest.shards if s.file != file] + [entry], key=lambda s: s.file)
        self.manifest = dataclasses.replace(self.manifest, shards=tuple(shards))
        write_manifest(self.root, self.manifest)
        log.info("wrote %s (%d samples)", file, entry.samples)
        return entry
