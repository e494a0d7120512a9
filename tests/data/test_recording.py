"""The data set's simulation run: which frames become a vehicle's samples."""

import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.recording import record_run
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.data.settings import DatasetConfig
from crchfl_sumo.sumo.scenario import load_scenario

STANDING_SPEED_MPS = ExpertConfig.stop_speed_mps
VEHICLE = "t01_data_0"  # departs standing and waits at a red light within its first minute


def standing_times(frames, rows):
    return [frames[i].t_s for i in rows if frames[i].speed_mps[frames[i].index_of(VEHICLE)] < STANDING_SPEED_MPS]


def test_a_standing_vehicle_is_sampled_at_its_own_period():
    scenario = load_scenario("town01")
    every_frames, every_rows = record_run(scenario, 5, {VEHICLE: 200}, 0.25)
    frames, sampled = record_run(scenario, 5, {VEHICLE: 200}, 0.25, standing_every=4)
    rows = sampled[VEHICLE]
    assert len(rows) == 200
    thinned, every = standing_times(frames, rows), standing_times(every_frames, every_rows[VEHICLE])
    assert thinned and len(thinned) < len(every)  # it stood, and fewer of its samples stand
    assert all(t % 1.0 == 0 for t in thinned)  # standing: once a second
    # moving: every 0.25 s as before, and the count is filled from the first frame on
    expected = [
        i for i, f in enumerate(frames)
        if VEHICLE in f.ids.tolist() and f.t_s % 0.25 == 0
        and (f.t_s % 1.0 == 0 or f.speed_mps[f.index_of(VEHICLE)] >= STANDING_SPEED_MPS)
    ][:200]
    assert rows == expected
    # the same simulation either way: only the choice of frames differs
    assert [f.t_s for f in frames[: len(every_frames)]] == [f.t_s for f in every_frames[: len(frames)]]


def test_the_standing_sampling_is_a_whole_number_of_steps():
    assert DatasetConfig().standing_sample_every == 4  # the default: once a second at 0.25 s
    assert from_mapping(DatasetConfig, {"standing_sample_every": 1}).standing_sample_every == 1
    for every in (0, 1001):
        with pytest.raises(CrchflError, match="dataset.standing_sample_every: .* give 1 to sample"):
            from_mapping(DatasetConfig, {"standing_sample_every": every})
    for every in (2.5, "4"):
        with pytest.raises(CrchflError, match="standing_sample_every: expected an integer"):
            from_mapping(DatasetConfig, {"standing_sample_every": every})
