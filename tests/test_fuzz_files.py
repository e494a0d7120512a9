"""Seeded fuzzing of the files a user hands in: data sets, model checkpoints, a run's checkpoint and logs.

Every generated bad input must end in a CrchflError whose one-line message
names the file (exit 2 through ``cli.main``) or be read successfully; any
other exception is a failure. Each family builds one small valid original
per module and mutates copies of it: truncated and bit-flipped files, shards
with wrong dtypes, shapes, links, ranges or NaN under a matching checksum,
manifests that are not UTF-8, nest deeply or point outside their folder,
checkpoint payloads with missing or wrong keys, NaN or huge weights, huge
image sizes, pickles that would run code. Where a command reads the file
cheaply (dataset-stats, run --resume) some cases go through ``cli.main``;
the rest call the loading functions the commands use.
"""

from __future__ import annotations

import json
import os
import shutil
import traceback
from pathlib import Path
from typing import Callable

import h5py
import numpy as np
import pytest
import torch

from crchfl_sumo.cli import main
from crchfl_sumo.core.config import from_mapping, to_mapping, toml_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.dataset import ShardDataset, load_samples, load_vehicle_samples
from crchfl_sumo.data.manifest import MANIFEST_NAME, Manifest
from crchfl_sumo.data.shards import LABEL_DATASETS, LABEL_SHAPES, DatasetWriter, ShardData, sha256_file
from crchfl_sumo.data.stats import dataset_stats, write_mosaic
from crchfl_sumo.federation.run import PREVIOUS_STATE_FILE, STATE_FILE, run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.federation.run_data import read_inputs
from crchfl_sumo.learning.checkpoint import CHECKPOINT_FORMAT, load_model, save_checkpoint
from crchfl_sumo.learning.model import build_model
from crchfl_sumo.learning.settings import ModelConfig

from helpers import PAPER_VEHICLES, Killed, SumTrainer, kill_after, result_files, run_config, write_dataset

SEED = 18
H, W = 48, 64
CASES = {"shard bytes": 120, "shard content": 130, "manifest": 110, "model file": 150, "run files": 50, "run cli": 6}


class Outcomes:
    """Each case's end: read, refused with a good message, or a failure (anything else)."""

    def __init__(self) -> None:
        self.read = self.refused = 0
        self.failures: list[str] = []

    def check(self, case: str, names: Path, action: Callable[[], object]) -> bool:
        """Run ``action``; True if it was refused (with a good message or not)."""
        try:
            action()
            self.read += 1
        except CrchflError as exc:
            message = str(exc)
            if str(names) not in message or "\n" in message or "\x1b" in message or "weights_only" in message:
                self.failures.append(f"{case}: message does not name {names} in one line: {message!r}")
            self.refused += 1
            return True
        except Exception:  # anything else escapes as a traceback from the command
            self.failures.append(f"{case}: {traceback.format_exc(limit=-3)}")
        return False

    def check_cli(self, case: str, names: Path, argv: list[str], capsys) -> int:
        capsys.readouterr()
        try:
            code = main(argv)
        except Exception:
            self.failures.append(f"{case}: {traceback.format_exc(limit=-3)}")
            return -1
        err = capsys.readouterr().err.strip()
        if code == 0:
            self.read += 1
        elif code == 2 and str(names) in err and "\n" not in err and err.startswith("crchfl-sumo: error: "):
            self.refused += 1
        else:
            self.failures.append(f"{case}: exit {code}, stderr {err!r}")
        return code

    def assert_clean(self, cases: int, some_refused: bool = True) -> None:
        assert self.read + self.refused + len(self.failures) >= cases
        assert not self.failures, f"{len(self.failures)} of {cases} cases ended badly:\n" + "\n".join(self.failures[:10])
        assert self.refused > 0 or not some_refused  # the family does reach the checks


def flip_bits(data: bytes, rng: np.random.Generator, limit: int | None = None) -> bytes:
    raw = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        raw[int(rng.integers(0, min(len(raw), limit or len(raw))))] ^= 1 << int(rng.integers(0, 8))
    return bytes(raw)


# ---------------------------------------------------------------- data sets


def shard_data(n: int, rng: np.random.Generator) -> ShardData:
    zeros = np.zeros(n)
    return ShardData(
        rng.integers(0, 256, (n, 4, H, W, 3), dtype=np.uint8) // 64 * 64,  # a few levels: lzf compresses a little
        np.stack([rng.random(n), rng.uniform(-1, 1, n), rng.random(n)], axis=1).astype(np.float32),
        rng.integers(0, 7, n),
        rng.integers(0, 4, n),
        rng.uniform(0, 14, n).astype(np.float32),
        rng.uniform(0, 14, n).astype(np.float32),
        np.zeros((n, 3), np.float32),
        np.arange(n) * 0.25,
        zeros,
        zeros,
        zeros,
    )


@pytest.fixture(scope="module")
def original_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fuzz") / "data"
    rng = np.random.default_rng(SEED)
    header = Manifest(scenario="paper", seed=0, sample_period_s=0.25, image_height=H, image_width=W, compression="lzf")
    writer = DatasetWriter(root, header)
    writer.add("a-train-0.h5", shard_data(4, rng), vehicle="v0", town="town01", edge="e0", split="train")
    writer.add("a-train-1.h5", shard_data(3, rng), vehicle="v1", town="town01", edge="e0", split="train")
    writer.add("a-test-0.h5", shard_data(2, rng), vehicle="t0", town="town01", edge="e0", split="test")
    return root


def fresh_copy(original: Path, folder: Path) -> Path:
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(original, folder, symlinks=True)
    return folder


def reseal(root: Path, file: str, **changes) -> None:
    """The manifest entry of ``file`` made to match the file again: the checksum passes, the content is wrong."""
    raw = json.loads((root / MANIFEST_NAME).read_text())
    for entry in raw["shards"]:
        if entry["file"] == file:
            entry.update({"size_bytes": (root / file).stat().st_size, "sha256": sha256_file(root / file), **changes})
    (root / MANIFEST_NAME).write_text(json.dumps(raw))


SHARDS = ("a-train-0.h5", "a-train-1.h5", "a-test-0.h5")


def read_dataset(root: Path, rng: np.random.Generator, out: Path, outcomes: Outcomes, case: str, capsys) -> None:
    """One of the ways the commands read a data set, picked by ``rng``."""
    way = int(rng.integers(0, 6))
    if rng.random() < 1 / 20:  # the command (its figure costs about a second when the data set reads)
        outcomes.check_cli(case, root, ["dataset-stats", str(root), "--out", str(out)], capsys)
        return

    def torch_dataset(root):
        dataset = ShardDataset(root)
        try:
            for i in range(len(dataset)):
                dataset[i]
        finally:
            dataset.close()

    readers = (load_samples, dataset_stats, load_vehicle_samples, torch_dataset,
               lambda r: write_mosaic(r, out / "mosaic.png"), lambda r: load_samples(r, "test"))
    outcomes.check(case, root, lambda: readers[way](root))


def test_fuzz_shard_bytes(original_dataset, tmp_path, capsys):
    """Truncated and bit-flipped shards, the manifest resealed to match them or not."""
    rng = np.random.default_rng([SEED, 1])
    outcomes = Outcomes()
    for case in range(CASES["shard bytes"]):
        root = fresh_copy(original_dataset, tmp_path / "data")
        file = SHARDS[int(rng.integers(0, len(SHARDS)))]
        data = (root / file).read_bytes()
        if rng.random() < 0.3:
            damaged = data[: int(rng.integers(0, len(data)))]
            what = f"truncated {file} to {len(damaged)} bytes"
        else:
            damaged = flip_bits(data, rng, 4096 if rng.random() < 0.5 else None)  # the metadata is at the start
            what = f"flipped bits in {file}"
        (root / file).write_bytes(damaged)
        resealed = rng.random() < 0.8
        if resealed:
            reseal(root, file)
        read_dataset(root, rng, tmp_path / f"out{case}", outcomes, f"case {case} ({what}, resealed {resealed})", capsys)
    outcomes.assert_clean(CASES["shard bytes"])


def content_mutation(f: h5py.File, name: str, rng: np.random.Generator, outside: Path) -> str:
    """Replace dataset ``name`` of an open shard by something the schema must refuse (or, rarely, accept)."""
    old = f[name][()]
    kind = ["dtype", "shape", "nan", "range", "delete", "group", "soft link", "external link", "scalar"][
        int(rng.integers(0, 9))
    ]
    del f[name]
    if kind == "dtype":
        dtype = [np.int8, np.int32, np.float16, np.float64, np.uint16, np.bool_, np.float32, np.int64][int(rng.integers(0, 8))]
        f.create_dataset(name, data=old.astype(dtype))
    elif kind == "shape":
        change = int(rng.integers(0, 4))
        new = (old[:-1], np.concatenate([old, old[:1]]), old[..., None], old.reshape(-1) if old.ndim > 1 else old[None])[change]
        f.create_dataset(name, data=new)
    elif kind == "nan" and old.dtype.kind == "f":
        new = old.copy()
        new.reshape(-1)[int(rng.integers(0, new.size))] = [np.nan, np.inf, -np.inf][int(rng.integers(0, 3))]
        f.create_dataset(name, data=new)
    elif kind == "range" or kind == "nan":
        new = old.copy()
        flat = new.reshape(-1)
        index = int(rng.integers(0, flat.size))
        if new.dtype.kind in "iu":
            limits = np.iinfo(new.dtype)
            flat[index] = np.clip([7, 99, -1, 4, 2**40, -(2**40)][int(rng.integers(0, 6))], limits.min, limits.max)
        else:
            flat[index] = [-0.5, 1.5, -2.0, 1e30, -1e30][int(rng.integers(0, 5))]
        f.create_dataset(name, data=new)
    elif kind == "group":
        f.create_group(name)
    elif kind == "soft link":
        f[name] = h5py.SoftLink("/" + [n for n in ("images", *LABEL_DATASETS) if n != name][0])
    elif kind == "external link":
        with h5py.File(outside, "w") as other:
            other.create_dataset(name, data=old)
        f[name] = h5py.ExternalLink(str(outside), name)
    elif kind == "scalar":
        f.create_dataset(name, data=np.float32(1.0))
    return f"{kind} of {name}"


def test_fuzz_shard_content(original_dataset, tmp_path, capsys):
    """Shards whose checksum matches but whose datasets are wrong: dtypes, shapes, NaN, ranges, links, huge shapes."""
    rng = np.random.default_rng([SEED, 2])
    outcomes = Outcomes()
    names = ("images", *LABEL_DATASETS)
    for case in range(CASES["shard content"]):
        root = fresh_copy(original_dataset, tmp_path / "data")
        file = SHARDS[int(rng.integers(0, len(SHARDS)))]
        changes = {}
        if rng.random() < 0.1:  # a shape that asks for far more memory than the file holds
            n = int(10 ** rng.uniform(5, 12))
            with h5py.File(root / file, "w") as f:
                f.create_dataset("images", shape=(n, 4, H, W, 3), dtype=np.uint8, chunks=(1, 4, H, W, 3),
                                 compression=["gzip", "lzf"][int(rng.integers(0, 2))])
                for name, dtype in LABEL_DATASETS.items():
                    f.create_dataset(name, shape=(n, *LABEL_SHAPES.get(name, ())), dtype=dtype)
            what, changes = f"declared {n} samples", {"samples": n}
        else:
            with h5py.File(root / file, "a") as f:
                what = content_mutation(f, names[int(rng.integers(0, len(names)))], rng, tmp_path / "outside.h5")
        reseal(root, file, **changes)
        read_dataset(root, rng, tmp_path / f"out{case}", outcomes, f"case {case} ({what} in {file})", capsys)
    outcomes.assert_clean(CASES["shard content"])


ODD_VALUES = (None, "x", "", [], {}, [1, 2], -1, 0, 10**30, 1.5, True, float("nan"), float("inf"), "../x")
ESCAPES = ("../outside.h5", "/tmp/outside.h5", "sub/a.h5", "..", "./a-train-0.h5", "a.h5\u0000", ".hidden.h5",
           "..\\outside.h5", "a-train-0.h5/")


def manifest_mutation(root: Path, rng: np.random.Generator, outside: Path) -> str:
    path = root / MANIFEST_NAME
    text = path.read_text()
    raw = json.loads(text)
    kind = int(rng.integers(0, 10))
    if kind == 9:  # a value nested in the header's tables
        table = ["camera", "labels"][int(rng.integers(0, 2))]
        key = ["expert", "raster", "world", "height_px", "steer_class_values"][int(rng.integers(0, 5))]
        value = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        raw[table][key] = {"speed_horizon_s": value, "stop_speed_mps": value} if rng.random() < 0.5 else value
        path.write_text(json.dumps(raw))
        return f"{table}.{key} = {raw[table][key]!r}"
    if kind == 0:
        data = bytearray(text.encode())
        at = int(rng.integers(0, len(data)))
        data[at:at] = bytes(rng.integers(128, 256, int(rng.integers(1, 4)), dtype=np.uint8))
        path.write_bytes(bytes(data))
        return f"non-UTF-8 bytes at {at}"
    if kind == 1:
        path.write_text(text[: int(rng.integers(0, len(text)))])
        return "truncated"
    if kind == 2:
        depth = int(10 ** rng.uniform(2, 6))
        opener, closer = [("[", "]"), ('{"a":', "}")][int(rng.integers(0, 2))]
        where = ["top", "camera", "shards"][int(rng.integers(0, 3))]
        nested = opener * depth + "1" + closer * depth
        if where == "top":
            path.write_text(nested)
        else:
            path.write_text(text.replace(f'"{where}": ', f'"{where}": {nested}, "x{where}": ', 1))
        return f"nested {depth} deep at {where}"
    if kind == 3:
        key = sorted(raw)[int(rng.integers(0, len(raw)))]
        del raw[key]
        what = f"no {key}"
    elif kind == 4:
        key = sorted(raw)[int(rng.integers(0, len(raw)))]
        raw[key] = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        what = f"{key} = {raw[key]!r}"
    elif kind in (5, 6):
        entry = raw["shards"][int(rng.integers(0, len(raw["shards"])))]
        key = sorted(entry)[int(rng.integers(0, len(entry)))]
        entry[key] = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        what = f"shard {key} = {entry[key]!r}"
    elif kind == 7:
        entry = raw["shards"][int(rng.integers(0, len(raw["shards"])))]
        escape = ESCAPES[int(rng.integers(0, len(ESCAPES)))]
        if escape == "../outside.h5":  # the same bytes outside the folder: size and sha256 match
            shutil.copy(root / entry["file"], root.parent / "outside.h5")
        entry["file"] = escape
        what = f"shard file {escape!r}"
    else:
        entry = raw["shards"][int(rng.integers(0, len(raw["shards"])))]
        shutil.copy(root / entry["file"], outside)
        (root / entry["file"]).unlink()
        (root / entry["file"]).symlink_to(outside)
        what = f"{entry['file']} a link out of the folder"
    path.write_text(json.dumps(raw))
    return what


def test_fuzz_manifest(original_dataset, tmp_path, capsys):
    """Manifests: not UTF-8, truncated, nested deep, keys missing or of odd types, shards outside the folder."""
    rng = np.random.default_rng([SEED, 3])
    outcomes = Outcomes()
    for case in range(CASES["manifest"]):
        root = fresh_copy(original_dataset, tmp_path / "cases" / "data")
        what = manifest_mutation(root, rng, tmp_path / "outside.h5")
        read_dataset(root, rng, tmp_path / f"out{case}", outcomes, f"case {case} ({what})", capsys)
    outcomes.assert_clean(CASES["manifest"])


# ---------------------------------------------------------------- model files

MODEL = ModelConfig(image_height=H, image_width=W)


class RunsCode:
    def __init__(self, call, argument):
        self.call, self.argument = call, argument

    def __reduce__(self):
        return (self.call, (self.argument,))


def model_payload_mutation(payload: dict, rng: np.random.Generator, marker: Path) -> str:
    kind = int(rng.integers(0, 9))
    weights = payload["state_dict"]
    name = sorted(weights)[int(rng.integers(0, len(weights)))]
    if kind == 8:  # the data set's camera block a drive renders with
        value = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        payload["extra"]["camera"] = [value, {"raster": value}, {"raster": {"camera": {"height_px": value}}},
                                      {"world": {"x": value}}][int(rng.integers(0, 4))]
        return f"extra.camera = {payload['extra']['camera']!r}"
    if kind == 0:
        key = ["format", "model_config", "state_dict", "extra"][int(rng.integers(0, 4))]
        if rng.random() < 0.5:
            del payload[key]
            return f"no {key}"
        payload[key] = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        return f"{key} = {payload[key]!r}"
    if kind == 1:
        keys = sorted(to_mapping(MODEL))
        key = keys[int(rng.integers(0, len(keys)))]
        payload["model_config"][key] = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        return f"model_config.{key} = {payload['model_config'][key]!r}"
    if kind == 2:
        height, width = [(4096, 8192), (1081, 64), (48, 1921), (10**9, 10**9), (48, 65), (64, 128)][int(rng.integers(0, 6))]
        payload["model_config"].update(image_height=height, image_width=width)
        return f"image size {height} x {width}"
    if kind == 3:
        tensor = weights[name].clone()
        tensor.reshape(-1)[int(rng.integers(0, tensor.numel()))] = [float("nan"), float("inf"), -float("inf"), 1e30,
                                                                    -1e30, 1e7][int(rng.integers(0, 6))]
        weights[name] = tensor
        return f"a bad value in {name}"
    if kind == 4:
        tensor = weights[name]
        new = [tensor.to_sparse(), tensor.to(torch.float64), tensor.to(torch.float16), tensor.to(torch.int64),
               tensor.reshape(-1)[:-1].clone(), tensor[None].clone(), torch.tensor(1.0)][int(rng.integers(0, 7))]
        weights[name] = new
        return f"{name} as {new.layout} {new.dtype} {list(new.shape)}"
    if kind == 5:
        if rng.random() < 0.5:
            del weights[name]
            return f"no {name}"
        weights[f"{name}.extra"] = torch.zeros(2)
        return f"an extra tensor beside {name}"
    if kind == 6:
        weights[name] = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        return f"{name} = {weights[name]!r}"
    call = [os.system, eval, exec][int(rng.integers(0, 3))]
    argument = f"touch {marker}" if call is os.system else f"open({str(marker)!r}, 'w').close()"
    where = ["model_config", "extra", "state_dict", "format"][int(rng.integers(0, 4))]
    if where == "format":
        payload["format"] = RunsCode(call, argument)
    else:
        payload[where]["x"] = RunsCode(call, argument)
    return f"a pickle calling {call.__name__} in {where}"


def test_fuzz_model_files(tmp_path, capsys):
    """Model checkpoints (what drive and drive-bench load): truncated, bit-flipped, or a payload gone wrong.

    A refused file goes through `crchfl-sumo drive-bench` too, about one in seven: the CLI loads the model before
    any episode (a file that loads would start a benchmark, too slow here)."""
    rng = np.random.default_rng([SEED, 4])
    weights = build_model(MODEL, seed=0).state_dict()
    original = tmp_path / "original.pt"
    save_checkpoint(original, MODEL, weights, {"epoch": 1})
    data = original.read_bytes()
    marker = tmp_path / "code-ran"
    outcomes = Outcomes()
    images, command, speed = torch.zeros(1, 4, H, W, 3, dtype=torch.uint8), torch.zeros(1, dtype=torch.int64), torch.zeros(1)

    def load_and_run(path: Path):
        model = load_model(path)
        with torch.no_grad():
            model(images, command, speed)

    for case in range(CASES["model file"]):
        path = tmp_path / f"m{case}.pt"
        if rng.random() < 0.35:
            if rng.random() < 0.4:
                path.write_bytes(data[: int(rng.integers(0, len(data)))])
                what = "truncated"
            else:
                path.write_bytes(flip_bits(data, rng))
                what = "bit-flipped"
        else:
            payload = {"format": CHECKPOINT_FORMAT, "model_config": to_mapping(MODEL), "state_dict": dict(weights),
                       "extra": {"epoch": 1}}
            what = model_payload_mutation(payload, rng, marker)
            torch.save(payload, path)
        refused = outcomes.check(f"case {case} ({what})", path, lambda: load_and_run(path))
        if refused and rng.random() < 0.15:
            outcomes.check_cli(f"case {case} ({what}) via drive-bench", path,
                               ["drive-bench", str(path), "--out", str(tmp_path / f"bench{case}")], capsys)
        assert not marker.exists(), f"case {case} ({what}) ran code from the file"
        path.unlink()
    outcomes.assert_clean(CASES["model file"])


# ---------------------------------------------------------------- a run's checkpoint and logs


@pytest.fixture(scope="module")
def killed_run(tmp_path_factory):
    """A run killed after its third checkpoint (federation_state.pt and federation_state.prev.pt there) and the whole run."""
    folder = tmp_path_factory.mktemp("fuzzrun")
    dataset = write_dataset(folder / "data", PAPER_VEHICLES)
    config = from_mapping(RunConfig, run_config(dataset, scheme="hfl", cloud_interval=2, cloud_rounds=2))
    inputs = read_inputs(config)
    run_federation_dir(config, inputs, folder / "whole", trainer=SumTrainer())
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, folder / "killed", trainer=SumTrainer(), after_checkpoint=kill_after(3))
    return config, inputs, folder


def run_files_mutation(out: Path, rng: np.random.Generator) -> tuple[str, bool]:
    """Damage one or two of the files a resume reads; also says whether the result must equal the whole run's."""
    kind = int(rng.integers(0, 6))
    name = [STATE_FILE, PREVIOUS_STATE_FILE][int(rng.integers(0, 2))] if kind < 4 else None
    if kind == 0:
        data = (out / name).read_bytes()
        (out / name).write_bytes(data[: int(rng.integers(0, len(data)))])
        return f"truncated {name}", True
    if kind == 1:
        (out / name).write_bytes(flip_bits((out / name).read_bytes(), rng))
        return f"bit-flipped {name}", False  # a flip in a tensor's bytes loads: the run goes on from other weights
    if kind == 2:
        for both in (STATE_FILE, PREVIOUS_STATE_FILE):
            (out / both).write_bytes(b"")
        return "both checkpoints empty", True
    if kind == 3:
        payload = torch.load(out / name, weights_only=True)
        part = ["state", "logs", "resolved"][int(rng.integers(0, 3))]
        keys = sorted(payload[part])
        key = keys[int(rng.integers(0, len(keys)))]
        payload[part][key] = ODD_VALUES[int(rng.integers(0, len(ODD_VALUES)))]
        torch.save(payload, out / name)
        return f"{name} {part}.{key} = {payload[part][key]!r}", False
    log = ["metrics.jsonl", "ledger.jsonl", "stragglers.jsonl"][int(rng.integers(0, 3))]
    data = (out / log).read_bytes()
    if kind == 4:
        (out / log).write_bytes(data[: int(rng.integers(0, len(data) + 1))])
        return f"truncated {log}", False
    at = int(rng.integers(0, len(data) + 1))
    (out / log).write_bytes(data[:at] + bytes(rng.integers(0, 256, 8, dtype=np.uint8)) + data[at:])
    return f"garbage in {log}", False


def test_fuzz_run_files(killed_run, tmp_path):
    """`run --resume` on damaged checkpoints and logs: refused with the file named, or resumed."""
    config, inputs, folder = killed_run
    rng = np.random.default_rng([SEED, 5])
    outcomes = Outcomes()
    whole = result_files(folder / "whole")
    for case in range(CASES["run files"]):
        out = fresh_copy(folder / "killed", tmp_path / "out")
        what, exact = run_files_mutation(out, rng)
        finished = {}

        def resume():
            finished["summary"] = run_federation_dir(config, inputs, out, trainer=SumTrainer(), resume=True)

        outcomes.check(f"case {case} ({what})", out, resume)
        if finished and exact:  # a detectably bad federation_state.pt: the previous one carried on to the same end
            assert result_files(out) == whole, f"case {case} ({what}) resumed to other results"
    outcomes.assert_clean(CASES["run files"])


def test_fuzz_run_resume_through_the_cli(tmp_path, capsys):
    """`crchfl-sumo run CONFIG --out DIR --resume` with the real trainer on damaged checkpoints: exit 0 or 2."""
    dataset = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    mapping = run_config(dataset, scheme="hfl", cloud_interval=1, cloud_rounds=2)
    path = tmp_path / "run.toml"
    path.write_text(toml_text(mapping))
    config = from_mapping(RunConfig, mapping)
    inputs = read_inputs(config)
    with pytest.raises(Killed):
        run_federation_dir(config, inputs, tmp_path / "killed", after_checkpoint=kill_after(2))
    rng = np.random.default_rng([SEED, 6])
    outcomes = Outcomes()
    for case in range(CASES["run cli"]):
        out = fresh_copy(tmp_path / "killed", tmp_path / f"out{case}")
        what, _ = run_files_mutation(out, rng)
        outcomes.check_cli(f"case {case} ({what})", out, ["run", str(path), "--out", str(out), "--resume"], capsys)
    outcomes.assert_clean(CASES["run cli"], some_refused=False)  # six cases may all resume


def test_the_fuzz_set_is_large_enough():
    assert sum(CASES.values()) >= 400
