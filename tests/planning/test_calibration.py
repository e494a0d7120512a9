from __future__ import annotations

import numpy as np
import pytest
import tomllib
import torch

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.planning.calibration import (
    CalibrationConfig,
    Fit,
    admissible,
    calibration_toml,
    edge_groups,
    effective_samples,
    fit_alpha,
    fit_gamma_d,
    fit_pilots,
    fit_score_curve,
    run_pilots,
    score_curve,
)
from crchfl_sumo.planning.plan_command import load_plan_configs

CURVE = (0.9, 1.5, 0.4)  # score(S) = 0.9 - 1.5 S^-0.4


def test_score_curve_fit_recovers_known_parameters():
    sizes = np.array([10.0, 30.0, 100.0, 300.0, 1000.0])
    (a, b, c), rms = fit_score_curve(sizes, score_curve(sizes, *CURVE))
    assert (a, b, c) == pytest.approx(CURVE, rel=1e-4)
    assert rms < 1e-8


def test_effective_samples_inverts_the_curve_and_clips():
    for size in (5.0, 50.0, 777.0):
        assert effective_samples(CURVE, float(score_curve(size, *CURVE)), 1e6) == pytest.approx(size, rel=1e-9)
    assert effective_samples(CURVE, 0.95, 1234.0) == 1234.0  # above the asymptote: the cap
    assert effective_samples(CURVE, float(score_curve(5000.0, *CURVE)), 1000.0) == 1000.0


def test_alpha_recovered_from_hand_made_pilots():
    x = [20, 50, 120]
    alpha, rms = fit_alpha(x, [0.35 * v for v in x])
    assert alpha == pytest.approx(0.35) and rms == pytest.approx(0.0, abs=1e-9)
    # through the origin: x . e / x . x
    alpha, _ = fit_alpha([1, 2], [1, 3])
    assert alpha == pytest.approx((1 + 6) / 5)


def test_gamma_and_d_recovered_from_hand_made_pilots():
    s = 300.0
    runs = [(2, 1, 1), (5, 1, 1), (5, 1, 2), (4, 2, 3)]
    t = [ie * ic * T for ie, ic, T in runs]
    y = [s * T for _, _, T in runs]
    e = [0.6 * (1 - 1.5 / ti) * yi for ti, yi in zip(t, y)]
    gamma, d, rms = fit_gamma_d(t, y, e)
    assert gamma == pytest.approx(0.6) and d == pytest.approx(1.5) and rms < 1e-9


def test_fit_pilots_end_to_end_on_synthetic_scores():
    s = 300
    alpha, gamma, d = 0.4, 0.7, 1.5
    curve = lambda size: float(score_curve(size, *CURVE))  # noqa: E731
    runs = [(2, 1, 1), (5, 1, 1), (5, 1, 2), (3, 2, 2)]
    data = {
        "metric": "loss",
        "local_samples": s,
        "reference_samples": [30, 60, 120, 210, 300],
        "reference_scores": [curve(v) for v in (30, 60, 120, 210, 300)],
        "pretrain_samples": [45, 90, 180],
        "pretrain_scores": [curve(alpha * x) for x in (45, 90, 180)],
        "hfl": [
            {"edge_interval": ie, "cloud_interval": ic, "cloud_rounds": T,
             "score": curve(gamma * (1 - d / (ie * ic * T)) * s * T)}
            for ie, ic, T in runs
        ],
    }
    fit, derived = fit_pilots(data)
    assert (fit.alpha, fit.gamma, fit.d) == pytest.approx((alpha, gamma, d), rel=1e-3)
    assert derived["hfl_t"] == [2, 5, 10, 12]


def test_admissible_clips_to_problem_p():
    assert admissible(1.3, -0.1, -2.0) == (1.0, 0.0, 0.0)
    assert admissible(0.2, 0.5, 3.0) == (0.2, 0.5, 3.0)


def test_calibration_file_is_read_by_plan(tmp_path):
    fit = Fit(0.25, 0.8, 1.75, (1.0, 2.0, 0.5), 0.01, 3.0, 4.0)
    data = {
        "metric": "loss", "local_samples": 10, "test_samples": 4, "epochs": 2,
        "reference_samples": [1, 2, 5, 10], "reference_scores": [-3.0, -2.5, -2.0, -1.9],
        "pretrain_samples": [2], "pretrain_scores": [-2.6],
        "hfl": [{"edge_interval": 2, "cloud_interval": 1, "cloud_rounds": 1, "score": -2.1}],
        "train_s_per_sample_epoch": 0.0025,
    }
    derived = {"pretrain_effective": [1.5], "hfl_effective": [6.0]}
    path = tmp_path / "calibration.toml"
    path.write_text(calibration_toml(fit, data, derived, seed=3, scenario="paper"))
    allocation, _ = load_plan_configs(path)
    assert (allocation.alpha, allocation.gamma, allocation.d) == (0.25, 0.8, 1.75)
    assert tomllib.loads(path.read_text())["calibration"]["train_s_per_sample_epoch"] == 0.0025


def test_calibration_file_holds_admissible_values_only(tmp_path):
    fit = Fit(1.7, 0.3, -0.5, (1.0, 2.0, 0.5), 0.0, 0.0, 0.0)
    data = {
        "metric": "accuracy", "local_samples": 10, "test_samples": 4, "epochs": 2,
        "reference_samples": [1, 2], "reference_scores": [0.1, 0.2],
        "pretrain_samples": [2], "pretrain_scores": [0.1],
        "hfl": [{"edge_interval": 2, "cloud_interval": 1, "cloud_rounds": 1, "score": 0.2}],
    }
    path = tmp_path / "c.toml"
    path.write_text(calibration_toml(fit, data, {"pretrain_effective": [1.0], "hfl_effective": [2.0]}, 0, "paper"))
    allocation, _ = load_plan_configs(path)
    assert (allocation.alpha, allocation.gamma, allocation.d) == (1.0, 0.3, 0.0)


def test_config_rejects_unfittable_sizes():
    with pytest.raises(CrchflError, match="reference_fractions"):
        CalibrationConfig(reference_fractions=(0.5, 1.0))
    with pytest.raises(CrchflError, match="hfl_runs"):
        CalibrationConfig(hfl_runs=((2, 1, 1), (1, 2, 1)))


def test_edge_groups_one_edge_per_town():
    assert edge_groups(["t02_data_1", "t01_data_0", "t02_data_0"]) == [["t01_data_0"], ["t02_data_0", "t02_data_1"]]


def _random_samples(n: int, rng: np.random.Generator) -> Samples:
    return Samples.from_numpy(
        rng.integers(0, 256, size=(n, 4, 48, 64, 3), dtype=np.uint8),
        rng.random((n, 3), dtype=np.float32),
        rng.integers(0, 7, size=n).astype(np.int64),
        rng.integers(0, 4, size=n),
        rng.uniform(0, 14, size=n),
        rng.uniform(0, 14, size=n),
    )


def test_run_pilots_tiny_end_to_end_is_seeded():
    rng = np.random.default_rng(0)
    vehicles = {"t01_data_0": _random_samples(6, rng), "t02_data_0": _random_samples(4, rng)}
    test = _random_samples(5, rng)
    config = CalibrationConfig(
        reference_fractions=(0.3, 0.5, 0.8, 1.0), epochs=1, pretrain_fractions=(0.5,), hfl_runs=((1, 1, 1), (2, 1, 1))
    )
    torch.set_num_threads(1)
    first = run_pilots(vehicles, test, config, seed=1)
    again = run_pilots(vehicles, test, config, seed=1)
    # everything but the measured training speed is seeded
    assert first.pop("train_s_per_sample_epoch") > 0 and again.pop("train_s_per_sample_epoch") > 0
    assert first == again
    assert first["reference_samples"] == [3, 5, 8, 10] and first["pretrain_samples"] == [5]
    assert [r["edge_interval"] for r in first["hfl"]] == [1, 2]
    assert all(np.isfinite(v) for v in first["reference_scores"] + first["pretrain_scores"])
