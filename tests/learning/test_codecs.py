"""Update codecs: what a receiver decodes, what is left for error feedback, and the bytes."""

from __future__ import annotations

import math

import pytest
import torch

from crchfl_sumo.learning.codecs import encoded_fraction, int8_roundtrip, int8_transfer, kept_count, topk_roundtrip


def test_int8_is_off_by_at_most_half_a_step_and_counters_travel_whole():
    torch.manual_seed(0)
    delta = {"w": torch.randn(1000), "b": torch.zeros(5), "n": torch.tensor(7)}
    out = int8_roundtrip(delta)
    scale = float(delta["w"].abs().max()) / 127.0
    assert float((out["w"] - delta["w"]).abs().max()) <= scale / 2 + 1e-7
    assert len(torch.unique(out["w"])) <= 255  # 8 bits
    assert torch.equal(out["b"], torch.zeros(5)) and int(out["n"]) == 7
    # the largest entry is exact: it is 127 steps
    i = int(delta["w"].abs().argmax())
    assert float(out["w"][i]) == pytest.approx(float(delta["w"][i]), rel=1e-6)


def test_an_int8_transfer_is_the_reference_plus_the_quantized_difference():
    reference = {"w": torch.tensor([1.0, 2.0, 3.0])}
    model = {"w": torch.tensor([1.5, 2.0, 2.0])}  # difference 0.5, 0, -1: scale 1 / 127
    out = int8_transfer(model, reference)
    step = 1.0 / 127
    expected = [1.0 + round(0.5 / step) * step, 2.0, 3.0 - 1.0]
    assert out["w"].tolist() == pytest.approx(expected, abs=1e-6)


def test_topk_sends_the_largest_entries_and_the_residual_carries_over():
    delta = {"w": torch.tensor([0.1, -5.0, 0.2, 3.0]), "n": torch.tensor(2)}
    sent, left = topk_roundtrip(delta, 0.5)  # keeps 2 of 4
    assert sent["w"].tolist() == [0.0, -5.0, 0.0, 3.0] and left["w"].tolist() == pytest.approx([0.1, 0.0, 0.2, 0.0])
    assert torch.equal(sent["w"] + left["w"], delta["w"]) and int(sent["n"]) == 2
    # next upload: what was left is added; 0.2 + 0.15 now beats the new entries
    nxt = {"w": torch.tensor([0.0, 0.01, 0.15, 0.02]), "n": torch.tensor(2)}
    sent2, left2 = topk_roundtrip(nxt, 0.25, left)
    assert sent2["w"].tolist() == pytest.approx([0.0, 0.0, 0.35, 0.0])
    assert torch.equal(sent2["w"] + left2["w"], nxt["w"] + left["w"])


def test_encoded_bytes_by_hand():
    state = {"w": torch.zeros(100), "n": torch.zeros((), dtype=torch.int64)}  # 400 + 8 raw bytes
    assert encoded_fraction(state, "none") == 1.0
    assert encoded_fraction(state, "int8") == pytest.approx((100 + 4 + 8) / 408)
    # topk 1 %: one entry of w, its value (4) and index (4); the counter whole
    assert kept_count(100, 0.01) == 1 and kept_count(10, 0.01) == 1 and kept_count(0, 0.5) == 0
    assert encoded_fraction(state, "topk", 0.01) == pytest.approx((8 + 8) / 408)
    assert encoded_fraction(state, "topk", 0.1) == pytest.approx((10 * 8 + 8) / 408)
    assert math.isclose(encoded_fraction({"w": torch.zeros(4, dtype=torch.float64)}, "int8"), (4 + 4) / 32)
