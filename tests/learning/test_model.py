import io

import numpy as np
import pytest
import torch
from torch import nn

from crchfl_sumo.core.config import from_mapping, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.data.labels import STEER_CLASS_VALUES
from crchfl_sumo.learning.model import (
    DrivingModel,
    GridAveragePool,
    GroupNorm,
    build_model,
    count_parameters,
    model_from_state,
    predict_actions,
    state_size_bytes,
)
from crchfl_sumo.learning.settings import ModelConfig

SMALL = ModelConfig("compact", 48, 64)
PAPER_ARCH = ModelConfig("compact", 48, 64, arch="paper")
SEVEN = ModelConfig("compact", 48, 64, steer_bins=7)  # the cil network with the paper's 7 steer classes
COMMANDS = torch.tensor([0, 1, 2, 3, 1])
SPEEDS = torch.tensor([0.0, 3.0, 8.0, 12.5, 5.0])


def _images(n, config=SMALL, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 4, config.image_height, config.image_width, 3), dtype=torch.uint8, generator=g)


def _run(model, images, command=None, speed=None):
    n = len(images)
    command = torch.zeros(n, dtype=torch.int64) if command is None else command
    speed = torch.zeros(n) if speed is None else speed
    return model(images, command, speed)


@pytest.mark.parametrize("height,width", [(48, 64), (66, 200), (64, 96)])
@pytest.mark.parametrize(
    "options",
    [{}, {"arch": "paper"}, {"norm": "batch"}, {"norm": "layer"}, {"norm": "none"}, {"command_input": "concat"},
     {"command_input": "none", "speed_input": True}],
)
def test_output_shapes_and_ranges(height, width, options):
    config = ModelConfig("compact", height, width, **options)
    longitudinal, steer_logits = build_model(config, seed=0)(_images(5, config), COMMANDS, SPEEDS)
    assert config.longitudinal == ("pedals" if options.get("arch") == "paper" else "target_speed")  # the defaults
    assert longitudinal.shape == (5, 2 if config.longitudinal == "pedals" else 1) and steer_logits.shape == (5, config.steer_bins)
    if config.longitudinal == "pedals":
        assert longitudinal.min() >= 0 and longitudinal.max() <= 1
    assert torch.isfinite(longitudinal).all() and torch.isfinite(steer_logits).all()


def test_a_target_speed_model_has_one_unbounded_branch_i_output():
    config = ModelConfig("compact", 48, 64, longitudinal="target_speed")
    model = build_model(config, seed=0)
    with torch.no_grad():
        model.branch_throttle_brake.heads[0][-1].bias.fill_(1.3)  # 13 m/s: beyond a sigmoid's range
    target, steer_logits = model(_images(5, config), COMMANDS, SPEEDS)
    assert target.shape == (5, 1) and steer_logits.shape == (5, config.steer_bins)
    assert target.min() > 1.0


def test_predict_actions_of_a_target_speed_model_drives_towards_it():
    config = ModelConfig("compact", 48, 64, longitudinal="target_speed", speed_horizon_s=2.0)
    model = build_model(config, seed=0)
    head = model.branch_throttle_brake.heads[0][-1]
    with torch.no_grad():
        head.weight.zero_()
        head.bias.fill_(0.5)  # 5 m/s whatever the images
    speed = torch.tensor([0.0, 5.0, 9.0])
    actions = predict_actions(model, _images(3), torch.tensor([0, 0, 0]), speed, max_accel_mps2=2.0, max_decel_mps2=4.0)
    # (5 - v) / 2 s: +2.5 m/s^2 (full throttle), 0 (throttle for rolling resistance and drag), -2 (brake)
    assert actions[0, 0] == pytest.approx(1.0) and actions[0, 2] == 0
    assert actions[1, 0] == pytest.approx((0.015 * 9.81 + 2.64e-4 * 25) / 2.0, rel=1e-5) and actions[1, 2] == 0
    assert actions[2, 0] == 0 and actions[2, 2] == pytest.approx((2.0 - 0.015 * 9.81 - 2.64e-4 * 81) / 4.0, rel=1e-5)
    with torch.no_grad():
        head.bias.fill_(0.09)  # 0.9 m/s: below STAND_TARGET_MPS, a stop
    standing = predict_actions(model, _images(1)[0], 0, 0.0)
    assert standing[0] == 0 and standing[2] == pytest.approx(0.9)  # holds the brake, does not creep
    with torch.no_grad():
        head.bias.fill_(0.5)
    geared = predict_actions(model, _images(3), torch.tensor([0, 0, 0]), speed, max_accel_mps2=2.0,
                             max_decel_mps2=4.0, brake_gain=2.0)
    assert geared[:2] == pytest.approx(actions[:2])  # at or below the target: as labelled
    # above it: (5 - 9) / 2 s x 2 = -4 m/s^2
    assert geared[2, 2] == pytest.approx((4.0 - 0.015 * 9.81 - 2.64e-4 * 81) / 4.0, rel=1e-5)


def test_parameter_count_does_not_depend_on_image_size():
    for options in ({}, {"arch": "paper"}):
        counts = {
            count_parameters(DrivingModel(ModelConfig("compact", h, w, **options))) for h, w in [(48, 64), (66, 200), (90, 160)]
        }
        assert len(counts) == 1
        assert 300_000 < counts.pop() < 1_000_000


def test_the_paper_architecture_is_the_network_of_format_1_checkpoints():
    model = DrivingModel(PAPER_ARCH)
    assert count_parameters(model) == 482_515  # docs/model.md, before ModelConfig.arch
    assert not any(isinstance(m, (torch.nn.GroupNorm, torch.nn.BatchNorm2d)) for m in model.modules())
    widths = [m.out_features for m in model.branch_steer.layers if isinstance(m, torch.nn.Linear)]
    assert widths == [100, 50, 10, 7]  # the 10-unit bottleneck stays in the paper's network
    names = set(model.state_dict())
    assert "branch_steer.layers.0.weight" in names and "branch_throttle_brake.layers.18.bias" in names
    images = _images(3, PAPER_ARCH)
    first = _run(model, images, torch.tensor([0, 1, 2]), torch.tensor([0.0, 5.0, 9.0]))
    second = _run(model, images, torch.tensor([3, 3, 3]), torch.tensor([1.0, 1.0, 1.0]))
    assert all(torch.equal(a, b) for a, b in zip(first, second))  # command and speed are ignored


def test_the_cil_architecture_is_normalised_without_the_bottleneck():
    model = DrivingModel(SMALL)
    norms = [m for m in model.branch_steer.features if isinstance(m, torch.nn.GroupNorm)]
    assert [(n.num_groups, n.num_channels) for n in norms] == [(8, 24), (4, 36), (8, 48), (8, 64), (8, 64)]
    assert len(model.branch_steer.heads) == 4 and len(model.branch_throttle_brake.heads) == 1
    widths = [m.out_features for m in model.branch_steer.heads[0] if isinstance(m, torch.nn.Linear)]
    assert widths == [50, 21]  # 50 units before the 21-way output, not 10
    assert isinstance(DrivingModel(ModelConfig(norm="batch")).branch_steer.features[1], torch.nn.BatchNorm2d)
    assert DrivingModel(ModelConfig(norm="layer")).branch_steer.features[1].num_groups == 1


def test_initial_steer_logits_are_near_uniform():
    _, logits = _run(build_model(SMALL, seed=0), _images(8))
    probabilities, n = logits.softmax(dim=1), SMALL.steer_bins
    assert probabilities.max() < 1.4 / n and probabilities.min() > 0.7 / n  # 1/21 = 0.048 each, no class favoured


def test_branched_heads_are_picked_by_the_command():
    model = build_model(SEVEN, seed=0)
    with torch.no_grad():
        for k, head in enumerate(model.branch_steer.heads):
            head[-1].weight.zero_()
            head[-1].bias.copy_(torch.nn.functional.one_hot(torch.tensor(k + 1), 7) * 5.0)  # head k says class k + 1
    _, logits = _run(model, _images(5), COMMANDS, SPEEDS)
    assert logits.argmax(dim=1).tolist() == [1, 2, 3, 4, 2]


@pytest.mark.parametrize("options,command_matters,pedals_see_command,speed_matters", [
    ({"command_pedals": False}, True, False, False),
    ({"command_pedals": False, "speed_input": True}, True, False, True),
    ({"command_pedals": True}, True, True, False),
    ({"command_pedals": True, "command_input": "concat"}, True, True, False),
    ({"command_pedals": False, "command_input": "concat"}, True, False, False),
    ({"command_pedals": True, "command_input": "none", "speed_input": False}, False, False, False),
    ({"command_input": "none", "speed_input": True}, False, False, True),
])
def test_command_and_speed_reach_the_outputs_as_configured(options, command_matters, pedals_see_command, speed_matters):
    model = build_model(ModelConfig("compact", 48, 64, **options), seed=0).eval()
    images = _images(4)
    base = _run(model, images, torch.tensor([0, 0, 0, 0]), torch.full((4,), 2.0))
    other_command = _run(model, images, torch.tensor([1, 2, 3, 1]), torch.full((4,), 2.0))
    other_speed = _run(model, images, torch.tensor([0, 0, 0, 0]), torch.full((4,), 9.0))
    assert (not torch.equal(base[1], other_command[1])) == command_matters
    assert (not torch.equal(base[0], other_command[0])) == pedals_see_command
    assert (not torch.equal(base[0], other_speed[0])) == speed_matters
    assert (not torch.equal(base[1], other_speed[1])) == speed_matters


def test_the_speed_can_be_kept_to_branch_i():
    both = build_model(ModelConfig("compact", 48, 64, speed_input=True), seed=0).eval()
    pedals_only = build_model(ModelConfig("compact", 48, 64, speed_input=True, steer_speed_input=False), seed=0).eval()
    images, commands = _images(4), torch.tensor([0, 0, 0, 0])
    slow, fast = (_run(pedals_only, images, commands, torch.full((4,), v)) for v in (2.0, 9.0))
    assert not torch.equal(slow[0], fast[0]) and torch.equal(slow[1], fast[1])
    # the steer branch is the one of a model without speed input: one input fewer
    blind = build_model(ModelConfig("compact", 48, 64), seed=0)
    assert count_parameters(pedals_only.branch_steer) == count_parameters(blind.branch_steer)
    heads = len(both.branch_steer.heads)  # one input more: a weight per unit of each head's first layer
    assert count_parameters(both.branch_steer) == count_parameters(blind.branch_steer) + heads * both.config.shape.hidden[1]
    with pytest.raises(CrchflError, match="model.steer_speed_input"):
        ModelConfig(steer_speed_input="no")


def test_same_seed_same_weights_and_other_seed_differs():
    a, b, c = (build_model(SMALL, seed=s).state_dict() for s in (3, 3, 4))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def _branch_inputs(model, images) -> dict:
    """{"head": what branch I is handed, "sides": what branch II is handed} in one forward pass."""
    seen = {}
    hooks = [model.branch_throttle_brake.register_forward_pre_hook(lambda m, args: seen.update(head=args[0])),
             model.branch_steer.register_forward_pre_hook(lambda m, args: seen.update(sides=args[0]))]
    outputs = _run(model, images)
    for hook in hooks:
        hook.remove()
    return {**seen, "outputs": outputs}


def test_branches_see_their_cameras_in_order():
    images = _images(2)
    seen = _branch_inputs(build_model(SMALL, seed=0), images)
    normalised = images.float() / 127.5 - 1
    assert torch.allclose(seen["head"], normalised[:, 0].permute(0, 3, 1, 2), atol=1e-6)
    for k, camera in enumerate((1, 2, 3)):  # CamF, CamL, CamR -> channels 0-2, 3-5, 6-8
        assert torch.allclose(seen["sides"][:, 3 * k : 3 * k + 3], normalised[:, camera].permute(0, 3, 1, 2), atol=1e-6)
    assert seen["head"].min() >= -1 and seen["head"].max() <= 1


def test_predict_actions_decodes_steer_with_the_dac():
    model = build_model(PAPER_ARCH, seed=0)
    last = model.branch_steer.layers[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0, 0, 0, 0, 0, 5.0, 0]))  # class 5 always wins
    actions = predict_actions(model, _images(3), torch.tensor([0, 1, 2]), torch.tensor([0.0, 1.0, 2.0]))
    assert actions.shape == (3, 3) and actions.dtype == np.float32
    assert actions[:, 1] == pytest.approx([-0.275] * 3)
    assert ((actions[:, [0, 2]] >= 0) & (actions[:, [0, 2]] <= 1)).all()
    single = predict_actions(model, _images(1)[0], 2, 4.5)
    assert single.shape == (3,) and single[1] in STEER_CLASS_VALUES
    assert model.training  # the training flag is restored


def test_expected_steer_decoding_weights_the_class_values_by_probability():
    model = build_model(PAPER_ARCH, seed=0)
    last = model.branch_steer.layers[-1]
    with torch.no_grad():
        last.weight.zero_()
        # logits ln 3 for class 1 (0.125) and ln 1 = 0 for class 4 (-0.125), -inf-like elsewhere:
        # probabilities 3/4 and 1/4, so the expected steer is 0.75 * 0.125 - 0.25 * 0.125 = 0.0625.
        last.bias.copy_(torch.tensor([-50.0, float(np.log(3.0)), -50.0, -50.0, 0.0, -50.0, -50.0]))
    images = _images(2)
    expected = predict_actions(model, images, torch.tensor([0, 0]), torch.zeros(2), "expected")
    argmax = predict_actions(model, images, torch.tensor([0, 0]), torch.zeros(2), "argmax")
    assert expected[:, 1] == pytest.approx([0.0625, 0.0625], abs=1e-6)
    assert argmax[:, 1] == pytest.approx([0.125, 0.125])
    assert expected[:, [0, 2]] == pytest.approx(argmax[:, [0, 2]])  # the pedals do not depend on the decoding
    assert predict_actions(model, images, torch.tensor([0, 0]), torch.zeros(2), "auto") == pytest.approx(argmax)
    with pytest.raises(CrchflError, match="steer-decoding"):
        predict_actions(model, images, torch.tensor([0, 0]), torch.zeros(2), "mean")


def test_auto_decoding_weights_a_fine_steer_heads_likeliest_bins_by_probability():
    model = build_model(ModelConfig("compact", 48, 64), seed=0)  # cil: 21 bins 0.1 apart over [-1, 1]
    assert model.config.steer_bins == 21
    logits = torch.full((21,), -50.0)
    logits[11], logits[12] = float(np.log(3.0)), 0.0  # bins of 0.1 and 0.2: 0.75 * 0.1 + 0.25 * 0.2 = 0.125
    with torch.no_grad():
        for head in model.branch_steer.heads:  # one per route command
            head[-1].weight.zero_()
            head[-1].bias.copy_(logits)
    images = _images(2)
    auto = predict_actions(model, images, torch.tensor([0, 1]), torch.zeros(2))
    assert auto[:, 1] == pytest.approx([0.125, 0.125], abs=1e-6)
    # a far bin is left out by auto (mode), not by expected: 0.6 on 0.1, 0.2 on 0.2, 0.2 on -0.5
    logits = torch.full((21,), -50.0)
    logits[11], logits[12], logits[5] = float(np.log(3.0)), 0.0, 0.0
    with torch.no_grad():
        for head in model.branch_steer.heads:
            head[-1].bias.copy_(logits)
    auto = predict_actions(model, images, torch.tensor([0, 1]), torch.zeros(2))
    assert auto[:, 1] == pytest.approx([0.125, 0.125], abs=1e-6)
    expected = predict_actions(model, images, torch.tensor([0, 1]), torch.zeros(2), "expected")
    assert expected[:, 1] == pytest.approx([0.6 * 0.1 + 0.2 * 0.2 - 0.2 * 0.5] * 2, abs=1e-6)
    assert predict_actions(model, images, torch.tensor([0, 1]), torch.zeros(2), "argmax")[:, 1] == pytest.approx([0.1, 0.1])


def test_predict_actions_passes_command_and_speed():
    model = build_model(ModelConfig("compact", 48, 64, longitudinal="pedals", steer_bins=7), seed=0)
    images = _images(3)
    command, speed = torch.tensor([1, 2, 3]), torch.tensor([0.0, 4.0, 11.0])
    throttle_brake, logits = model.eval()(images, command, speed)
    actions = predict_actions(model, images, command.numpy(), speed.numpy())
    assert actions[:, [0, 2]] == pytest.approx(throttle_brake.detach().numpy())
    assert actions[:, 1] == pytest.approx(STEER_CLASS_VALUES[logits.argmax(dim=1).numpy()])
    one = predict_actions(model, images[1], 2, 4.0)
    assert one == pytest.approx(actions[1], abs=1e-6)
    with pytest.raises(ValueError, match="3 images, 2 commands"):
        predict_actions(model, images, torch.tensor([0, 1]), speed)
    with pytest.raises(ValueError, match="commands must lie in 0..5"):
        predict_actions(model, images, torch.tensor([0, 1, 6]), speed)
    with pytest.raises(ValueError, match="commands must lie in 0..5"):
        predict_actions(model, images, torch.tensor([0, -1, 2]), speed)


def test_paper_size_matches_the_reference_implementation():
    model = DrivingModel(ModelConfig("paper", arch="paper"))
    assert count_parameters(model) == pytest.approx(39.4e6, rel=0.02)
    size_bytes = state_size_bytes(model.state_dict())
    assert size_bytes == pytest.approx(150 * 2**20, rel=0.02)  # FACTS.md: 150 MB per model
    buffer = io.BytesIO()
    torch.save(model.state_dict(), buffer)
    assert buffer.tell() == pytest.approx(size_bytes, rel=0.001)  # serialized = raw tensor bytes + small header


def test_config_validation_and_round_trip():
    with pytest.raises(CrchflError, match="image_height"):
        ModelConfig("compact", 32, 64)
    with pytest.raises(CrchflError, match="size"):
        ModelConfig("huge")
    config = ModelConfig(
        "paper", 64, 96, norm="batch", command_input="concat", command_pedals=True, speed_input=True,
        longitudinal="target_speed", speed_horizon_s=1.5, steer_bins=21,
    )
    assert from_mapping(ModelConfig, to_mapping(config)) == config
    assert to_mapping(config) == {
        "size": "paper", "image_height": 64, "image_width": 96,
        "arch": "cil", "norm": "batch", "command_input": "concat", "command_pedals": True, "speed_input": True,
        "steer_speed_input": True,
        "longitudinal": "target_speed", "speed_horizon_s": 1.5, "steer_bins": 21,
    }
    for bad in (6, 8, 5, 203, 7.0, True):
        with pytest.raises(CrchflError, match="model.steer_bins"):
            ModelConfig(steer_bins=bad)
    with pytest.raises(CrchflError, match="model.steer_bins: 21 applies to arch 'cil' only"):
        ModelConfig(arch="paper", steer_bins=21)
    for bad in (0.0, 7.0, float("nan")):
        with pytest.raises(CrchflError, match="model.speed_horizon_s must lie in"):
            ModelConfig(speed_horizon_s=bad)
    for key, value in (("arch", "resnet"), ("norm", "instance"), ("command_input", "film"), ("longitudinal", "gear")):
        with pytest.raises(CrchflError, match=f"model.{key}: '{value}' is unknown"):
            ModelConfig(**{key: value})
    with pytest.raises(CrchflError, match="model.speed_input"):
        ModelConfig(speed_input="yes")
    with pytest.raises(CrchflError, match="model.command_pedals: 1 must be true or false"):
        ModelConfig(command_pedals=1)
    with pytest.raises(CrchflError, match="model.command_pedals: True applies to arch 'cil' only"):
        ModelConfig(arch="paper", command_pedals=True)
    with pytest.raises(CrchflError, match="model.norm: 'batch' applies to arch 'cil' only"):
        ModelConfig(arch="paper", norm="batch")
    with pytest.raises(CrchflError, match="model.command_input"):
        ModelConfig(arch="paper", command_input="concat")
    with pytest.raises(CrchflError, match="model.longitudinal: 'target_speed' applies to arch 'cil' only"):
        ModelConfig(arch="paper", longitudinal="target_speed")


def test_model_from_state_copies_weights_and_leaves_the_rng_alone():
    source = build_model(SMALL, seed=0)
    state = source.state_dict()
    rng_before = torch.random.get_rng_state()
    model = model_from_state(SMALL, state)
    assert torch.equal(torch.random.get_rng_state(), rng_before)
    assert all(torch.equal(model.state_dict()[k], state[k]) for k in state)
    original = {k: v.clone() for k, v in state.items()}
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)  # changing the copy must not change the source
    assert all(torch.equal(state[k], original[k]) for k in state)
    assert all(p.requires_grad for p in model.parameters())
    images = _images(2)
    assert torch.equal(_run(build_model(SMALL, seed=0), images)[1], _run(model_from_state(SMALL, state), images)[1])


@pytest.mark.parametrize("height,width", [(5, 13), (1, 5), (7, 22), (2, 8)])
def test_grid_pool_equals_adaptive_average_pooling(height, width):
    x = torch.randn(3, 4, height, width)
    expected = torch.nn.functional.adaptive_avg_pool2d(x, (2, 8))
    assert torch.allclose(GridAveragePool((2, 8))(x), expected, atol=1e-6)


def test_the_controller_reaches_the_target_over_the_models_horizon():
    config = ModelConfig("compact", 48, 64, speed_horizon_s=1.0)
    assert ModelConfig().speed_horizon_s == ExpertConfig().speed_horizon_s == 1.0  # the defaults agree
    model = build_model(config, seed=0)
    head = model.branch_throttle_brake.heads[0][-1]
    with torch.no_grad():
        head.weight.zero_()
        head.bias.fill_(0.6)  # 6 m/s
    # at 5 m/s: +1 m/s over 1 s (not 0.5 m/s^2 as over 2 s), plus rolling resistance and drag
    throttle = predict_actions(model, _images(1)[0], 0, 5.0)[0]
    assert throttle == pytest.approx((1.0 + 0.015 * 9.81 + 2.64e-4 * 25) / 2.6, rel=1e-5)


def test_a_finer_steer_head_learns_the_nearest_bin_and_reads_as_the_papers_class():
    from crchfl_sumo.learning.model import paper_class_of_bin, steer_targets

    fine = ModelConfig(image_height=48, image_width=64, steer_bins=21)
    model = build_model(fine, seed=0)
    images = torch.zeros(2, 4, 48, 64, 3, dtype=torch.uint8)
    _, logits = model(images, torch.tensor([0, 1]), torch.zeros(2))
    assert logits.shape == (2, 21)
    # targets: the bin nearest the analogue steer (0.23 -> 0.2, -0.46 -> -0.5); the paper's 7 keep their class
    steer = torch.tensor([0.23, -0.46])
    assert steer_targets(fine, torch.tensor([2, 6]), steer).tolist() == [12, 5]
    assert steer_targets(ModelConfig(steer_bins=7), torch.tensor([2, 6]), steer).tolist() == [2, 6]
    # each bin's paper class: -1 .. -0.4 -> 6 (-0.425), -0.3 -> 5, -0.2 and -0.1 -> 4, 0 -> 0, ..., 0.4 .. 1 -> 3
    assert paper_class_of_bin(fine).tolist() == [6] * 7 + [5, 4, 4, 0, 1, 1, 2] + [3] * 7
    assert paper_class_of_bin(ModelConfig(steer_bins=7)).tolist() == list(range(7))
    # argmax drives with the bin's value; auto (the default, mode) weighs it and its neighbours, so it lies
    # within a bin of argmax's
    actions = predict_actions(model, images[0], 0, 0.0, steer_decoding="argmax")
    assert np.isclose(actions[1], np.round(actions[1], 1))
    mode = predict_actions(model, images[0], 0, 0.0, steer_decoding="mode")
    assert np.isclose(predict_actions(model, images[0], 0, 0.0)[1], mode[1])
    assert abs(mode[1] - actions[1]) <= 0.1 + 1e-6


def test_group_norm_on_bfloat16_channels_last_follows_float32():
    # Under bfloat16 autocast the convolutions hand GroupNorm bfloat16 in channels_last layout; its fast
    # path must give nn.GroupNorm's result within bfloat16's rounding, keep the layout the next convolution
    # wants, and send float32 gradients to the float32 affine weights.
    torch.manual_seed(0)
    norm = GroupNorm(8, 24)
    with torch.no_grad():
        norm.weight.uniform_(0.5, 1.5)
        norm.bias.uniform_(-0.5, 0.5)
    # (an input that needs no gradient crashes PyTorch 2.13's channels_last float32 backward; in the
    # network every GroupNorm input comes from a trained convolution)
    x = torch.randn(4, 24, 7, 9).contiguous(memory_format=torch.channels_last).requires_grad_()
    expected = nn.GroupNorm.forward(norm, x)
    assert torch.equal(norm(x), expected)  # float32: nn.GroupNorm's own path
    y = norm(x.detach().bfloat16().requires_grad_())
    assert y.dtype == torch.bfloat16 and y.is_contiguous(memory_format=torch.channels_last)
    assert torch.allclose(y.float(), expected, atol=0.05, rtol=0.02)  # bfloat16: 8 significant bits
    y.float().square().sum().backward()
    float_weight = norm.weight.grad.clone()
    norm.weight.grad = None
    expected.square().sum().backward()
    assert norm.weight.grad.dtype == torch.float32
    assert torch.allclose(float_weight, norm.weight.grad, rtol=0.05)


def test_under_autocast_the_branches_see_bfloat16_images_equal_to_the_float32_ones_rounded():
    model, images = build_model(SMALL, seed=0), _images(2)
    float32 = _branch_inputs(model, images)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        seen = _branch_inputs(model, images)
    longitudinal, steer_logits = seen["outputs"]
    for name in ("head", "sides"):
        assert seen[name].dtype == torch.bfloat16
        assert torch.allclose(seen[name].float(), float32[name], atol=4e-3)  # bfloat16 steps near 1: 2**-8
    assert torch.isfinite(steer_logits.float()).all() and torch.isfinite(longitudinal.float()).all()


def test_model_from_state_keeps_batch_norm_counters_integer_so_its_checkpoint_loads(tmp_path):
    # BatchNorm's num_batches_tracked is int64; cast to float32 it failed the checkpoint's weight check.
    from crchfl_sumo.learning.checkpoint import load_model, save_checkpoint

    config = ModelConfig("compact", 48, 64, norm="batch")
    state = build_model(config, seed=0).state_dict()
    copied = model_from_state(config, state).state_dict()
    assert {k: v.dtype for k, v in copied.items()} == {k: v.dtype for k, v in state.items()}
    assert copied["branch_steer.features.1.num_batches_tracked"].dtype == torch.int64
    save_checkpoint(tmp_path / "model.pt", config, copied)
    assert all(torch.equal(load_model(tmp_path / "model.pt").state_dict()[k], v) for k, v in copied.items())


def test_a_six_command_network_has_a_head_per_lane_change_and_a_four_command_one_reads_them_as_follow():
    six = build_model(ModelConfig("compact", 48, 64, steer_bins=7, commands=6), seed=0)
    four = build_model(SEVEN, seed=0)
    assert len(six.branch_steer.heads) == 6 and len(four.branch_steer.heads) == 4
    for model in (six, four):
        with torch.no_grad():
            for k, head in enumerate(model.branch_steer.heads):
                head[-1].weight.zero_()
                head[-1].bias.copy_(torch.nn.functional.one_hot(torch.tensor(k), 7) * 5.0)  # head k says class k
    commands = torch.tensor([0, 1, 2, 3, 4, 5])
    assert _run(six, _images(6), commands)[1].argmax(dim=1).tolist() == [0, 1, 2, 3, 4, 5]
    assert _run(four, _images(6), commands)[1].argmax(dim=1).tolist() == [0, 1, 2, 3, 0, 0]  # 4, 5: follow's head
    # the one-hot input has a place per command: six of them
    concat = build_model(ModelConfig("compact", 48, 64, command_input="concat", commands=6), seed=0)
    assert concat.branch_steer.heads[0][0].in_features == SMALL.shape.hidden[0] + 6
    actions = predict_actions(six, _images(2), torch.tensor([4, 5]), torch.tensor([5.0, 5.0]))
    assert actions.shape == (2, 3)
    with pytest.raises(ValueError, match="0..5"):
        predict_actions(six, _images(1), torch.tensor([6]), torch.tensor([5.0]))


def test_the_commands_setting_takes_the_datas_lane_changes_and_is_checked():
    from crchfl_sumo.learning.settings import with_data_commands

    assert SMALL.commands is None and SMALL.num_commands == 4
    assert "commands" not in to_mapping(SMALL)  # unset: the towns' configs and checkpoints read as before
    assert with_data_commands(SMALL, 3) is SMALL
    lanes = with_data_commands(SMALL, 5)
    assert lanes.commands == 6 and lanes.num_commands == 6 and to_mapping(lanes)["commands"] == 6
    set_four = ModelConfig("compact", 48, 64, commands=4)
    assert with_data_commands(set_four, 5).num_commands == 4  # a setting given stays
    assert with_data_commands(PAPER_ARCH, 5) is PAPER_ARCH  # the paper's network has no command
    assert from_mapping(ModelConfig, to_mapping(lanes)) == lanes
    with pytest.raises(CrchflError, match="model.commands: 5; use 4"):
        ModelConfig("compact", 48, 64, commands=5)
    with pytest.raises(CrchflError, match="model.commands"):
        ModelConfig("compact", 48, 64, arch="paper", commands=6)


def test_mode_decoding_weights_the_most_likely_class_and_its_neighbours_only():
    from crchfl_sumo.learning.model import mode_steer

    values = np.linspace(-1.0, 1.0, 21, dtype=np.float32)  # 0.1 apart; index 10 is 0
    p = np.zeros((3, 21), np.float32)
    p[0, 10], p[0, 9] = 0.6, 0.4  # straight on or a little left: -0.04
    p[1, 10], p[1, 5], p[1, 4] = 0.4, 0.35, 0.25  # a turn (-0.5, -0.6) or not: the mode is 0 alone
    p[2, 0], p[2, 1] = 0.7, 0.3  # at the edge: one neighbour only
    assert mode_steer(p, values) == pytest.approx([-0.04, 0.0, -0.97], abs=1e-6)
    # the paper's 7 classes are not in value order: neighbours are by value (0.125 and 0.275 beside 0.275's)
    seven = np.zeros((1, 7), np.float32)
    seven[0, 2], seven[0, 1], seven[0, 3], seven[0, 4] = 0.5, 0.2, 0.2, 0.1  # 0.275, 0.125, 0.425, -0.125
    assert mode_steer(seven, STEER_CLASS_VALUES) == pytest.approx((0.5 * 0.275 + 0.2 * 0.125 + 0.2 * 0.425) / 0.9)
    model = build_model(SMALL, seed=0)  # through predict_actions: a steer within the classes' range
    actions = predict_actions(model, _images(2), torch.tensor([0, 1]), torch.tensor([5.0, 5.0]), steer_decoding="mode")
    assert np.all(np.abs(actions[:, 1]) <= 1.0)
