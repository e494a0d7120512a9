"""Training on a CUDA device follows training on the CPU. Skipped where no GPU is present.

The CPU is the reference: the same start, the same batches (the shuffling generator
stays on the CPU), float32 unless a test says otherwise. On the GPU, convolutions
run in TF32 by default and in another summation order, so the tolerances are
those of the bfloat16 tests in test_training.py, not bit equality.
"""

import os

import pytest
import torch

from helpers import random_samples as _samples
from crchfl_sumo.learning.checkpoint import load_model, save_checkpoint
from crchfl_sumo.learning.model import GroupNorm, build_model
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.devices import resolved_precision
from crchfl_sumo.learning.training import Learner, evaluate, train_vehicles

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
# As a command's parts have it: set before this process's first cuBLAS call (torch reads it once).
os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")

SMALL = ModelConfig("compact", 48, 64)


def _flat_difference(a, b, keys):
    return torch.cat([(a[k].cpu() - b[k].cpu()).flatten() for k in keys]).abs()


def _trained(device, samples, **config):
    learner = Learner(build_model(SMALL, seed=0).to(device), TrainConfig(device=device, **config))
    metrics = learner.train_epoch(samples, torch.Generator().manual_seed(0))
    return learner.state(), metrics


@pytest.mark.parametrize("sampling", ["uniform", "pedal_balanced"])
def test_a_cuda_epoch_follows_the_cpu_epoch(sampling):
    samples, start = _samples(96, seed=1), build_model(SMALL, seed=0).state_dict()
    cpu, cpu_metrics = _trained("cpu", samples, precision="fp32", sampling=sampling)
    cuda, cuda_metrics = _trained("cuda", samples, precision="fp32", sampling=sampling)
    assert all(value.device.type == "cpu" for value in cuda.values())  # states leave the GPU
    move, difference = _flat_difference(cpu, start, start), _flat_difference(cpu, cuda, start)
    assert difference.mean() < 0.2 * move.mean()
    assert cuda_metrics.loss == pytest.approx(cpu_metrics.loss, rel=1e-2)


def test_auto_precision_is_bfloat16_on_a_gpu_that_has_it():
    # bfloat16 arithmetic came with compute capability 8.0 (Ampere); the H200 is 9.0.
    expected = "bf16" if torch.cuda.get_device_capability() >= (8, 0) else "fp32"
    assert resolved_precision(TrainConfig(device="cuda"), torch.device("cuda")) == expected


def test_bf16_group_norm_on_cuda_is_nn_group_norm():
    # Affine weights that bfloat16 cannot hold exactly: the CPU's fast path (weights cast to bfloat16)
    # would give other values.
    norm = GroupNorm(4, 16).cuda()
    torch.nn.init.normal_(norm.weight, 1.0, 0.3, generator=torch.Generator("cuda").manual_seed(0))
    torch.nn.init.normal_(norm.bias, 0.0, 0.3, generator=torch.Generator("cuda").manual_seed(1))
    x = torch.randn(3, 16, 6, 8, device="cuda")
    with torch.autocast("cuda", dtype=torch.bfloat16):
        ours = norm(x.to(torch.bfloat16))
        plain = torch.nn.GroupNorm.forward(norm, x.to(torch.bfloat16))
    assert torch.equal(ours, plain)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_vmap_trainer_follows_the_sequential_loop_on_cuda(precision):
    vehicles = [_samples(n, seed=10 + i) for i, n in enumerate((70, 33, 0, 45))]
    start = [build_model(SMALL, seed=s).state_dict() for s in (0, 1, 2, 0)]
    results = {
        method: train_vehicles(start, vehicles, 1, SMALL,
                               TrainConfig(device="cuda", multi_vehicle=method, precision=precision), seed=5)
        for method in ("sequential", "vmap")
    }
    for v in (0, 1, 3):
        sequential, vmapped = results["sequential"][0][v], results["vmap"][0][v]
        move = _flat_difference(sequential, start[v], start[v])
        assert _flat_difference(sequential, vmapped, start[v]).mean() < 0.1 * move.mean()
        loss_sequential, loss_vmapped = results["sequential"][1][v][0].loss, results["vmap"][1][v][0].loss
        assert loss_vmapped == pytest.approx(loss_sequential, rel=1e-2)
    assert _flat_difference(results["vmap"][0][2], start[2], start[2]).max() == 0  # the idle vehicle


@pytest.mark.parametrize("method", ["sequential", "vmap"])
def test_deterministic_cuda_training_repeats_bit_for_bit(method):
    vehicles = [_samples(40, seed=3), _samples(24, seed=4)]
    state = build_model(SMALL, seed=0).state_dict()
    config = TrainConfig(device="cuda", deterministic=True, multi_vehicle=method)
    first, again = (train_vehicles([state, state], vehicles, 1, SMALL, config, seed=7)[0] for _ in range(2))
    assert all(torch.equal(a[k], b[k]) for a, b in zip(first, again) for k in state)


def test_a_model_trained_on_cuda_loads_and_evaluates_on_the_cpu(tmp_path):
    samples = _samples(64, seed=2)
    state, _ = _trained("cuda", samples)
    save_checkpoint(tmp_path / "model.pt", SMALL, state)
    model = load_model(tmp_path / "model.pt")
    assert all(torch.equal(model.state_dict()[k], state[k]) for k in state)
    on_cpu = evaluate(model, samples, TrainConfig(device="cpu"))
    on_cuda = evaluate(model.to("cuda"), samples, TrainConfig(device="cuda"))
    assert on_cuda.loss == pytest.approx(on_cpu.loss, rel=1e-2)
