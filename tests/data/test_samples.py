import numpy as np
import pytest
import torch

from crchfl_sumo.data.samples import Samples


def _make(n, h=8, w=10, seed=0):
    rng = np.random.default_rng(seed)
    return Samples.from_numpy(
        rng.integers(0, 256, size=(n, 4, h, w, 3), dtype=np.uint8),
        rng.random((n, 3), dtype=np.float32),
        rng.integers(0, 7, size=n),
        rng.integers(0, 4, size=n),
        rng.uniform(0, 14, size=n),
        rng.uniform(0, 14, size=n),
    )


def test_from_numpy_dtypes_and_len():
    s = _make(5)
    assert len(s) == 5
    assert s.images.dtype == torch.uint8 and s.actions.dtype == torch.float32
    assert s.steer_class.dtype == torch.int64
    assert s.command.dtype == torch.int64 and s.speed_mps.dtype == torch.float32
    assert s.image_hw == (8, 10)


def test_subset_picks_rows_in_order():
    s = _make(6)
    sub = s.subset([4, 1])
    assert len(sub) == 2
    assert torch.equal(sub.images[0], s.images[4]) and torch.equal(sub.actions[1], s.actions[1])
    assert sub.steer_class.tolist() == [s.steer_class[4].item(), s.steer_class[1].item()]
    assert sub.command.tolist() == [s.command[4].item(), s.command[1].item()]
    assert sub.speed_mps.tolist() == [s.speed_mps[4].item(), s.speed_mps[1].item()]
    assert sub.target_speed_mps.tolist() == [s.target_speed_mps[4].item(), s.target_speed_mps[1].item()]
    assert len(s.subset(slice(1, 4))) == 3


def test_concat_round_trips_subsets():
    s = _make(7)
    back = Samples.concat([s.subset(range(0, 3)), s.subset(range(3, 7))])
    assert torch.equal(back.images, s.images)
    assert torch.equal(back.actions, s.actions)
    assert torch.equal(back.steer_class, s.steer_class)
    assert torch.equal(back.command, s.command) and torch.equal(back.speed_mps, s.speed_mps)
    assert torch.equal(back.target_speed_mps, s.target_speed_mps)


def test_concat_rejects_mixed_sizes_and_empty_list():
    with pytest.raises(ValueError):
        Samples.concat([_make(2, 8, 10), _make(2, 8, 12)])
    with pytest.raises(ValueError):
        Samples.concat([])


def test_validation_rejects_bad_shapes_and_classes():
    s = _make(3)
    rest = (s.command, s.speed_mps, s.target_speed_mps)
    with pytest.raises(ValueError, match="images"):
        Samples(s.images.float(), s.actions, s.steer_class, *rest)
    with pytest.raises(ValueError, match="actions"):
        Samples(s.images, s.actions[:2], s.steer_class, *rest)
    with pytest.raises(ValueError, match="steer_class"):
        Samples(s.images, s.actions, torch.tensor([0, 7, 1]), *rest)
    with pytest.raises(ValueError, match="command"):
        Samples(s.images, s.actions, s.steer_class, torch.tensor([0, 6, 1]), *rest[1:])  # 0..5: COMMAND_NAMES
    with pytest.raises(ValueError, match="command"):
        Samples(s.images, s.actions, s.steer_class, s.command.int(), *rest[1:])
    with pytest.raises(ValueError, match="speed_mps"):
        Samples(s.images, s.actions, s.steer_class, s.command, s.speed_mps.double(), s.target_speed_mps)
    with pytest.raises(ValueError, match="speed_mps"):
        Samples(s.images, s.actions, s.steer_class, s.command, torch.tensor([1.0, -0.5, 2.0]), s.target_speed_mps)
    with pytest.raises(ValueError, match="target_speed_mps"):
        Samples(s.images, s.actions, s.steer_class, s.command, s.speed_mps, torch.tensor([1.0, float("nan"), 2.0]))


def test_to_keeps_every_field():
    s = _make(2).to("cpu")
    assert s.command.dtype == torch.int64 and s.speed_mps.dtype == torch.float32 and len(s) == 2


def test_empty_has_zero_length():
    e = Samples.empty(8, 10)
    assert len(e) == 0 and e.image_hw == (8, 10)
    assert e.command.shape == (0,) and e.speed_mps.dtype == torch.float32
