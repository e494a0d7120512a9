"""On-disk data set: one HDF5 shard per vehicle, a JSON manifest, checksums, resume.

Layout of a data set folder::

    DIR/manifest.json     header (scenario, seed, cameras, label schema, image
                          size) + one entry per finished shard (sha256 included)
    DIR/<name>.h5         one vehicle's samples: datasets images uint8
                          [N,4,H,W,3] (one chunk per sample), actions float32
                          [N,3], steer_class int64 [N], command int64 [N],
                          speed_mps, target_speed_mps float32 [N], perturbation float32 [N,2]
                          (lateral_m, yaw_deg of a recovery sample's pose), t_s,
                          x_m, y_m, heading_rad float64 [N]; attributes
                          vehicle, town, edge, split

Both files are plain formats (h5py / json suffice to read them). Every file is
written under a temporary name in DIR, then renamed, so a crash leaves either
the old file or the new one. The manifest is rewritten after each shard, so an
interrupted generation knows which shards are finished and a rerun skips them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import h5py
import numpy as np

from crchfl_sumo.core.atomic import atomic_path, atomic_write_text, remove_stale_temporaries
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.data.labels import ACTION_NAMES, COMMAND_NAMES, STEER_CLASS_VALUES
from crchfl_sumo.vision.camera import CAMERA_NAMES

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"
FORMAT_NAME = "crchfl-sumo-dataset"
FORMAT_VERSION = 3  # 2: command, speed_mps and perturbation per sample; 3: target_speed_mps
NOMINAL_SAMPLE_BYTES = 1800 * 1024  # the paper's charge per sample: four PNGs of ~450 KB (FACTS.md)
SPLITS = ("train", "test")
PERTURBATION_NAMES = ("lateral_m", "yaw_deg")  # positive = the rendered pose is left of / turned left of the track
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
}

Compression = Literal["lzf", "gzip", "none"]


def label_schema() -> dict[str, Any]:
    """The label schema recorded in every manifest."""
    return {
        "actions": list(ACTION_NAMES),
        "cameras": list(CAMERA_NAMES),
        "steer_class_values": [round(float(v), 6) for v in STEER_CLASS_VALUES],
        "steer_sign": "positive = right, negative = left",
        "throttle_brake_range": [0.0, 1.0],
        "commands": list(COMMAND_NAMES),
        "perturbation": list(PERTURBATION_NAMES),
    }


@dataclass(frozen=True)
class ShardData:
    """One vehicle's samples as numpy arrays (N samples, images H x W)."""

    images: np.ndarray  # uint8 [N, 4, H, W, 3], cameras in CAMERA_NAMES order, RGB
    actions: np.ndarray  # float32 [N, 3] (throttle, steer, brake)
    steer_class: np.ndarray  # int64 [N]
    command: np.ndarray  # int64 [N], labels.COMMAND_NAMES
    speed_mps: np.ndarray  # float32 [N]
    target_speed_mps: np.ndarray  # float32 [N], data/expert.py's target_speeds
    perturbation: np.ndarray  # float32 [N, 2] (lateral_m, yaw_deg); (0, 0) = rendered on the track
    t_s: np.ndarray  # float64 [N] simulated time of each sample
    x_m: np.ndarray  # float64 [N] vehicle centre
    y_m: np.ndarray
    heading_rad: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.images)
        shape = self.images.shape
        if self.images.dtype != np.uint8 or len(shape) != 5 or shape[1] != len(CAMERA_NAMES) or shape[4] != 3:
            raise ValueError(f"images must be uint8 [N, 4, H, W, 3], got {self.images.dtype} {self.images.shape}")
        if self.actions.shape != (n, len(ACTION_NAMES)):
            raise ValueError(f"actions must be [{n}, 3], got {self.actions.shape}")
        if self.perturbation.shape != (n, len(PERTURBATION_NAMES)):
            raise ValueError(f"perturbation must be [{n}, 2], got {self.perturbation.shape}")
        for name in ("steer_class", "command", "speed_mps", "target_speed_mps", "t_s", "x_m", "y_m", "heading_rad"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must be [{n}], got {getattr(self, name).shape}")

    def __len__(self) -> int:
        return len(self.images)


@dataclass(frozen=True)
class ShardEntry:
    """The manifest's record of one finished shard."""

    file: str
    vehicle: str
    town: str
    edge: str
    split: str
    samples: int
    size_bytes: int
    sha256: str
    png_bytes_per_sample: float  # mean PNG-encoded size of the sample's four images


@dataclass(frozen=True)
class Manifest:
    """Header of a data set plus its finished shards (manifest.json)."""

    scenario: str
    seed: int
    sample_period_s: float
    image_height: int
    image_width: int
    camera: dict[str, Any] = field(default_factory=dict)
    labels: dict[str, Any] = field(default_factory=label_schema)
    compression: str = "lzf"
    shards: tuple[ShardEntry, ...] = ()

    def header(self) -> dict[str, Any]:
        """Everything but the shard list: what two runs must share to fill one folder."""
        data = _jsonable(dataclasses.asdict(self))
        data.pop("shards")
        return data

    def entry(self, file: str) -> ShardEntry | None:
        """The shard entry for ``file``, or None."""
        return next((s for s in self.shards if s.file == file), None)

    def select(self, split: str | None = None, vehicles: list[str] | None = None) -> tuple[ShardEntry, ...]:
        """Shards of ``split`` (None: all) and of ``vehicles`` (None: all), in manifest order."""
        if split is not None and split not in SPLITS:
            raise CrchflError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
        return tuple(
            s for s in self.shards if (split is None or s.split == split) and (vehicles is None or s.vehicle in vehicles)
        )

    @property
    def samples(self) -> int:
        return sum(s.samples for s in self.shards)

    @property
    def speed_horizon_s(self) -> float:
        """The horizon of the samples' target speeds (labels.expert.speed_horizon_s)."""
        return float(self.labels.get("expert", {}).get("speed_horizon_s", ExpertConfig().speed_horizon_s))

    def check_model(self, model_config, where: str) -> None:
        """Refuse a model (a learning.settings.ModelConfig) these labels cannot train: another target-speed horizon."""
        if model_config.longitudinal == "target_speed":
            self.check_horizon(model_config.speed_horizon_s, where)

    def check_horizon(self, model_speed_horizon_s: float, where: str) -> None:
        """Refuse a target-speed model of another horizon than these labels'."""
        if abs(model_speed_horizon_s - self.speed_horizon_s) > 1e-9:
            raise CrchflError(
                f"model.speed_horizon_s: {model_speed_horizon_s} s, but the data set {where} labels the target "
                f"speed {self.speed_horizon_s} s ahead; set model.speed_horizon_s = {self.speed_horizon_s}"
            )

    @property
    def png_bytes_per_sample(self) -> float:
        """Sample-weighted mean PNG size of one sample's four images over all shards (0 if empty)."""
        total = self.samples
        return sum(s.png_bytes_per_sample * s.samples for s in self.shards) / total if total else 0.0

    def to_json(self) -> str:
        data = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **self.header()}
        data["samples"] = self.samples
        data["nominal_bytes_per_sample"] = NOMINAL_SAMPLE_BYTES
        data["png_bytes_per_sample"] = round(self.png_bytes_per_sample, 1)
        data["shards"] = [dataclasses.asdict(s) for s in self.shards]
        return json.dumps(data, indent=2) + "\n"

    @staticmethod
    def from_json(text: str, where: str) -> Manifest:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CrchflError(f"{where}: not valid JSON ({exc}); delete the folder and generate it again") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
            raise CrchflError(f"{where}: not a crchfl-sumo data set manifest")
        if data.get("version") != FORMAT_VERSION:
            raise CrchflError(
                f"{where}: format version {data.get('version')}, this code reads {FORMAT_VERSION}; regenerate the data set"
            )
        try:
            shards = tuple(ShardEntry(**s) for s in data["shards"])
            header = {f.name: data[f.name] for f in dataclasses.fields(Manifest) if f.name != "shards"}
        except (KeyError, TypeError) as exc:
            raise CrchflError(f"{where}: malformed manifest ({exc}); regenerate the data set") from None
        return Manifest(**header, shards=shards)


def _jsonable(value: Any) -> Any:
    """Round trip through JSON so that tuples/lists and ints/floats compare alike."""
    return json.loads(json.dumps(value))


def sha256_file(path: Path, block_bytes: int = 1 << 22) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(block_bytes):
            digest.update(block)
    return digest.hexdigest()


# ---------------------------------------------------------------- shards


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
    path = Path(root) / entry.file
    fix = (
        f"delete {path} and rerun the same `crchfl-sumo dataset` command with --out {root}: "
        "it regenerates only missing or damaged shards"
    )
    if not path.is_file():
        raise CrchflError(f"{path}: shard listed in {MANIFEST_NAME} is missing; {fix}")
    size = path.stat().st_size
    if size != entry.size_bytes:
        raise CrchflError(
            f"{path}: shard is truncated or altered ({size} bytes, manifest says {entry.size_bytes}); {fix}"
        )
    if sha256_file(path) != entry.sha256:
        raise CrchflError(f"{path}: shard is corrupt (sha256 differs from {MANIFEST_NAME}); {fix}")
    return path


def read_shard(root: Path, entry: ShardEntry, verify: bool = True, images: bool = True) -> ShardData:
    """Read one shard (checked against the manifest first unless ``verify`` is False).

    ``images=False`` skips the image array (returned with zero samples' worth
    of pixels: shape [N, 4, 0, 0, 3]) for statistics that need only labels.
    """
    path = verify_shard(root, entry) if verify else Path(root) / entry.file
    try:
        with h5py.File(path, "r") as f:
            missing = [name for name in LABEL_DATASETS if name not in f]
            if missing:
                raise CrchflError(
                    f"{path}: shard has no {', '.join(missing)} (written by an older version of crchfl-sumo); "
                    "regenerate the data set into a new folder with `crchfl-sumo dataset`"
                )
            if images:
                pixels = f["images"][()]
            else:
                pixels = np.zeros((entry.samples, len(CAMERA_NAMES), 0, 0, 3), np.uint8)
            data = ShardData(images=pixels, **{name: f[name][()] for name in LABEL_DATASETS})
    except (OSError, KeyError, ValueError) as exc:
        raise CrchflError(f"{path}: unreadable shard ({exc}); delete it and rerun `crchfl-sumo dataset`") from None
    if len(data) != entry.samples:
        raise CrchflError(f"{path}: {len(data)} samples, manifest says {entry.samples}; delete it and regenerate")
    return data


# ---------------------------------------------------------------- manifest


def read_manifest(root: Path) -> Manifest:
    """The manifest of the data set in ``root``; CrchflError if there is none."""
    path = Path(root) / MANIFEST_NAME
    if not path.is_file():
        raise CrchflError(f"{path}: no data set manifest; generate one with `crchfl-sumo dataset SCENARIO --out {root}`")
    return Manifest.from_json(path.read_text(encoding="utf-8"), str(path))


def write_manifest(root: Path, manifest: Manifest) -> None:
    atomic_write_text(Path(root) / MANIFEST_NAME, manifest.to_json())


class DatasetWriter:
    """Fills a data set folder shard by shard, resuming an earlier, interrupted run.

    A folder that already holds a manifest with the same header (scenario,
    seed, cameras, labels, image size, compression) is resumed: shards whose
    file still matches its checksum count as done and are kept; the rest are
    dropped from the manifest and written again. A different header is an
    error, so two data sets never mix in one folder.
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
                raise CrchflError(
                    f"{self.root / MANIFEST_NAME}: this folder holds a data set made with other settings "
                    f"(scenario {old.scenario!r}, seed {old.seed}); choose another --out folder or delete this one"
                )
            for entry in old.shards:
                try:
                    verify_shard(self.root, entry)
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
        if not file.endswith(".h5") or "/" in file or file.startswith("."):
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
