"""Channel model: TR 38.901 formulas against hand-computed values, noise, rate, AR(1) statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.links import channel as ch
from crchfl_sumo.links.channel import ChannelConfig, WirelineConfig

UMI = ChannelConfig()  # 5.9 GHz, h_UT = 1.5 m; sites at 10 m below
UMA = ChannelConfig(scenario="uma", carrier_hz=3.5e9)


def test_noise_power_of_20_mhz_with_9_db_noise_figure():
    # -174 + 10 log10(20e6) + 9 = -174 + 73.0103 + 9 = -91.9897 dBm
    assert ch.noise_power_dbm(20e6, 9.0) == pytest.approx(-91.9897, abs=1e-4)


def test_breakpoint_distance_umi():
    # d'BP = 4 (10 - 1)(1.5 - 1) 5.9e9 / 299792458 = 18 * 5.9e9 / 299792458 = 354.245 m
    assert ch.breakpoint_distance_m(10.0, 1.5, 5.9e9) == pytest.approx(354.245, abs=1e-3)


def test_umi_los_path_loss_before_breakpoint():
    # d2D = 100 m: d3D = sqrt(100^2 + 8.5^2) = 100.3606; log10 = 2.0015630
    # PL1 = 32.4 + 21 * 2.0015630 + 20 * log10(5.9) = 32.4 + 42.03282 + 15.41704 = 89.84986 dB
    assert ch.los_path_loss_db(100.0, 10.0, UMI) == pytest.approx(89.84986, abs=1e-4)


def test_umi_los_path_loss_beyond_breakpoint():
    # d2D = 500 m > d'BP = 354.245 m: d3D = 500.07224, log10 = 2.6990328
    # PL2 = 32.4 + 40 * 2.6990328 + 15.41704 - 9.5 * log10(354.245^2 + 8.5^2)
    #     = 32.4 + 107.96131 + 15.41704 - 9.5 * 5.0988576 = 155.77835 - 48.43915 = 107.33920 dB
    assert ch.los_path_loss_db(500.0, 10.0, UMI) == pytest.approx(107.33920, abs=1e-4)


def test_umi_nlos_path_loss_takes_the_larger_formula():
    # d2D = 300 m: d3D = 300.12039, log10 = 2.4772955
    # PL'NLOS = 35.3 * 2.4772955 + 22.4 + 21.3 * log10(5.9) = 87.44853 + 22.4 + 16.41915 = 126.26768 dB
    # PL_LOS  = 32.4 + 21 * 2.4772955 + 15.41704 = 99.84025 dB; max -> 126.26768 dB
    assert ch.nlos_path_loss_db(300.0, 10.0, UMI) == pytest.approx(126.26768, abs=1e-4)
    assert ch.path_loss_db(300.0, 10.0, False, UMI) == pytest.approx(126.26768, abs=1e-4)
    assert ch.path_loss_db(300.0, 10.0, True, UMI) == pytest.approx(99.84025, abs=1e-4)


def test_uma_los_and_nlos_path_loss():
    # UMa, 3.5 GHz, h_BS = 25 m: d'BP = 4 * 24 * 0.5 * 3.5e9 / c = 560.39 m
    # d2D = 200 m: d3D = sqrt(200^2 + 23.5^2) = 201.37589, log10 = 2.3040075
    # PL1 = 28 + 22 * 2.3040075 + 20 * log10(3.5) = 28 + 50.68816 + 10.88136 = 89.56953 dB
    # PL'NLOS = 13.54 + 39.08 * 2.3040075 + 10.88136 = 13.54 + 90.04061 + 10.88136 = 114.46197 dB
    assert ch.los_path_loss_db(200.0, 25.0, UMA) == pytest.approx(89.56953, abs=1e-4)
    assert ch.nlos_path_loss_db(200.0, 25.0, UMA) == pytest.approx(114.46197, abs=1e-4)


def test_nlos_never_below_los_and_loss_grows_with_distance():
    d = np.linspace(1.0, 2000.0, 500)
    los, nlos = ch.los_path_loss_db(d, 10.0, UMI), ch.nlos_path_loss_db(d, 10.0, UMI)
    assert np.all(nlos >= los)
    assert np.all(np.diff(los) >= 0) and np.all(np.diff(nlos) >= 0)
    # below 10 m the 10 m value is used (validity range of the TR)
    assert ch.los_path_loss_db(2.0, 10.0, UMI) == ch.los_path_loss_db(10.0, 10.0, UMI)


def test_los_probability_values():
    # UMi: 1 up to 18 m; at 36 m: 18/36 + exp(-36/36)(1 - 18/36) = 0.5 + 0.5 e^-1 = 0.683940
    assert ch.los_probability(18.0) == 1.0
    assert ch.los_probability(36.0) == pytest.approx(0.683940, abs=1e-6)
    # UMa, h_UT <= 13 m: at 63 m: 18/63 + e^-1 (45/63) = 0.285714 + 0.262771 = 0.548485
    assert ch.los_probability(63.0, "uma") == pytest.approx(0.548485, abs=1e-6)
    p = ch.los_probability(np.linspace(18.0, 1000.0, 200))
    assert np.all(np.diff(p) < 0) and np.all((p > 0) & (p <= 1))


def test_expected_path_loss_lies_between_los_and_nlos():
    # d = 36 m: p = 0.683940, so PL = p LOS + (1 - p) NLOS in dB
    los, nlos = ch.los_path_loss_db(36.0, 10.0, UMI), ch.nlos_path_loss_db(36.0, 10.0, UMI)
    p = 0.683940
    assert ch.expected_path_loss_db(36.0, 10.0, UMI) == pytest.approx(p * los + (1 - p) * nlos, abs=1e-4)


def test_received_power_and_snr_link_budget():
    # 23 dBm + 3 dBi + 3 dBi - 89.84986 dB = -60.84986 dBm; SNR = -60.84986 + 91.98970 = 31.13984 dB
    rx = ch.received_power_dbm(89.84986, 0.0, UMI)
    assert rx == pytest.approx(-60.84986, abs=1e-5)
    assert ch.snr_db(rx, UMI) == pytest.approx(31.13984, abs=1e-4)


def test_shannon_rate_with_cap_efficiency_and_floor():
    # SNR 15 -> log2(16) = 4 bit/s/Hz; 20 MHz -> 80 Mbit/s
    assert ch.shannon_rate_bps(15.0, 20e6) == pytest.approx(80e6)
    # cap 3 bit/s/Hz -> 60 Mbit/s; efficiency 0.5 -> 0.5 * 4 = 2 bit/s/Hz -> 40 Mbit/s
    assert ch.shannon_rate_bps(15.0, 20e6, max_bps_per_hz=3.0) == pytest.approx(60e6)
    assert ch.shannon_rate_bps(15.0, 20e6, efficiency=0.5) == pytest.approx(40e6)
    # the cap applies after the efficiency: min(0.5 * 4, 1.5) = 1.5 -> 30 Mbit/s
    assert ch.shannon_rate_bps(15.0, 20e6, 1.5, 0.5) == pytest.approx(30e6)
    # below the minimum SNR nothing gets through
    assert ch.shannon_rate_bps(0.05, 20e6, min_snr_linear=0.1) == 0.0


def test_link_rate_uses_the_config_and_the_share():
    # SNR 15, default cap 5.55, efficiency 0.6: min(0.6 * 4, 5.55) = 2.4 bit/s/Hz
    # half of 20 MHz -> 10e6 * 2.4 = 24 Mbit/s; -10 dB floor = 0.1 linear
    assert ch.link_rate_bps(15.0, 0.5, UMI) == pytest.approx(24e6)
    assert ch.link_rate_bps(0.09, 1.0, UMI) == 0.0
    # very high SNR hits the cap: 20e6 * 5.55 = 111 Mbit/s
    assert ch.link_rate_bps(1e9, 1.0, UMI) == pytest.approx(111e6)


def test_ar1_keeps_unit_variance_and_exponential_correlation():
    rng = np.random.default_rng(0)
    x0 = rng.standard_normal(200_000)
    # 10 m along a 13 m decorrelation distance: rho = exp(-10/13) = 0.46336
    x1 = ch.ar1_step(x0, 10.0, 13.0, rng.standard_normal(x0.shape))
    assert np.std(x1) == pytest.approx(1.0, abs=0.01)
    assert np.corrcoef(x0, x1)[0, 1] == pytest.approx(math.exp(-10 / 13), abs=0.01)
    # no travel: unchanged; infinite travel: only the innovation is left
    assert np.array_equal(ch.ar1_step(x0, 0.0, 13.0, np.ones_like(x0)), x0)
    assert np.array_equal(ch.ar1_step(x0, np.inf, 13.0, np.ones_like(x0)), np.ones_like(x0))


def test_standard_normal_cdf():
    assert ch.standard_normal_cdf(0.0) == pytest.approx(0.5)
    assert ch.standard_normal_cdf(np.array([-1.959964, 1.959964])) == pytest.approx([0.025, 0.975], abs=1e-6)


def test_below_standard_normal_cdf_answers_as_the_exact_formula_even_at_ties():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.standard_normal(100_000) * 3.0, [-40.0, -9.0, 0.0, 9.0, 40.0]])
    p = np.concatenate([rng.random(100_000), [0.0, 1e-20, 0.5, 1.0, 1.0]])
    # thresholds at the exact value of Phi and one ulp either side: only the exact formula separates them
    exact = ch.standard_normal_cdf(x[:2000])
    x = np.concatenate([x, x[:2000], x[:2000], x[:2000]])
    p = np.concatenate([p, exact, np.nextafter(exact, 2.0), np.nextafter(exact, -1.0)])
    below = ch.below_standard_normal_cdf(x, p)
    assert np.array_equal(below, ch.standard_normal_cdf(x) < p)
    assert below[-4000:-2000].all() and not below[-6000:-4000].any()  # strictly below one ulp up, not at Phi


def test_coherence_time_from_doppler():
    # f_D = 10 * 5.9e9 / 299792458 = 196.80 Hz; T_c = 0.423 / 196.80 = 2.1494 ms
    assert ch.coherence_time_s(10.0, 5.9e9) == pytest.approx(2.1494e-3, rel=1e-4)
    # a stopped car uses the floor speed (1 m/s): 10x longer
    assert ch.coherence_time_s(0.0, 5.9e9) == pytest.approx(21.494e-3, rel=1e-4)


def test_wireline_rate():
    assert ch.wireline_rate_bps(WirelineConfig(rate_bps=1e9, latency_s=0.01)) == 1e9


def test_configs_from_toml_mapping_and_validation():
    table = {"carrier_hz": 3.5e9, "bandwidth_hz": 40e6, "los_mode": "expected"}
    cfg = from_mapping(ChannelConfig, table, "channel")
    assert cfg.carrier_hz == 3.5e9 and cfg.bandwidth_hz == 40e6 and cfg.los_mode == "expected"
    with pytest.raises(CrchflError, match="carrier_hz"):
        ChannelConfig(carrier_hz=5.9)  # GHz instead of Hz
    with pytest.raises(CrchflError, match="efficiency"):
        ChannelConfig(efficiency=1.5)
    with pytest.raises(CrchflError, match="los_mode"):
        from_mapping(ChannelConfig, {"los_mode": "sometimes"}, "channel")
    with pytest.raises(CrchflError, match="unknown key"):
        from_mapping(ChannelConfig, {"bandwith_hz": 1e6}, "channel")
    with pytest.raises(CrchflError, match="wireline.rate_bps"):
        WirelineConfig(rate_bps=0.0)
