"""The data set's manifest (DIR/manifest.json): its header and one entry per finished shard.

The header holds what two runs must share to fill one folder (scenario, seed,
sample period, image size, the camera and world settings, the label schema,
compression); each entry names one finished shard of data/shards.py with its
size and sha256. The manifest is checked where it is read (UTF-8, size, types,
plain shard names inside the folder) and written atomically.
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.config import MAX_DEPTH, from_mapping, nesting_depth, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import ExpertConfig, expert_from_labels
from crchfl_sumo.data.labels import ACTION_NAMES, COMMAND_NAMES, SIGNAL_NAMES, STEER_CLASS_VALUES
from crchfl_sumo.data.recovery import PERTURBATION_NAMES
from crchfl_sumo.data.settings import MAX_SAMPLE_PERIOD_S
from crchfl_sumo.vision.camera import CAMERA_NAMES, MAX_HEIGHT_PX, MAX_WIDTH_PX
from crchfl_sumo.vision.raster import camera_settings

MANIFEST_NAME = "manifest.json"
FORMAT_NAME = "crchfl-sumo-dataset"
# 2: command, speed_mps, perturbation; 3: target_speed_mps; 4: forward_m; 5: signal_*, yield_gap_m; 6: the commands
# change_left and change_right (codes 4 and 5; older data sets hold codes 0..3, which mean what they meant)
FORMAT_VERSION = 6
READ_VERSIONS = (4, 5, 6)  # a format-4 data set loads: its samples' signal is "unknown"
NOMINAL_SAMPLE_BYTES = 1800 * 1024  # the paper's charge per sample: four PNGs of ~450 KB (FACTS.md)
SPLITS = ("train", "test")
MAX_MANIFEST_BYTES = 64 * 1024 * 1024


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
        "signal_state": list(SIGNAL_NAMES),
    }


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

    def town_vehicles(self, towns: Sequence[str] | None, where: str, split: str = "train") -> list[str] | None:
        """The vehicles of ``towns``' shards in ``split``, in manifest order (None: every town, no selection):
        what `train --train-towns` and `dagger --train-towns` train on. ``where`` names the data set."""
        if towns is None:
            return None
        shards = self.select(split)
        held = sorted({s.town for s in shards})
        unknown = sorted(set(towns) - set(held))
        if unknown or not towns:
            raise CrchflError(
                f"{where}: --train-towns {','.join(towns)}: no {split} shard of {', '.join(unknown) or 'any town'}; "
                f"its {split} shards are of {', '.join(held)}"
            )
        return [s.vehicle for s in shards if s.town in towns]

    @property
    def samples(self) -> int:
        return sum(s.samples for s in self.shards)

    @property
    def speed_horizon_s(self) -> float:
        """The horizon of the samples' target speeds (labels.expert.speed_horizon_s)."""
        return float(self.labels.get("expert", {}).get("speed_horizon_s", ExpertConfig().speed_horizon_s))

    def expert(self, where: str) -> ExpertConfig:
        """The expert settings the labels were made with (labels.expert; read from ``where``)."""
        return expert_from_labels(self.labels.get("expert", {}), f"{where}: labels.expert")

    def drive_settings(self, where: str) -> dict[str, Any]:
        """What a model file keeps of its data set, so that a drive renders and steers as the data did:
        the raster and world settings ("camera") and the expert's ("expert", with its steering rack)."""
        return dict(zip(DRIVE_SETTINGS, (self.camera, to_mapping(self.expert(where)))))

    def check_model(self, model_config, where: str) -> None:
        """Refuse a model (a learning.settings.ModelConfig) these labels cannot train: another target-speed horizon."""
        if model_config.longitudinal == "target_speed":
            self.check_horizon(model_config.speed_horizon_s, where)

    def check_camera(self, model_camera: dict | None, where: str, model_where: str) -> None:
        """Refuse fine-tuning a model on images drawn otherwise than its own data set's: ``model_camera`` is its
        checkpoint's copy of that manifest's camera block (not checked where either holds none)."""
        if not model_camera or not self.camera:
            return
        ours = camera_settings(self.camera, f"{where}: camera")
        theirs = camera_settings(model_camera, f"{model_where}: extra.camera")
        if ours != theirs:
            mine, its = to_mapping(ours[0]), to_mapping(theirs[0])
            differ = [f"raster.{k} {mine[k]!r} against {its.get(k)!r}" for k in mine if mine[k] != its.get(k)]
            differ += ["the world settings"] if ours[1] != theirs[1] else []
            raise CrchflError(
                f"{where}: its images are drawn otherwise than those of the data set {model_where} trained on "
                f"({'; '.join(differ)}); give that data set, or draw one with its settings (`crchfl-sumo dataset "
                "--config` with a [raster] table)"
            )

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
        """The manifest in ``text`` (read from ``where``), checked: types, image size, plain shard names."""
        fix = "delete the folder and generate it again"
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CrchflError(f"{where}: not valid JSON ({exc}); {fix}") from None
        except RecursionError:
            raise CrchflError(f"{where}: nested too deeply to be a data set manifest; {fix}") from None
        if nesting_depth(data) > MAX_DEPTH:  # the limit configs have (core.config), before anything walks it
            raise CrchflError(f"{where}: nested too deeply to be a data set manifest; {fix}")
        if not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
            raise CrchflError(f"{where}: not a crchfl-sumo data set manifest")
        if data.get("version") not in READ_VERSIONS:
            raise CrchflError(
                f"{where}: format version {data.get('version')}, this code reads "
                f"{', '.join(map(str, READ_VERSIONS))}; regenerate the data set"
            )
        known = {f.name for f in dataclasses.fields(Manifest)}
        missing = sorted(known - set(data))
        if missing:
            raise CrchflError(f"{where}: malformed manifest (no {', '.join(missing)}); regenerate the data set")
        manifest = from_mapping(Manifest, {k: v for k, v in data.items() if k in known}, f"{where}: manifest")
        _check_manifest(manifest, where)
        return manifest


# The keys of Manifest.drive_settings, as a model file's extra holds them.
DRIVE_SETTINGS = ("camera", "expert")

SHA256_HEX = re.compile(r"[0-9a-f]{64}")


def _check_manifest(manifest: Manifest, where: str) -> None:
    """Refuse what from_mapping's types let through: a bad image size, a shard outside the folder, bad counts."""
    fix = "regenerate the data set"
    if not (8 <= manifest.image_height <= MAX_HEIGHT_PX and 8 <= manifest.image_width <= MAX_WIDTH_PX):
        raise CrchflError(
            f"{where}: image size {manifest.image_height} x {manifest.image_width} lies outside 8 x 8 .. "
            f"{MAX_HEIGHT_PX} x {MAX_WIDTH_PX} pixels; {fix}"
        )
    if not 0 < manifest.sample_period_s <= MAX_SAMPLE_PERIOD_S:
        raise CrchflError(
            f"{where}: sample_period_s is {manifest.sample_period_s}, not a time in "
            f"(0, {MAX_SAMPLE_PERIOD_S:g}] s; {fix}"
        )
    for key in ("camera", "labels"):
        if not isinstance(getattr(manifest, key), dict):
            raise CrchflError(f"{where}: {key} must be a table, got {type(getattr(manifest, key)).__name__}; {fix}")
    if manifest.camera:  # the raster and world settings the images were drawn with (a run and a drive read them)
        camera_settings(manifest.camera, f"{where}: camera")
    try:  # the expert's settings the labels were made with (target-speed horizon, stop speed, rack)
        manifest.expert(where)
    except CrchflError as exc:
        raise CrchflError(f"{exc}; {fix}") from None
    files = [entry.file for entry in manifest.shards]
    if len(set(files)) != len(files):
        raise CrchflError(f"{where}: a shard file is listed twice; {fix}")
    for entry in manifest.shards:
        if not is_plain_shard_name(entry.file):
            raise CrchflError(
                f"{where}: shard file {entry.file!r} is not a plain '<name>.h5' inside the data set folder; {fix}"
            )
        if entry.split not in SPLITS:
            raise CrchflError(f"{where}: shard {entry.file} has split {entry.split!r}, not one of {', '.join(SPLITS)}")
        if (
            entry.samples < 0 or entry.size_bytes < 0 or not SHA256_HEX.fullmatch(entry.sha256)
            or not 0 <= entry.png_bytes_per_sample < float("inf")
        ):
            raise CrchflError(
                f"{where}: shard {entry.file} needs samples >= 0, size_bytes >= 0, png_bytes_per_sample >= 0 "
                f"and a sha256 of 64 hex digits; {fix}"
            )


def is_plain_shard_name(file: str) -> bool:
    """True for a file name that stays in its data set folder: '<name>.h5', no folder part, not hidden."""
    return (
        file.endswith(".h5") and len(file) > 3 and not file.startswith(".")
        and "/" not in file and "\\" not in file and "\0" not in file
    )


def _jsonable(value: Any) -> Any:
    """Round trip through JSON so that tuples/lists and ints/floats compare alike."""
    return json.loads(json.dumps(value))


def read_manifest(root: Path) -> Manifest:
    """The manifest of the data set in ``root``; CrchflError if there is none or it is not one."""
    path = Path(root) / MANIFEST_NAME
    if not path.is_file():
        raise CrchflError(f"{path}: no data set manifest; generate one with `crchfl-sumo dataset SCENARIO --out {root}`")
    fix = "delete the folder and generate it again"
    try:
        if path.stat().st_size > MAX_MANIFEST_BYTES:
            raise CrchflError(f"{path}: over {MAX_MANIFEST_BYTES // 2**20} MiB, too big to be a data set manifest; {fix}")
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise CrchflError(f"{path}: not UTF-8 text (byte {exc.start}); {fix}") from None
    except OSError as exc:
        raise CrchflError(f"{path}: cannot be read ({exc.strerror}); check its permissions") from None
    return Manifest.from_json(text, str(path))


def write_manifest(root: Path, manifest: Manifest) -> None:
    atomic_write_text(Path(root) / MANIFEST_NAME, manifest.to_json())
