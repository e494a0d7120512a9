"""Helpers shared by the test modules: tiny data sets, run configs, kill hooks, SUMO statistics, hand-made networks."""

from __future__ import annotations

import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from crchfl_sumo.data.labels import SIGNAL_GREEN, SIGNAL_RED
from crchfl_sumo.data.manifest import Manifest
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.data.shards import DatasetWriter, ShardData
from crchfl_sumo.sumo.installation import sumo_binary

PAPER_VEHICLES = [
    ("t01_data_0", "town01", "edge01"),
    ("t01_data_1", "town01", "edge01"),
    ("t02_data_0", "town02", "edge02"),
    ("t02_data_1", "town02", "edge02"),
    ("t02_data_2", "town02", "edge02"),
]


def write_dataset(root: Path, vehicles, samples=(2, 3, 2, 2, 1), test_samples=4, seed=0, commands=4,
                  signals=False) -> Path:
    """A tiny data set of random 48 x 64 samples, one train shard per vehicle and one test shard; route commands
    drawn from 0 .. ``commands`` - 1 (6: the lane changes too); ``signals``: random red or green next signals
    0 to 60 m ahead (else unknown, as in data sets before format 5)."""
    rng = np.random.default_rng(seed)
    header = Manifest(scenario="paper", seed=0, sample_period_s=0.25, image_height=48, image_width=64, compression="none")
    writer = DatasetWriter(root, header)

    def data(n):
        zeros = np.zeros(n)
        return ShardData(
            rng.integers(0, 256, (n, 4, 48, 64, 3), dtype=np.uint8),
            rng.random((n, 3), dtype=np.float32),
            rng.integers(0, 7, n),
            rng.integers(0, commands, n),
            rng.uniform(0, 14, n).astype(np.float32),
            rng.uniform(0, 14, n).astype(np.float32),
            np.zeros((n, 3), np.float32),
            np.arange(n) * 0.25,
            zeros,
            zeros,
            zeros,
            signal_state=rng.choice([SIGNAL_RED, SIGNAL_GREEN], n).astype(np.int8) if signals else None,
            signal_distance_m=rng.uniform(0, 60, n).astype(np.float32) if signals else None,
        )

    for i, ((vehicle, town, edge), n) in enumerate(zip(vehicles, samples)):
        writer.add(f"{town}-train-{i}.h5", data(n), vehicle=vehicle, town=town, edge=edge, split="train")
    writer.add("town01-test-0.h5", data(test_samples), vehicle="t01_test_0", town="town01", edge="edge01", split="test")
    return root


def run_config(dataset: Path, **federation) -> dict:
    return {
        "dataset": str(dataset),
        "federation": {"scheme": "hfl", "edge_interval": 1, "cloud_rounds": 2, **federation},
        "ledger": {"nominal_model_mb": 10.0},
        "model": {"image_height": 48, "image_width": 64},
        "train": {"device": "cpu", "deterministic": True},
        "clock": {"kind": "constant"},
    }


class SumTrainer:
    """Cheap stand-in for TorchTrainer: the loop and its files do not depend on what learning does."""

    def initial_state(self):
        import torch

        return {"w": torch.zeros(3, dtype=torch.float64)}

    def train(self, states, samples, epochs, seed, needed=None):
        return [{"w": s["w"] + epochs * len(x) + (seed % 7)} for s, x in zip(states, samples)]

    def evaluate(self, state):
        total = float(state["w"].sum())
        return {"loss": 100.0 / (1.0 + total), "accuracy": total / (1.0 + total)}


class Killed(Exception):
    pass


def kill_after(steps: int):
    """Raise right after the checkpoint of step number ``steps`` (1 = the first step) was written."""

    def hook(state):
        if state.steps == steps:
            raise Killed

    return hook


def result_files(out: Path) -> dict[str, str]:
    return {name: (out / name).read_text() for name in ("metrics.jsonl", "ledger.jsonl", "stragglers.jsonl", "summary.json")}


def half_hour_statistics(sumocfg: Path, tmp_path: Path) -> ET.Element:
    """SUMO's statistic output after 30 simulated minutes of ``sumocfg`` (collisions checked at junctions too)."""
    stats = tmp_path / "stats.xml"
    subprocess.run(
        [sumo_binary("sumo"), "-c", str(sumocfg), "--end", "1800",
         "--no-step-log", "true", "--collision.action", "warn", "--collision.check-junctions", "true",
         "--statistic-output", str(stats)],
        check=True, capture_output=True,
    )
    return ET.parse(stats).getroot()


def random_samples(n: int, seed: int):
    """n Samples of random images and labels at 48 x 64 (what a trainer's tests need, not a drive)."""
    rng = np.random.default_rng(seed)
    return Samples.from_numpy(
        rng.integers(0, 256, size=(n, 4, 48, 64, 3), dtype=np.uint8),
        rng.random((n, 3), dtype=np.float32),
        rng.integers(0, 7, size=n),
        rng.integers(0, 4, size=n),
        rng.uniform(0, 14, size=n),
        rng.uniform(0, 14, size=n),
    )


def netconvert(nodes: Path, edges: Path, out: Path, *extra: str) -> None:
    """netconvert a hand-written network as the towns are built: no U-turns, coordinates as written."""
    subprocess.run(
        [sumo_binary("netconvert"), "-n", str(nodes), "-e", str(edges), *extra,
         "--no-turnarounds=true", "--offset.disable-normalization=true", "-o", str(out)],
        check=True, capture_output=True,
    )


def fork_network(folder: Path, approach_lanes: int = 1) -> Path:
    """A hand-made fork: Z -> A (``approach_lanes`` lanes, 100 m), A -> B (two lanes, 200 m), then B -> C left
    (from AB's left lane only) or B -> D straight on (from its right lane only); lanes 3.2 m wide. Each lane of
    ZA continues on the lane of AB of its index. Returns the .net.xml path."""
    (folder / "f.nod.xml").write_text(
        '<nodes><node id="Z" x="-100" y="0"/><node id="A" x="0" y="0"/><node id="B" x="200" y="0"/>'
        '<node id="C" x="200" y="200"/><node id="D" x="400" y="0"/></nodes>'
    )
    (folder / "f.edg.xml").write_text(
        f'<edges><edge id="ZA" from="Z" to="A" numLanes="{approach_lanes}" speed="13.89" width="3.2"/>'
        '<edge id="AB" from="A" to="B" numLanes="2" speed="13.89" width="3.2"/>'
        '<edge id="BC" from="B" to="C" numLanes="1" speed="13.89" width="3.2"/>'
        '<edge id="BD" from="B" to="D" numLanes="1" speed="13.89" width="3.2"/></edges>'
    )
    straight_on = "".join(f'<connection from="ZA" to="AB" fromLane="{i}" toLane="{i}"/>' for i in range(approach_lanes))
    (folder / "f.con.xml").write_text(
        f'<connections>{straight_on}<connection from="AB" to="BC" fromLane="1" toLane="0"/>'
        '<connection from="AB" to="BD" fromLane="0" toLane="0"/></connections>'
    )
    netconvert(folder / "f.nod.xml", folder / "f.edg.xml", folder / "f.net.xml", "--connection-files",
               str(folder / "f.con.xml"))
    return folder / "f.net.xml"


def one_car_scenario(net: Path, edges: str, step_s: float = 0.25, **vehicle: str) -> Path:
    """A .sumocfg beside ``net`` (NAME.net.xml -> NAME.sumocfg, NAME.rou.xml) with one car "ego" (4.5 m, sigma 0)
    departing at 0 s at its top speed along ``edges``; ``vehicle``: more of its attributes (departLane="0")."""
    stem = net.name.removesuffix(".net.xml")
    extra = "".join(f' {key}="{value}"' for key, value in vehicle.items())
    (net.parent / f"{stem}.rou.xml").write_text(
        f'<routes><vType id="car" length="4.5" sigma="0"/><vehicle id="ego" type="car" depart="0"{extra} '
        f'departSpeed="max"><route edges="{edges}"/></vehicle></routes>'
    )
    (net.parent / f"{stem}.sumocfg").write_text(
        f'<configuration><input><net-file value="{net.name}"/><route-files value="{stem}.rou.xml"/></input>'
        f'<time><step-length value="{step_s:g}"/></time></configuration>'
    )
    return net.parent / f"{stem}.sumocfg"
