"""core.numbers: the argparse types and config checks of numbers, with hand-computed expectations."""

import argparse
import math

import numpy as np
import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import (
    SEED_MAX,
    check_range,
    check_seed,
    in_range,
    integer_arg,
    number_arg,
    range_text,
    seed_arg,
)


def test_range_text_and_in_range():
    assert range_text(0, 86400, lo_open=True) == "(0, 86400]"
    assert range_text(1, 8) == "[1, 8]"
    assert in_range(0.0, 0, 1) and not in_range(0.0, 0, 1, lo_open=True)
    assert in_range(1.0, 0, 1) and not in_range(1.0000001, 0, 1)
    assert not in_range(math.nan, 0, 1)  # NaN compares false: never in a range


def test_number_arg_takes_finite_numbers_in_range():
    seconds = number_arg(0, 60, "simulated seconds", lo_open=True)
    assert seconds("0.5") == 0.5 and seconds("60") == 60.0 and seconds("1e1") == 10.0
    for text, message in [
        ("nan", "nan is not a finite number; give simulated seconds in (0, 60]"),
        ("inf", "inf is not a finite number"),
        ("-inf", "-inf is not a finite number"),
        ("1e308", "1e308 is out of range; give simulated seconds in (0, 60]"),
        ("0", "0 is out of range"),
        ("60.001", "60.001 is out of range"),
        ("ten", "'ten' is not a number"),
    ]:
        with pytest.raises(argparse.ArgumentTypeError, match=message.replace("(", r"\(").replace("[", r"\[")):
            seconds(text)


def test_integer_arg_takes_integers_in_range():
    factor = integer_arg(1, 8, "a whole factor")
    assert factor("1") == 1 and factor("8") == 8
    with pytest.raises(argparse.ArgumentTypeError, match=r"9 is out of range; give a whole factor in 1 \.\. 8"):
        factor("9")
    with pytest.raises(argparse.ArgumentTypeError, match=r"'2.5' is not an integer"):
        factor("2.5")
    with pytest.raises(argparse.ArgumentTypeError, match="is out of range"):
        factor("9" * 400)


SEED_MESSAGE = r"outside the seed range; give an integer in 0 \.\. 2147483647"


def test_a_seed_is_0_to_2_pow_31_minus_1():
    assert SEED_MAX == 2147483647
    assert seed_arg("0") == 0 and seed_arg("2147483647") == 2147483647
    for text in ("-1", "2147483648", str(2**64)):
        with pytest.raises(argparse.ArgumentTypeError, match=SEED_MESSAGE):
            seed_arg(text)
    assert check_seed(7, "federation.seed") == 7
    with pytest.raises(CrchflError, match="federation.seed: 18446744073709551616 is outside the seed range"):
        check_seed(2**64, "federation.seed")
    with pytest.raises(CrchflError, match="federation.seed: True is not a seed"):
        check_seed(True, "federation.seed")


def test_the_seed_range_is_what_numpy_torch_and_sumo_take():
    import numpy as np
    import torch

    from crchfl_sumo.sumo.scenario import load_scenario
    from crchfl_sumo.sumo.simulation import Simulation

    for seed in (0, SEED_MAX):
        np.random.default_rng(seed)
        np.random.RandomState(seed)
        torch.Generator().manual_seed(seed)
    with pytest.raises(ValueError):
        np.random.default_rng(-1)
    with Simulation(load_scenario("town01"), seed=SEED_MAX) as sim:  # SUMO's --seed is a C int
        assert len(list(sim.run(0.5))) >= 1
    with pytest.raises(CrchflError, match="could not load"):
        with Simulation(load_scenario("town01"), seed=SEED_MAX + 1) as sim:
            list(sim.run(0.5))


def test_check_range_names_the_key_and_the_range():
    assert check_range(2.0, "channel.x", 0, 10, "metres") == 2.0
    with pytest.raises(CrchflError, match=r"channel.x: 11 is out of range; give metres in \[0, 10\]"):
        check_range(11.0, "channel.x", 0, 10, "metres")
    with pytest.raises(CrchflError, match=r"channel.x: nan is not a finite number; give metres in \(0, 10\]"):
        check_range(math.nan, "channel.x", 0, 10, "metres", lo_open=True)


def test_check_range_lets_inf_through_only_where_it_means_no_limit():
    assert check_range(math.inf, "federation.deadline_s", 0, 86400, "seconds", lo_open=True, inf_ok=True) == math.inf
    assert check_range(86400, "federation.deadline_s", 0, 86400, "seconds", inf_ok=True) == 86400  # the bound itself
    with pytest.raises(CrchflError, match=r"deadline_s: 86400.5 is out of range; give seconds in \(0, 86400\]"):
        check_range(86400.5, "federation.deadline_s", 0, 86400, "seconds", lo_open=True, inf_ok=True)
    with pytest.raises(CrchflError, match="-inf is not a finite number"):
        check_range(-math.inf, "federation.deadline_s", 0, 86400, "seconds", inf_ok=True)
    with pytest.raises(CrchflError, match="inf is not a finite number"):
        check_range(math.inf, "transfer.max_outage_s", 0, 86400, "seconds")
    with pytest.raises(CrchflError, match="True is not a number"):
        check_range(True, "x", 0, 1, "a share")
    assert check_range(np.int64(3), "x", 0, 10, "a count") == 3  # numpy integers are numbers


@pytest.mark.parametrize(
    "cls, key, good, bad",
    [  # each bound's edge: the largest value taken and the next one refused
        ("crchfl_sumo.federation.settings:FederationConfig", "deadline_s", 86400.0, 86401.0),
        ("crchfl_sumo.federation.settings:FederationConfig", "cloud_rounds", 100_000, 100_001),
        ("crchfl_sumo.links.transfer:TransferConfig", "max_outage_s", 86400.0, 86401.0),
        ("crchfl_sumo.links.channel:WirelineConfig", "rate_bps", 1e12, 1.1e12),
        ("crchfl_sumo.sumo.scenario:SumoConfig", "speed_limit_mps", 200.0, 201.0),
        ("crchfl_sumo.sumo.scenario:SumoConfig", "edge_site_count", 1000, 1001),
        ("crchfl_sumo.core.backend:BackendConfig", "task_timeout_s", 7 * 86400.0, 7 * 86400.0 + 1),
        ("crchfl_sumo.learning.settings:TrainConfig", "adam_eps", 1.0, 1.5),
        ("crchfl_sumo.data.settings:OnlineConfig", "max_samples", 100_000, 100_001),
        ("crchfl_sumo.vision.world:WorldConfig", "margin_m", 1000.0, 1001.0),
    ],
)
def test_config_bounds_take_their_edge_and_refuse_past_it(cls, key, good, bad):
    import importlib

    module, name = cls.split(":")
    config_class = getattr(importlib.import_module(module), name)
    assert getattr(config_class(**{key: good}), key) == good
    with pytest.raises(CrchflError, match=rf"\.{key}: .* out of range"):
        config_class(**{key: bad})
