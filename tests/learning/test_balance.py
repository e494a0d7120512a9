import numpy as np
import pytest
import torch

from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.balance import BRAKE, CRUISE, HOLD, THROTTLE, class_weights, epoch_batches, pedal_states


def _samples(classes, commands):
    n = len(classes)
    return Samples.from_numpy(
        np.zeros((n, 4, 48, 64, 3), np.uint8), np.zeros((n, 3), np.float32), np.array(classes), np.array(commands),
        np.zeros(n, np.float32), np.zeros(n, np.float32),
    )


# 90 straight (class 0, command FOLLOW), 10 hard left (class 6, command LEFT)
IMBALANCED = _samples([0] * 90 + [6] * 10, [0] * 90 + [1] * 10)


def test_uniform_is_a_permutation_in_batches():
    batches = epoch_batches(IMBALANCED, 32, "uniform", torch.Generator().manual_seed(0))
    assert [len(b) for b in batches] == [32, 32, 32, 4]
    assert sorted(torch.cat(batches).tolist()) == list(range(100))


@pytest.mark.parametrize("sampling", ["class_balanced", "command_balanced"])
def test_balanced_sampling_draws_the_minority_as_often_as_the_majority(sampling):
    generator = torch.Generator().manual_seed(0)
    drawn = torch.cat([torch.cat(epoch_batches(IMBALANCED, 32, sampling, generator)) for _ in range(50)])
    assert len(drawn) == 50 * 100  # an epoch is still N draws
    minority = (drawn >= 90).float().mean().item()
    assert minority == pytest.approx(0.5, abs=0.03)  # 10 % of the samples, half of the draws


def test_pedal_states_by_hand():
    # (throttle, steer, brake), speed: standing on the brake, pulling away from standstill,
    # accelerating, cruising on a little throttle, braking, coasting, and standing with no pedal.
    actions = torch.tensor([[0.0, 0, 0.9], [0.8, 0, 0.0], [1.0, 0, 0.0], [0.08, 0, 0.0], [0.0, 0, 0.7],
                            [0.0, 0, 0.2], [0.0, 0, 0.0]])
    speed = torch.tensor([0.0, 0.0, 5.0, 12.0, 8.0, 8.0, 0.05])
    assert pedal_states(actions, speed).tolist() == [HOLD, THROTTLE, THROTTLE, CRUISE, BRAKE, CRUISE, HOLD]


def test_pedal_balanced_sampling_draws_each_pedal_state_equally():
    n_hold, n_brake = 90, 10
    actions = np.zeros((n_hold + n_brake, 3), np.float32)
    actions[:, 2] = 0.9
    speed = np.r_[np.zeros(n_hold), np.full(n_brake, 6.0)].astype(np.float32)
    samples = Samples.from_numpy(np.zeros((100, 4, 48, 64, 3), np.uint8), actions, np.zeros(100, np.int64),
                                 np.zeros(100, np.int64), speed, speed)
    generator = torch.Generator().manual_seed(0)
    drawn = torch.cat([torch.cat(epoch_batches(samples, 32, "pedal_balanced", generator)) for _ in range(50)])
    assert (drawn >= n_hold).float().mean().item() == pytest.approx(0.5, abs=0.03)


def test_sampling_is_seeded():
    draw = lambda seed: torch.cat(epoch_batches(IMBALANCED, 32, "class_balanced", torch.Generator().manual_seed(seed)))
    assert torch.equal(draw(3), draw(3)) and not torch.equal(draw(3), draw(4))
    assert epoch_batches(_samples([], []), 32, "class_balanced", torch.Generator()) == []


def test_class_weights_by_hand():
    classes = torch.tensor([0] * 90 + [6] * 10)
    assert class_weights(classes, "none") is None
    inverse = class_weights(classes, "inverse")
    # N / (K n_c): 100 / (2 * 90) and 100 / (2 * 10); absent classes 0
    assert inverse.tolist() == pytest.approx([100 / 180, 0, 0, 0, 0, 0, 5.0])
    sqrt = class_weights(classes, "sqrt_inverse")
    scale = 100 / (90 / 90**0.5 + 10 / 10**0.5)  # sum_c n_c w_c = N
    assert sqrt.tolist() == pytest.approx([scale / 90**0.5, 0, 0, 0, 0, 0, scale / 10**0.5])
    for weights in (inverse, sqrt):
        assert float((weights[classes]).sum()) == pytest.approx(100)
