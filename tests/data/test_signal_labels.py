"""The signal ahead in the data: SUMO's next signal, its stop line's distance and the yield gap, per sample,
from a hand-made approach to a red light through the shard and back; format-4 shards still load."""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from helpers import netconvert, one_car_scenario

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.dataset import load_samples
from crchfl_sumo.data.generation import red_line_distances, signal_columns
from crchfl_sumo.data.labels import (
    SIGNAL_GREEN, SIGNAL_GREEN_MINOR, SIGNAL_NAMES, SIGNAL_NONE, SIGNAL_OFF, SIGNAL_RED, SIGNAL_UNKNOWN, SIGNAL_YELLOW,
    signal_codes,
)
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.data.manifest import MANIFEST_NAME
from crchfl_sumo.data.shards import read_shard, sha256_file
from crchfl_sumo.learning.balance import epoch_batches, near_red, near_yield
from crchfl_sumo.sumo.scenario import load_scenario
from crchfl_sumo.sumo.simulation import Simulation, yield_gap_m

from test_shard_validation import make_dataset, shard_data  # this folder is on the path, as helpers is

RED_S = 40.0  # the light shows red this long, then green


@pytest.fixture(scope="module")
def red_light(tmp_path_factory) -> Path:
    """A 150 m approach to a light (red for RED_S, then green) and 150 m beyond; one car from the far end."""
    folder = tmp_path_factory.mktemp("red")
    (folder / "r.nod.xml").write_text(
        '<nodes><node id="A" x="0" y="0"/><node id="B" x="150" y="0" type="traffic_light"/>'
        '<node id="C" x="300" y="0"/></nodes>'
    )
    (folder / "r.edg.xml").write_text(
        '<edges><edge id="AB" from="A" to="B" numLanes="1" speed="13.89"/>'
        '<edge id="BC" from="B" to="C" numLanes="1" speed="13.89"/></edges>'
    )
    (folder / "r.tll.xml").write_text(
        f'<tlLogics><tlLogic id="B" type="static" programID="0" offset="0"><phase duration="{RED_S:g}" state="r"/>'
        '<phase duration="1000" state="G"/></tlLogic></tlLogics>'
    )
    netconvert(folder / "r.nod.xml", folder / "r.edg.xml", folder / "r.net.xml", "--tllogic-files",
               str(folder / "r.tll.xml"))
    return one_car_scenario(folder / "r.net.xml", "AB BC")


def test_the_signal_ahead_of_an_approach_to_red_then_green(red_light):
    import sumolib

    stop_line_m = sumolib.net.readNet(str(red_light.parent / "r.net.xml")).getLane("AB_0").getLength()
    with Simulation(load_scenario(red_light), seed=0, watch={"ego"}) as sim:
        frames = [f for f in sim.run(RED_S + 20.0) if "ego" in f.ids]
    columns = signal_columns(frames, "ego", np.zeros(len(frames)))
    rows = [f.index_of("ego") for f in frames]
    lane = np.array([f.lane_id[r] for f, r in zip(frames, rows)])
    front_m = np.array([f.lane_pos_m[r] for f, r in zip(frames, rows)])
    t_s = np.array([f.t_s for f in frames])
    on_approach = lane == "AB_0"
    red = on_approach & (t_s < RED_S)
    # red until RED_S, green after; the stop line's distance is what is left of the approach lane
    assert np.all(columns["signal_state"][red] == SIGNAL_RED)
    assert np.all(columns["signal_state"][on_approach & (t_s > RED_S)] == SIGNAL_GREEN)  # the frame at RED_S is before the switch
    assert np.allclose(columns["signal_distance_m"][on_approach], stop_line_m - front_m[on_approach], atol=1e-3)
    assert np.all(np.diff(columns["signal_distance_m"][on_approach]) <= 1e-4)  # never farther
    # the car stood at the line on red: within 2 m of it, standing
    speed = np.array([f.speed_mps[r] for f, r in zip(frames, rows)])
    standing = red & (speed < 0.1)
    assert standing.sum() * 0.25 > 10.0
    assert np.all(columns["signal_distance_m"][standing] < 2.0)
    # past the light there is none ahead
    beyond = lane == "BC_0"
    assert beyond.any() and np.all(columns["signal_state"][beyond] == SIGNAL_NONE)
    assert np.all(np.isinf(columns["signal_distance_m"][beyond]))
    assert np.all(np.isinf(columns["yield_gap_m"]))  # no other vehicle, no foe
    # a sample drawn 3 m ahead of its track is 3 m nearer the line, and never past it
    shifted = signal_columns(frames, "ego", np.full(len(frames), 3.0))
    assert np.allclose(shifted["signal_distance_m"][on_approach],
                       np.maximum(columns["signal_distance_m"][on_approach] - 3.0, 0.0))
    # a red-line sample drawn 4 m back is 4 m farther; red_line_distances gives the red ones' lines only
    backed = signal_columns(frames, "ego", np.full(len(frames), -4.0))
    assert np.allclose(backed["signal_distance_m"][on_approach], columns["signal_distance_m"][on_approach] + 4.0)
    lines = red_line_distances(frames, "ego")
    shows_red = columns["signal_state"] == SIGNAL_RED  # the frame at RED_S too
    assert np.allclose(lines[shows_red], columns["signal_distance_m"][shows_red]) and np.isinf(lines[~shows_red]).all()


def test_signal_codes_and_the_yield_gap_by_hand():
    assert signal_codes(["r", "u", "s", "y", "Y", "G", "g", "o", "O", "", "?"]).tolist() == [
        SIGNAL_RED, SIGNAL_RED, SIGNAL_RED, SIGNAL_YELLOW, SIGNAL_YELLOW, SIGNAL_GREEN, SIGNAL_GREEN_MINOR,
        SIGNAL_OFF, SIGNAL_OFF, SIGNAL_NONE, SIGNAL_OFF,
    ]
    # (foe, ego dist, foe dist, ego exit, foe exit, ego lane, foe lane, ego must respond, foe must respond)
    foes = [
        ("a", 10.0, 25.0, 14.0, 29.0, "l", "m", True, False),  # yield to it: 25 m from the conflict
        ("b", 10.0, 8.0, 14.0, 12.0, "l", "m", False, True),  # it yields to us: not a gap we must respect
        ("c", 10.0, -6.0, 14.0, -2.0, "l", "m", True, False),  # already through the conflict
        ("d", 10.0, 40.0, 14.0, 44.0, "l", "m", True, False),
    ]
    assert yield_gap_m(foes) == 25.0
    assert yield_gap_m(foes[1:3]) == math.inf and yield_gap_m([]) == math.inf


def test_signal_columns_round_trip_through_a_shard_and_old_shards_read_as_unknown(tmp_path):
    data = shard_data(4)
    import dataclasses

    data = dataclasses.replace(
        data, signal_state=np.array([SIGNAL_RED, SIGNAL_GREEN, SIGNAL_NONE, SIGNAL_YELLOW], np.int8),
        signal_distance_m=np.array([12.5, 3.0, np.inf, 0.0], np.float32),
        yield_gap_m=np.array([np.inf, 7.0, np.inf, -1.5], np.float32),
    )
    root = make_dataset(tmp_path / "d", n=1)
    from crchfl_sumo.data.manifest import read_manifest
    from crchfl_sumo.data.shards import DatasetWriter

    writer = DatasetWriter(root, read_manifest(root))
    writer.add("a.h5", data, vehicle="v0", town="town01", edge="e0", split="train")
    entry = read_manifest(root).entry("a.h5")
    back = read_shard(root, entry)
    assert back.signal_state.tolist() == data.signal_state.tolist()
    assert back.signal_distance_m.tolist() == data.signal_distance_m.tolist()
    assert back.yield_gap_m.tolist() == data.yield_gap_m.tolist()
    samples = load_samples(root, "train")
    assert samples.signal_state.tolist() == [SIGNAL_RED, SIGNAL_GREEN, SIGNAL_NONE, SIGNAL_YELLOW]
    assert near_red(samples, 30.0).tolist() == [True, False, False, True]
    assert near_red(samples, 10.0).tolist() == [False, False, False, True]
    # the yield gap loads too: a foe 7 m from the conflict point, one in it (-1.5 m), none
    assert samples.yield_gap_m.tolist() == [math.inf, 7.0, math.inf, -1.5]
    assert near_yield(samples, 30.0).tolist() == [False, True, False, True]
    assert near_yield(samples, 5.0).tolist() == [False, False, False, True]
    assert samples.subset([1, 3]).yield_gap_m.tolist() == [7.0, -1.5]

    # A format-4 data set: no signal datasets, version 4 in its manifest. It loads, its signal unknown.
    with h5py.File(root / "a.h5", "a") as f:
        for name in ("signal_state", "signal_distance_m", "yield_gap_m"):
            del f[name]
    raw = json.loads((root / MANIFEST_NAME).read_text())
    raw["version"] = 4
    raw["labels"].pop("signal_state")
    for shard in raw["shards"]:
        if shard["file"] == "a.h5":
            shard["size_bytes"], shard["sha256"] = (root / "a.h5").stat().st_size, sha256_file(root / "a.h5")
    (root / MANIFEST_NAME).write_text(json.dumps(raw))
    old = load_samples(root, "train")
    assert old.signal_state.tolist() == [SIGNAL_UNKNOWN] * 4
    assert torch.isinf(old.signal_distance_m).all() and not near_red(old, 30.0).any()
    assert torch.isinf(old.yield_gap_m).all() and not near_yield(old, 30.0).any()
    # ... and a data set of a format this code does not know is refused by name
    raw["version"] = 3
    (root / MANIFEST_NAME).write_text(json.dumps(raw))
    with pytest.raises(CrchflError, match="format version 3, this code reads 4, 5, 6; regenerate"):
        load_samples(root, "train")


def test_bad_signal_values_in_a_shard_are_refused_by_name(tmp_path):
    root = make_dataset(tmp_path / "d", n=2)
    for name, value, message in (
        ("signal_state", len(SIGNAL_NAMES), "signal_state holds 7; signal codes are 0..6"),
        ("signal_distance_m", np.nan, "signal_distance_m holds NaN or -inf"),
        ("yield_gap_m", -np.inf, "yield_gap_m holds NaN or -inf"),
    ):
        with h5py.File(root / "a.h5", "a") as f:
            keep = f[name][()]
            f[name][0] = value
        raw = json.loads((root / MANIFEST_NAME).read_text())
        raw["shards"][0]["size_bytes"], raw["shards"][0]["sha256"] = (root / "a.h5").stat().st_size, sha256_file(root / "a.h5")
        (root / MANIFEST_NAME).write_text(json.dumps(raw))
        with pytest.raises(CrchflError, match=rf"a\.h5: {message}"):
            load_samples(root, "train")
        with h5py.File(root / "a.h5", "a") as f:
            f[name][...] = keep


def _samples(states, distances, gaps=None) -> Samples:
    n = len(states)
    return Samples.from_numpy(
        np.zeros((n, 4, 2, 2, 3), np.uint8), np.zeros((n, 3), np.float32), np.zeros(n, np.int64),
        np.zeros(n, np.int64), np.zeros(n, np.float32), np.zeros(n, np.float32),
        np.asarray(states, np.int64), np.asarray(distances, np.float32),
        None if gaps is None else np.asarray(gaps, np.float32),
    )


def test_the_yield_weight_draws_samples_near_a_foe_that_many_times_as_often():
    # 2 of 10 samples near a foe (one in the conflict area), weight 4: each has probability 4 / 16 a draw
    gaps = [10.0, -2.0] + [math.inf] * 6 + [31.0, 45.0]
    samples = _samples([SIGNAL_GREEN] * 10, [5.0] * 10, gaps)
    generator = torch.Generator().manual_seed(0)
    draws = torch.cat([b for _ in range(400) for b in epoch_batches(
        samples, 10, "uniform", generator, yield_weight=4.0, yield_window_m=30.0)])
    shares = [float((draws == i).double().mean()) for i in (0, 1, 2, 8)]
    assert all(abs(a - b) < 0.02 for a, b in zip(shares, [0.25, 0.25, 1 / 16, 1 / 16]))  # 4000 draws: sd <= 0.007
    # weight 1 is the plain permutation, draw for draw; a sample near red and near a foe gets both weights
    a = epoch_batches(samples, 4, "uniform", torch.Generator().manual_seed(3))
    b = epoch_batches(samples, 4, "uniform", torch.Generator().manual_seed(3), yield_weight=1.0)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    both = _samples([SIGNAL_RED, SIGNAL_GREEN], [5.0, 5.0], [3.0, math.inf])
    generator = torch.Generator().manual_seed(1)
    draws = torch.cat([b for _ in range(2000) for b in epoch_batches(
        both, 2, "uniform", generator, red_weight=3.0, yield_weight=3.0)])
    assert abs(float((draws == 0).double().mean()) - 0.9) < 0.02  # 9 / 10; 4000 draws: sd 0.005
    with pytest.raises(ValueError, match="yield_gap_m values must be numbers or inf"):
        _samples([SIGNAL_GREEN], [5.0], [math.nan])


def test_the_red_weight_draws_near_red_samples_that_many_times_as_often():
    # 1 sample near red of 10: with weight 9 it has probability 9 / 18 = 0.5 a draw
    samples = _samples([SIGNAL_RED] + [SIGNAL_GREEN] * 9, [5.0] + [5.0] * 9)
    generator = torch.Generator().manual_seed(0)
    draws = torch.cat([b for _ in range(400) for b in epoch_batches(samples, 10, "uniform", generator, 9.0, 30.0)])
    share = float((draws == 0).double().mean())
    assert abs(share - 0.5) < 0.02  # 4000 draws: sd 0.008
    # weight 1 is today's permutation, draw for draw
    a = epoch_batches(samples, 4, "uniform", torch.Generator().manual_seed(3))
    b = epoch_batches(samples, 4, "uniform", torch.Generator().manual_seed(3), 1.0, 30.0)
    assert all(torch.equal(x, y) for x, y in zip(a, b)) and sorted(torch.cat(a).tolist()) == list(range(10))
    # beyond the window, or at a green, nothing changes in the odds
    far = _samples([SIGNAL_RED, SIGNAL_GREEN], [31.0, 1.0])
    assert not near_red(far, 30.0).any()
