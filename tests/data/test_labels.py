import numpy as np
import pytest

from crchfl_sumo.data.labels import STEER_CLASS_VALUES, digitize_steer, nearest_bin, steer_bin_values, steer_from_class


def test_dac_values_are_the_papers():
    assert steer_from_class(np.arange(7)).tolist() == pytest.approx(
        [0.0, 0.125, 0.275, 0.425, -0.125, -0.275, -0.425]
    )


def test_digitizer_inverts_dac_on_every_class():
    assert digitize_steer(steer_from_class(np.arange(7))).tolist() == list(range(7))


def test_digitizer_picks_nearest_value():
    # 0.2 is 0.075 from 0.125 and 0.075 from 0.275: tie goes to the lower index (class 1).
    steer = np.array([0.06, 0.07, 0.2, 0.21, 1.0, -0.3, -1.0, -0.06])
    assert digitize_steer(steer).tolist() == [0, 1, 1, 2, 3, 5, 6, 0]


def test_dac_rejects_unknown_class():
    with pytest.raises(ValueError):
        steer_from_class(np.array([7]))


def test_left_turn_value_is_negative_class():
    assert STEER_CLASS_VALUES[digitize_steer(-0.275)] == pytest.approx(-0.275)
    assert digitize_steer(-0.275) == 5


def test_steer_bins_are_the_papers_seven_or_evenly_spaced():
    assert steer_bin_values(7) is STEER_CLASS_VALUES
    assert np.allclose(steer_bin_values(21), np.arange(-10, 11) / 10)  # 0.1 apart, 0 in the middle
    assert steer_bin_values(21)[10] == 0.0
    assert nearest_bin(np.array([0.23, -0.46, 0.05, 1.7]), steer_bin_values(21)).tolist() == [12, 5, 10, 20]
