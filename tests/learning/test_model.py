import io

import numpy as np
import pytest
import torch

from crchfl_sumo.core.config import from_mapping, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.labels import STEER_CLASS_VALUES
from crchfl_sumo.learning.model import (
    DrivingModel,
    GridAveragePool,
    ModelConfig,
    build_model,
    count_parameters,
    model_from_state,
    predict_actions,
    state_size_bytes,
)

SMALL = ModelConfig("compact", 48, 64)


def _images(n, config=SMALL, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 4, config.image_height, config.image_width, 3), dtype=torch.uint8, generator=g)


@pytest.mark.parametrize("height,width", [(48, 64), (66, 200), (64, 96)])
def test_output_shapes_and_ranges(height, width):
    config = ModelConfig("compact", height, width)
    throttle_brake, steer_logits = build_model(config, seed=0)(_images(5, config))
    assert throttle_brake.shape == (5, 2) and steer_logits.shape == (5, 7)
    assert throttle_brake.min() >= 0 and throttle_brake.max() <= 1
    assert torch.isfinite(steer_logits).all()


def test_parameter_count_does_not_depend_on_image_size():
    counts = {count_parameters(DrivingModel(ModelConfig("compact", h, w))) for h, w in [(48, 64), (66, 200), (90, 160)]}
    assert len(counts) == 1
    assert 300_000 < counts.pop() < 1_000_000


def test_same_seed_same_weights_and_other_seed_differs():
    a, b, c = (build_model(SMALL, seed=s).state_dict() for s in (3, 3, 4))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_branches_see_their_cameras_in_order():
    model = build_model(SMALL, seed=0)
    seen = {}
    model.branch_throttle_brake.register_forward_pre_hook(lambda m, args: seen.update(head=args[0]))
    model.branch_steer.register_forward_pre_hook(lambda m, args: seen.update(sides=args[0]))
    images = _images(2)
    model(images)
    normalised = images.float() / 127.5 - 1
    assert torch.allclose(seen["head"], normalised[:, 0].permute(0, 3, 1, 2), atol=1e-6)
    for k, camera in enumerate((1, 2, 3)):  # CamF, CamL, CamR -> channels 0-2, 3-5, 6-8
        assert torch.allclose(seen["sides"][:, 3 * k : 3 * k + 3], normalised[:, camera].permute(0, 3, 1, 2), atol=1e-6)
    assert seen["head"].min() >= -1 and seen["head"].max() <= 1


def test_predict_actions_decodes_steer_with_the_dac():
    model = build_model(SMALL, seed=0)
    last = model.branch_steer.layers[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0, 0, 0, 0, 0, 5.0, 0]))  # class 5 always wins
    actions = predict_actions(model, _images(3))
    assert actions.shape == (3, 3) and actions.dtype == np.float32
    assert actions[:, 1] == pytest.approx([-0.275] * 3)
    assert ((actions[:, [0, 2]] >= 0) & (actions[:, [0, 2]] <= 1)).all()
    single = predict_actions(model, _images(1)[0])
    assert single.shape == (3,) and single[1] in STEER_CLASS_VALUES
    assert model.training  # the training flag is restored


def test_paper_size_matches_the_reference_implementation():
    model = DrivingModel(ModelConfig("paper"))
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
    config = ModelConfig("paper", 64, 96)
    assert from_mapping(ModelConfig, to_mapping(config)) == config
    assert to_mapping(config) == {"size": "paper", "image_height": 64, "image_width": 96}


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
    assert torch.equal(build_model(SMALL, seed=0)(images)[1], model_from_state(SMALL, state)(images)[1])


@pytest.mark.parametrize("height,width", [(5, 13), (1, 5), (7, 22), (2, 8)])
def test_grid_pool_equals_adaptive_average_pooling(height, width):
    x = torch.randn(3, 4, height, width)
    expected = torch.nn.functional.adaptive_avg_pool2d(x, (2, 8))
    assert torch.allclose(GridAveragePool((2, 8))(x), expected, atol=1e-6)
