from __future__ import annotations

import weakref

import pytest
import torch

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.learning.aggregate import RunningAverage, fedavg, weighted_average


def _state(w: list[float], b: float, count: int) -> dict[str, torch.Tensor]:
    return {
        "w": torch.tensor(w, dtype=torch.float32),
        "b": torch.tensor([b], dtype=torch.float32),
        "bn.num_batches_tracked": torch.tensor(count, dtype=torch.int64),
    }


def test_weighted_average_by_hand():
    # weights 1 and 3: result = 0.25 * a + 0.75 * b
    a = _state([1.0, 2.0], 4.0, 10)
    b = _state([5.0, -2.0], 0.0, 20)
    out = weighted_average([a, b], [1, 3])
    assert torch.equal(out["w"], torch.tensor([4.0, -1.0]))
    assert torch.equal(out["b"], torch.tensor([1.0]))
    # integer buffer: 0.25 * 10 + 0.75 * 20 = 17.5 -> rounds to even 18
    assert out["bn.num_batches_tracked"].item() == 18
    assert out["bn.num_batches_tracked"].dtype == torch.int64
    assert out["w"].dtype == torch.float32


def test_paper_sample_counts_three_vehicles():
    # Town02 of the paper: 2586, 2587 and 1555 samples.
    counts = [2586, 2587, 1555]
    states = [{"p": torch.tensor([float(v)])} for v in (1.0, 2.0, 3.0)]
    out = weighted_average(states, counts)
    expected = (2586 * 1 + 2587 * 2 + 1555 * 3) / sum(counts)
    assert out["p"].item() == pytest.approx(expected, rel=1e-7)


def test_float64_accumulation_then_cast_back():
    # In float16, 2049 is not representable; the average of 2048 and 2050 is.
    a = {"p": torch.tensor([2048.0], dtype=torch.float16)}
    b = {"p": torch.tensor([2050.0], dtype=torch.float16)}
    out = weighted_average([a, b], [1, 1])
    assert out["p"].dtype == torch.float16
    assert out["p"].item() == 2048.0  # exact mean 2049, cast to float16 rounds half to even
    gen = torch.Generator().manual_seed(0)
    states = [{"p": torch.randn(1000, generator=gen)} for _ in range(7)]
    counts = [2928, 2928, 2586, 2587, 1555, 1, 13]
    reference = sum(c * s["p"].double() for c, s in zip(counts, states)) / sum(counts)
    assert torch.allclose(weighted_average(states, counts)["p"], reference.float(), rtol=0, atol=1e-7)
    c = {"p": torch.tensor([1e-8], dtype=torch.float64)}
    d = {"p": torch.tensor([3e-8], dtype=torch.float64)}
    assert weighted_average([c, d], [1, 1])["p"].item() == pytest.approx(2e-8, rel=1e-15)


def test_equal_integer_buffers_stay_exact():
    states = [_state([0.0, 0.0], 0.0, 7) for _ in range(3)]
    out = weighted_average(states, [3, 5, 11])
    assert out["bn.num_batches_tracked"].item() == 7


def test_zero_weight_model_is_ignored():
    a = _state([1.0, 1.0], 1.0, 1)
    b = _state([100.0, 100.0], 100.0, 100)
    out = weighted_average([a, b], [2, 0])
    assert torch.equal(out["w"], a["w"])


def test_inputs_not_mutated_and_outputs_are_new_memory():
    a = _state([1.0, 2.0], 4.0, 10)
    b = _state([5.0, -2.0], 0.0, 20)
    copies = [{k: v.clone() for k, v in s.items()} for s in (a, b)]
    out = weighted_average([a, b], [1, 1])
    for original, copy in zip((a, b), copies):
        for key in original:
            assert torch.equal(original[key], copy[key])
    out["w"].add_(1000.0)
    assert torch.equal(a["w"], copies[0]["w"])
    single = weighted_average([a], [5])
    assert torch.equal(single["w"], a["w"])
    assert single["w"].data_ptr() != a["w"].data_ptr()


def test_running_average_by_hand_and_equal_to_the_batch_to_the_bit():
    running = RunningAverage([1, 3])
    running.add(_state([1.0, 2.0], 4.0, 10))
    running.add(_state([5.0, -2.0], 0.0, 20))
    out = running.result()
    assert torch.equal(out["w"], torch.tensor([4.0, -1.0])) and out["bn.num_batches_tracked"].item() == 18
    gen = torch.Generator().manual_seed(1)
    states = [{"w": torch.randn(64, 32, generator=gen), "n": torch.tensor(i, dtype=torch.int64)} for i in range(9)]
    counts = [2928, 2586, 2587, 1555, 1, 13, 0, 7, 449]
    running = RunningAverage(counts)
    for state in states:
        running.add(state)
    folded, batch = running.result(), weighted_average(states, counts)
    assert list(folded) == ["w", "n"] and all(torch.equal(folded[k], batch[k]) for k in batch)
    # and the FedAvg itself, summed another way
    reference = sum(c * s["w"].double() for c, s in zip(counts, states)) / sum(counts)
    assert torch.allclose(folded["w"], reference.float(), rtol=0, atol=1e-7)


def test_running_average_keeps_no_state_it_was_given():
    running = RunningAverage([1, 1])
    dropped = []
    first = {"w": torch.ones(1000)}
    weakref.finalize(first["w"], dropped.append, "first")
    running.add(first)
    del first
    assert dropped == ["first"]  # only its share of the sum is left
    running.add({"w": torch.full((1000,), 3.0)})
    assert torch.equal(running.result()["w"], torch.full((1000,), 2.0))


def test_running_average_wants_one_state_per_weight_and_gives_its_result_once():
    running = RunningAverage([1, 2])
    running.add({"p": torch.zeros(2)})
    with pytest.raises(CrchflError, match="1 states but 2 weights"):
        running.result()
    running.add({"p": torch.ones(2)})
    with pytest.raises(CrchflError, match="more than 2 states"):
        running.add({"p": torch.ones(2)})
    assert torch.allclose(running.result()["p"], torch.full((2,), 2 / 3))
    with pytest.raises(CrchflError, match="taken already"):
        running.result()
    with pytest.raises(CrchflError, match="keys differ"):
        mismatched = RunningAverage([1, 1])
        mismatched.add({"p": torch.zeros(2)})
        mismatched.add({"q": torch.zeros(2)})


def test_numpy_sample_counts_are_weights():
    import numpy as np

    out = weighted_average([{"p": torch.tensor([0.0])}, {"p": torch.tensor([4.0])}], list(np.array([1, 3])))
    assert out["p"].item() == 3.0


def test_fedavg_pairs():
    out = fedavg([({"p": torch.tensor([0.0])}, 1), ({"p": torch.tensor([4.0])}, 3)])
    assert out["p"].item() == 3.0


@pytest.mark.parametrize(
    "states, weights, fragment",
    [
        ([], [], "no states"),
        ([{"p": torch.zeros(2)}], [1, 2], "one weight per state"),
        ([{"p": torch.zeros(2)}, {"q": torch.zeros(2)}], [1, 1], "keys differ"),
        ([{"p": torch.zeros(2)}, {"p": torch.zeros(3)}], [1, 1], "shape"),
        ([{"p": torch.zeros(2)}, {"p": torch.zeros(2, dtype=torch.float64)}], [1, 1], "dtype"),
        ([{"p": torch.zeros(2)}, {"p": torch.zeros(2)}], [0, 0], "sum to zero"),
        ([{"p": torch.zeros(2)}], [-1], ">= 0"),
        ([{"p": torch.zeros(2)}], [float("nan")], ">= 0"),
        ([{"p": torch.zeros(2, dtype=torch.bool)}], [1], "no average"),
    ],
)
def test_rejects_bad_input(states, weights, fragment):
    with pytest.raises(CrchflError, match=fragment):
        weighted_average(states, weights)


def test_fedavg_empty():
    with pytest.raises(CrchflError):
        fedavg([])
