import json
import math

import numpy as np
import pytest
import torch

from crchfl_sumo.core.config import from_mapping, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.labels import digitize_steer
from helpers import random_samples as _samples
from crchfl_sumo.learning.checkpoint import load_checkpoint, load_model, save_checkpoint
from crchfl_sumo.learning.evaluation import always_straight
from crchfl_sumo.learning.model import build_model
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.centralized import train_centralized
from crchfl_sumo.learning.devices import resolve_device
from crchfl_sumo.learning.training import Learner, evaluate, train_vehicles

SMALL = ModelConfig("compact", 48, 64)
CPU = TrainConfig(device="cpu")




def test_one_training_step_lowers_the_loss_on_a_fixed_batch():
    batch = _samples(32, seed=1)
    trainer = Learner(build_model(SMALL, seed=0), CPU)
    before = evaluate(trainer.model, batch, CPU)
    trainer.train_epoch(batch, torch.Generator().manual_seed(0))  # 32 samples = exactly one step
    after = evaluate(trainer.model, batch, CPU)
    assert after.loss < before.loss
    assert after.loss_throttle_brake < before.loss_throttle_brake and after.loss_steer < before.loss_steer


def test_evaluate_matches_a_direct_computation_and_ignores_batching():
    samples = _samples(23, seed=2)
    model = build_model(SMALL, seed=0)
    small_batches = evaluate(model, samples, TrainConfig(device="cpu", eval_batch_size=5))
    with torch.no_grad():
        target_speed, logits = model.eval()(samples.images, samples.command, samples.speed_mps)
    mse = ((target_speed[:, 0] - samples.target_speed_mps / 10) ** 2).mean().item()  # the default: target speed
    # the default head's 21 bins 0.1 apart: each sample's target is the bin nearest its steer, and a
    # predicted bin is scored as the paper's class of its value
    bins = torch.round((samples.actions[:, 1] + 1) * 10).long()
    ce = torch.nn.functional.cross_entropy(logits, bins).item()
    paper = torch.as_tensor(digitize_steer(np.linspace(-1, 1, 21)))
    accuracy = (paper[logits.argmax(1)] == samples.steer_class).float().mean().item()
    assert small_batches.loss_throttle_brake == pytest.approx(mse, rel=1e-5)
    assert small_batches.loss_steer == pytest.approx(ce, rel=1e-5)
    assert small_batches.loss == pytest.approx(mse + ce, rel=1e-5)
    assert small_batches.accuracy == pytest.approx(accuracy)
    assert small_batches.num_samples == 23
    one_batch = evaluate(model, samples, TrainConfig(device="cpu", eval_batch_size=256))
    assert one_batch.confusion == small_batches.confusion and one_batch.loss == pytest.approx(small_batches.loss, rel=1e-6)


def _max_difference(a, b):
    return max((a[k] - b[k]).abs().max().item() for k in a)


@pytest.mark.slow
@pytest.mark.parametrize(
    "model_config,balance,epochs",
    [
        # One epoch for the normalised network: in a second epoch on random data Adam amplifies the float32
        # rounding of grouped convolutions to about one step in a few weights (measured); the ragged
        # drop-out of vehicles happens within the first epoch already.
        (SMALL, dict(sampling="uniform", class_weighting="sqrt_inverse"), 1),  # the defaults
        (ModelConfig("compact", 48, 64, speed_input=True, longitudinal="pedals"), dict(sampling="class_balanced"), 1),
        (ModelConfig("compact", 48, 64, arch="paper"), dict(sampling="command_balanced", learning_rate=1e-4), 2),
        (ModelConfig("compact", 48, 64, steer_bins=21), dict(class_weighting="inverse"), 1),  # finer steer bins
    ],
)
def test_vmap_trainer_equals_the_sequential_loop_on_ragged_vehicles(model_config, balance, epochs):
    # Ragged on purpose: 70 (two full batches + 6), 33 (one + 1), 0 (idle) and 45 samples.
    vehicles = [_samples(n, seed=10 + i) for i, n in enumerate((70, 33, 0, 45))]
    start = [build_model(model_config, seed=s).state_dict() for s in (0, 1, 2, 0)]
    results = {
        method: train_vehicles(
            start, vehicles, epochs, model_config,
            TrainConfig(device="cpu", multi_vehicle=method, precision="fp32", **balance), seed=5,
        )
        for method in ("sequential", "vmap")
    }
    (seq_states, seq_metrics), (vmap_states, vmap_metrics) = results["sequential"], results["vmap"]
    step = TrainConfig(**balance).learning_rate
    for v in range(4):
        moved = _max_difference(seq_states[v], start[v])
        # Stated tolerance: float32 rounding of grouped vs plain convolutions. Measured with these configs:
        # mean |difference| about 1e-9 against a mean move of 2e-3; the largest, in a few weights whose
        # gradient is near 0 (where Adam's step is the gradient's sign), 2e-5 to 1.5e-4. (Some other
        # combinations amplify it further, docs/model.md.)
        difference = torch.cat([(seq_states[v][k] - vmap_states[v][k]).flatten() for k in start[v]]).abs()
        assert difference.mean() < 1e-4 * step and difference.max() < 0.3 * step
        assert (moved > step) == (v != 2)
        for a, b in zip(seq_metrics[v], vmap_metrics[v]):
            assert a.num_samples == b.num_samples
            if a.num_samples:
                assert a.loss == pytest.approx(b.loss, rel=1e-5) and a.accuracy == pytest.approx(b.accuracy)
            else:
                assert math.isnan(a.loss) and math.isnan(b.loss)


def test_the_moving_average_is_the_hand_computed_one_over_the_steps():
    # 70 samples at batch 32: three steps. Record the trained weights after each; the kept weights are
    # e1 = w1, e2 = d e1 + (1 - d) w2, e3 = d e2 + (1 - d) w3 (the average starts at the first step's weights).
    decay = 0.75
    trainer = Learner(build_model(SMALL, seed=0), TrainConfig(device="cpu", precision="fp32", ema_decay=decay))
    after_steps = []
    trainer.optimizers[-1].register_step_post_hook(
        lambda *_: after_steps.append({k: v.detach().clone() for k, v in trainer.model.state_dict().items()}))
    trainer.train_epoch(_samples(70, seed=1), torch.Generator().manual_seed(0))
    assert len(after_steps) == 3
    kept = trainer.state()
    for name, value in kept.items():
        expected = after_steps[0][name]
        for weights in after_steps[1:]:
            expected = decay * expected + (1 - decay) * weights[name]
        assert torch.allclose(value, expected, rtol=0, atol=1e-6), name
    assert _max_difference(kept, after_steps[-1]) > 1e-4  # the average is not the last step
    assert trainer.kept_model is not trainer.model
    plain = Learner(build_model(SMALL, seed=0), CPU)  # without: the trained model itself
    assert plain.kept_model is plain.model and plain.average is None


def test_the_moving_average_is_refused_where_the_vehicles_train_vectorised():
    vehicles = [_samples(20, seed=3), _samples(12, seed=4)]
    state = build_model(SMALL, seed=0).state_dict()
    with pytest.raises(CrchflError, match="train.ema_decay: the vectorised training"):
        train_vehicles([state, state], vehicles, 1, SMALL, TrainConfig(device="cpu", multi_vehicle="vmap",
                                                                     ema_decay=0.9), seed=0)
    with pytest.raises(CrchflError, match=r"train.ema_decay: 1 is out of range; give a decay per step \(0 = off\) in \[0, 1\)"):
        TrainConfig(ema_decay=1.0)


def test_train_vehicles_is_reproducible_and_seed_dependent():
    vehicles = [_samples(20, seed=3), _samples(12, seed=4)]
    state = build_model(SMALL, seed=0).state_dict()
    run = lambda seed: train_vehicles([state, state], vehicles, 1, SMALL, CPU, seed=seed)[0]
    first, again, other = run(7), run(7), run(8)
    assert all(_max_difference(a, b) == 0 for a, b in zip(first, again))
    assert _max_difference(first[0], other[0]) > 0
    assert all(torch.equal(state[k], build_model(SMALL, seed=0).state_dict()[k]) for k in state)  # input untouched


def test_checkpoint_round_trip_loads_with_weights_only(tmp_path):
    model = build_model(SMALL, seed=0)
    path = tmp_path / "sub" / "model.pt"
    save_checkpoint(path, SMALL, model.state_dict(), {"epoch": 3, "note": "x"})
    assert sorted(p.name for p in path.parent.iterdir()) == ["model.pt"]  # no temp file left behind
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == "crchfl-sumo-model/2"
    assert raw["model_config"] == {
        "size": "compact", "image_height": 48, "image_width": 64,
        "arch": "cil", "norm": "group", "command_input": "branched", "command_pedals": SMALL.command_pedals,
        "speed_input": False, "steer_speed_input": True, "longitudinal": "target_speed", "speed_horizon_s": 1.0,
        "steer_bins": 21,
    }
    checkpoint = load_checkpoint(path)
    assert checkpoint.model_config == SMALL and checkpoint.extra == {"epoch": 3, "note": "x"}
    loaded = load_model(path)
    assert _max_difference(loaded.state_dict(), model.state_dict()) == 0
    x = _samples(2, seed=0)
    assert torch.equal(loaded(x.images, x.command, x.speed_mps)[1], model.eval()(x.images, x.command, x.speed_mps)[1])


def test_a_format_1_checkpoint_loads_as_the_paper_architecture(tmp_path):
    paper = ModelConfig("compact", 48, 64, arch="paper")
    model = build_model(paper, seed=0)
    # What save_checkpoint wrote before ModelConfig.arch existed.
    legacy = {
        "format": "crchfl-sumo-model/1",
        "model_config": {"size": "compact", "image_height": 48, "image_width": 64},
        "state_dict": model.state_dict(),
        "extra": {},
    }
    torch.save(legacy, tmp_path / "old.pt")
    assert load_checkpoint(tmp_path / "old.pt").model_config == paper
    assert _max_difference(load_model(tmp_path / "old.pt").state_dict(), model.state_dict()) == 0
    # Weights of one architecture under the other's config are refused, naming the file.
    save_checkpoint(tmp_path / "mixed.pt", SMALL, model.state_dict())
    with pytest.raises(CrchflError, match="mixed.pt: weights do not fit"):
        load_model(tmp_path / "mixed.pt")


def test_a_format_2_checkpoint_without_command_pedals_has_an_unconditioned_pedal_branch(tmp_path):
    before = ModelConfig("compact", 48, 64, command_pedals=False, longitudinal="pedals", steer_bins=7)
    model = build_model(before, seed=0)
    new_keys = ("command_pedals", "longitudinal", "speed_horizon_s", "steer_bins")
    mapping = {k: v for k, v in to_mapping(before).items() if k not in new_keys}  # written before the keys
    torch.save({"format": "crchfl-sumo-model/2", "model_config": mapping, "state_dict": model.state_dict(),
                "extra": {}}, tmp_path / "before.pt")
    assert load_checkpoint(tmp_path / "before.pt").model_config == before
    assert _max_difference(load_model(tmp_path / "before.pt").state_dict(), model.state_dict()) == 0


def test_checkpoint_errors_name_the_file(tmp_path):
    with pytest.raises(CrchflError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CrchflError, match="junk.pt"):
        load_checkpoint(tmp_path / "junk.pt")


def test_train_centralized_writes_metrics_and_checkpoint(tmp_path):
    train, test = _samples(40, seed=20), _samples(10, seed=21)
    seen = []
    records = train_centralized(train, test, 2, tmp_path, SMALL, CPU, seed=0, progress=seen.append)
    # samples trained so far after each batch of 32 (40 = 32 + 8 an epoch), over both epochs
    assert [(u.stage, u.done, u.total) for u in seen] == [("train", n, 80) for n in (32, 40, 72, 80)]
    lines = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert lines == records and [r["epoch"] for r in lines] == [1, 2]
    for key in ("loss", "accuracy", "loss_throttle_brake", "loss_steer", "samples_per_s", "train_loss"):
        assert key in lines[0]
    assert lines[0]["loss"] == pytest.approx(lines[0]["loss_throttle_brake"] + lines[0]["loss_steer"])
    final = evaluate(load_model(tmp_path / "checkpoint.pt"), test, CPU)
    for key in ("balanced_accuracy", "steer_error", "throttle_error", "brake_error"):
        assert lines[-1][key] == pytest.approx(getattr(final, key), rel=1e-5)
    assert lines[-1]["confusion"] == [list(row) for row in final.confusion]
    assert sum(map(sum, lines[-1]["confusion"])) == lines[-1]["test_samples"] == 10
    assert len(lines[-1]["recall"]) == 7
    assert lines[-1]["always_straight"] == always_straight(test)
    checkpoint = load_checkpoint(tmp_path / "checkpoint.pt")
    assert checkpoint.extra["epoch"] == 2
    reloaded = evaluate(load_model(tmp_path / "checkpoint.pt"), test, CPU)
    assert reloaded.loss == pytest.approx(lines[-1]["loss"], rel=1e-5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.prev.pt", "checkpoint.pt", "metrics.jsonl"]
    assert load_checkpoint(tmp_path / "checkpoint.prev.pt").extra["epoch"] == 1  # the one epoch 2 replaced


def test_train_centralized_rejects_a_size_mismatch(tmp_path):
    with pytest.raises(CrchflError, match="image_height"):
        train_centralized(_samples(4, 0), _samples(2, 1), 1, tmp_path, ModelConfig("compact", 64, 64), CPU, seed=0)


def test_train_config_validation():
    assert from_mapping(TrainConfig, {"batch_size": 16, "multi_vehicle": "vmap"}).batch_size == 16
    with pytest.raises(CrchflError, match="batch_size"):
        TrainConfig(batch_size=0)
    with pytest.raises(CrchflError, match="multi_vehicle"):
        from_mapping(TrainConfig, {"multi_vehicle": "threads"})
    with pytest.raises(CrchflError, match="train.sampling: 'balanced' is unknown"):
        TrainConfig(sampling="balanced")
    with pytest.raises(CrchflError, match="train.class_weighting"):
        TrainConfig(class_weighting="focal")
    assert resolve_device("cpu") == torch.device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(CrchflError, match="cuda"):
            resolve_device("cuda")


def test_bf16_precision_trains_float32_weights_close_to_the_float32_path():
    # One Adam step of a fixed batch in each precision: weights and optimiser stay float32, the loss falls,
    # and the bfloat16 forward moves the weights nearly as float32 does. Stated tolerance: bfloat16 keeps
    # about 3 significant digits; measured mean |difference| 4 to 8 % of the mean move (Adam's first step
    # is about lr in every weight, so a weight whose gradient is near 0 may step the other way).
    batch = _samples(32, seed=1)
    start = build_model(SMALL, seed=0).state_dict()
    trained = {}
    for precision in ("fp32", "bf16"):
        config = TrainConfig(device="cpu", precision=precision)
        trainer = Learner(build_model(SMALL, seed=0), config)
        before = evaluate(trainer.model, batch, CPU)
        metrics = trainer.train_epoch(batch, torch.Generator().manual_seed(0))
        assert evaluate(trainer.model, batch, CPU).loss < before.loss and math.isfinite(metrics.loss)
        assert all(t.dtype == torch.float32 for t in trainer.model.state_dict().values())
        assert all(s["exp_avg"].dtype == torch.float32 for o in trainer.optimizers for s in o.state.values())
        trained[precision] = trainer.state()
    move = torch.cat([(trained["fp32"][k] - start[k]).flatten() for k in start]).abs()
    difference = torch.cat([(trained["fp32"][k] - trained["bf16"][k]).flatten() for k in start]).abs()
    assert 0 < difference.mean() < 0.2 * move.mean()


def test_bf16_vmap_trainer_follows_the_sequential_loop():
    # The vmapped step runs the same bfloat16 forward as the sequential loop; batched convolutions round
    # differently, so the stated tolerance is bfloat16's (measured mean |difference| 2 to 4 % of the move).
    vehicles = [_samples(n, seed=10 + i) for i, n in enumerate((70, 33, 45))]
    start = [build_model(SMALL, seed=s).state_dict() for s in (0, 1, 0)]
    results = {
        method: train_vehicles(start, vehicles, 1, SMALL, TrainConfig(device="cpu", multi_vehicle=method,
                                                                      precision="bf16"), seed=5)
        for method in ("sequential", "vmap")
    }
    for v in range(3):
        sequential, vmapped = results["sequential"][0][v], results["vmap"][0][v]
        move = torch.cat([(sequential[k] - start[v][k]).flatten() for k in start[v]]).abs()
        difference = torch.cat([(sequential[k] - vmapped[k]).flatten() for k in start[v]]).abs()
        assert difference.mean() < 0.1 * move.mean()
        loss_sequential, loss_vmapped = results["sequential"][1][v][0].loss, results["vmap"][1][v][0].loss
        assert loss_vmapped == pytest.approx(loss_sequential, rel=1e-3)


def test_an_unknown_precision_is_refused_naming_the_key():
    with pytest.raises(CrchflError, match="train.precision.*'fp16'.*'fp32', 'bf16'"):
        TrainConfig(precision="fp16")


def test_bf16_on_a_cpu_without_bfloat16_arithmetic_warns_once_naming_the_fix(monkeypatch, caplog):
    from crchfl_sumo.learning import devices

    # Isolates the probe: this machine's CPU answers for itself, the test asks for one without bfloat16.
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    devices.native_bfloat16.cache_clear()
    devices._warn_emulated_bfloat16.cache_clear()
    try:
        with caplog.at_level("WARNING", logger=devices.log.name):
            Learner(build_model(SMALL, seed=0), TrainConfig(device="cpu", precision="bf16"))
            Learner(build_model(SMALL, seed=0), TrainConfig(device="cpu", precision="bf16"))
            Learner(build_model(SMALL, seed=0), TrainConfig(device="cpu", precision="fp32"))
        warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        assert len(warnings) == 1 and "emulated" in warnings[0] and "train.precision = 'fp32'" in warnings[0]
    finally:
        devices.native_bfloat16.cache_clear()
        devices._warn_emulated_bfloat16.cache_clear()


@pytest.mark.parametrize("has_bfloat16,expected", [(True, "bf16"), (False, "fp32")])
def test_auto_precision_trains_in_bfloat16_only_where_the_cpu_has_it(monkeypatch, has_bfloat16, expected):
    from crchfl_sumo.learning import devices

    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: has_bfloat16, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    devices.native_bfloat16.cache_clear()
    try:
        assert TrainConfig().precision == "auto"
        trainer = Learner(build_model(SMALL, seed=0), TrainConfig(device="cpu"))
        assert trainer.precision == expected
        seen = []
        trainer.model.branch_steer.register_forward_pre_hook(lambda m, args: seen.append(args[0].dtype))
        trainer.train_epoch(_samples(8, seed=1), torch.Generator().manual_seed(0))
        assert seen == [torch.bfloat16 if expected == "bf16" else torch.float32]
    finally:
        devices.native_bfloat16.cache_clear()


@pytest.mark.parametrize(
    "method,device,norm,expected",
    [
        ("auto", "cpu", "group", "sequential"),  # faster on a CPU (docs/model.md)
        ("auto", "cuda", "group", "vmap"),  # one launch of a step's kernels for all vehicles
        ("auto", "cuda", "batch", "sequential"),  # BatchNorm cannot be vmapped
        ("vmap", "cpu", "group", "vmap"),  # an explicit choice stands
        ("sequential", "cuda", "group", "sequential"),
    ],
)
def test_auto_multi_vehicle_vmaps_on_a_gpu_only(method, device, norm, expected):
    from crchfl_sumo.learning.devices import resolved_multi_vehicle

    model_config = ModelConfig("compact", 48, 64, norm=norm)
    assert resolved_multi_vehicle(TrainConfig(multi_vehicle=method), model_config, device) == expected
    if method == "auto":  # the vectorised step keeps no moving average of the weights
        assert resolved_multi_vehicle(TrainConfig(multi_vehicle=method, ema_decay=0.9), model_config, device) == "sequential"


def test_auto_multi_vehicle_on_the_cpu_trains_as_the_sequential_loop_bit_for_bit():
    vehicles = [_samples(40, seed=3), _samples(24, seed=4)]
    state = build_model(SMALL, seed=0).state_dict()
    run = lambda method: train_vehicles([state, state], vehicles, 1, SMALL,
                                        TrainConfig(device="cpu", multi_vehicle=method), seed=7)[0]
    auto, sequential = run("auto"), run("sequential")
    assert all(_max_difference(a, b) == 0 for a, b in zip(auto, sequential))
