import numpy as np
import pytest
import torch

from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.evaluation import Evaluation
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.trainers import RayTrainer, TorchTrainer

SMALL = ModelConfig("compact", 48, 64)
CPU = TrainConfig(device="cpu", deterministic=True)


def _samples(n, seed):
    rng = np.random.default_rng(seed)
    return Samples.from_numpy(
        rng.integers(0, 256, size=(n, 4, 48, 64, 3), dtype=np.uint8),
        rng.random((n, 3), dtype=np.float32),
        np.where(rng.random(n) < 0.8, 0, rng.integers(1, 7, size=n)),
        rng.integers(0, 4, size=n),
        rng.random(n, dtype=np.float32) * 12,
        rng.random(n, dtype=np.float32) * 12,
    )


@pytest.mark.parametrize("sampling,class_weighting", [("class_balanced", "none"), ("uniform", "sqrt_inverse")])
def test_trainers_give_full_metrics_and_the_same_models(sampling, class_weighting):
    config = TrainConfig(device="cpu", deterministic=True, sampling=sampling, class_weighting=class_weighting)
    test = _samples(12, seed=1)
    vehicles = [_samples(20, seed=2), _samples(9, seed=3)]
    local = TorchTrainer(SMALL, config, test, seed=0)
    start = local.initial_state()
    trained = list(local.train([start, start], vehicles, 1, seed=4))
    again = list(TorchTrainer(SMALL, config, test, seed=0).train([start, start], vehicles, 1, seed=4))
    assert all((a[k] == b[k]).all() for a, b in zip(trained, again) for k in a)  # same seed, same models
    evaluation = local.evaluation(trained[0])
    assert isinstance(evaluation, Evaluation) and evaluation.num_samples == 12
    expected = {k: v for k, v in evaluation.record().items() if k != "samples"}
    assert local.evaluate(trained[0]) == expected  # the loop's metric-line values
    assert local.always_straight["accuracy"] == pytest.approx(float((test.steer_class == 0).double().mean()))
    with Executor(BackendConfig()) as executor:
        remote = RayTrainer(SMALL, config, test, 0, executor)
        remote_trained = list(remote.train([start, start], vehicles, 1, seed=4))
        assert all((a[k] == b[k]).all() for a, b in zip(trained, remote_trained) for k in a)
        assert remote.evaluation(trained[0]).record() == evaluation.record()  # NaN recall compares as None
        assert remote.evaluate(trained[0]) == expected


def test_ray_trainer_sends_each_distinct_model_and_sample_set_once():
    test = _samples(4, seed=1)
    first, second = _samples(3, seed=2), _samples(2, seed=3)
    with Executor(BackendConfig()) as executor:
        put = executor.put
        sent = []
        executor.put = lambda obj: sent.append(obj) or put(obj)
        remote = RayTrainer(SMALL, CPU, test, 0, executor)
        shared, own = remote.initial_state(), TorchTrainer(SMALL, CPU, test, seed=1).initial_state()
        models = list(remote.train([shared, shared, own, shared], [first, second, first, first], 1, seed=4))
        assert len(models) == 4
        # the test set, then each starting model and each sample set once: 4 objects for 4 vehicles, not 8
        assert [id(x) for x in sent] == [id(test), id(shared), id(first), id(second), id(own)]
        sent.clear()
        list(remote.train([shared], [first], 1, seed=5))
        assert [id(x) for x in sent] == [id(shared)]  # the samples were sent before


def test_trainers_skip_the_vehicles_not_needed_and_train_the_others_to_the_bit():
    test = _samples(4, seed=1)
    vehicles = [_samples(6, seed=2), _samples(5, seed=3), _samples(7, seed=5)]
    local = TorchTrainer(SMALL, CPU, test, seed=0)
    start = local.initial_state()
    every = list(local.train([start] * 3, vehicles, 1, seed=4))
    some = list(local.train([start] * 3, vehicles, 1, seed=4, needed=[0, 2]))
    assert some[1] is None and all(torch.equal(some[i][k], every[i][k]) for i in (0, 2) for k in every[i])
    assert not all(torch.equal(every[0][k], every[2][k]) for k in every[0])  # vehicle i keeps its own seed
    assert list(local.train([start] * 3, vehicles, 1, seed=4, needed=[])) == [None, None, None]
    with Executor(BackendConfig()) as executor:
        remote = list(RayTrainer(SMALL, CPU, test, 0, executor).train([start] * 3, vehicles, 1, seed=4, needed=[2]))
        assert remote[:2] == [None, None] and all(torch.equal(remote[2][k], every[2][k]) for k in every[2])
