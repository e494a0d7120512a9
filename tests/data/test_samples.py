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
    )


def test_from_numpy_dtypes_and_len():
    s = _make(5)
    assert len(s) == 5
    assert s.images.dtype == torch.uint8 and s.actions.dtype == torch.float32
    assert s.steer_class.dtype == torch.int64
    assert s.image_hw == (8, 10)


def test_subset_picks_rows_in_order():
    s = _make(6)
    sub = s.subset([4, 1])
    assert len(sub) == 2
    assert torch.equal(sub.images[0], s.images[4]) and torch.equal(sub.actions[1], s.actions[1])
    assert sub.steer_class.tolist() == [s.steer_class[4].item(), s.steer_class[1].item()]
    assert len(s.subset(slice(1, 4))) == 3


def test_concat_round_trips_subsets():
    s = _make(7)
    back = Samples.concat([s.subset(range(0, 3)), s.subset(range(3, 7))])
    assert torch.equal(back.images, s.images)
    assert torch.equal(back.actions, s.actions)
    assert torch.equal(back.steer_class, s.steer_class)


def test_concat_rejects_mixed_sizes_and_empty_list():
    with pytest.raises(ValueError):
        Samples.concat([_make(2, 8, 10), _make(2, 8, 12)])
    with pytest.raises(ValueError):
        Samples.concat([])


def test_validation_rejects_bad_shapes_and_classes():
    s = _make(3)
    with pytest.raises(ValueError):
        Samples(s.images.float(), s.actions, s.steer_class)
    with pytest.raises(ValueError):
        Samples(s.images, s.actions[:2], s.steer_class)
    with pytest.raises(ValueError):
        Samples(s.images, s.actions, torch.tensor([0, 7, 1]))


def test_empty_has_zero_length():
    e = Samples.empty(8, 10)
    assert len(e) == 0 and e.image_hw == (8, 10)
