"""`crchfl-sumo calibrate`: fit alpha, gamma and d of problem P from short pilot runs.

Problem P (crchfl_sumo.planning.problem) values x pretraining samples at alpha * x
and y = s * T federated samples at gamma * (1 - d / t) * y, t = I_e * I_c * T.
Both are "effective samples": the number of the vehicles' own samples that,
trained on centrally, give the same test score. The calibration measures that
exchange rate (docs/calibration.md):

1. Reference curve: centralized pilots on S samples of the vehicles' own data
   (several S), fitted by score(S) = a - b * S^(-c) (concave, increasing).
   The score is minus the test Loss (default) or the test Accuracy.
2. alpha: pretraining pilots (stage I: the cloud trains on x uploaded samples,
   split over the vehicles in proportion to their data) -> S_eff = score^-1
   -> alpha = least squares of S_eff = alpha * x through the origin.
3. gamma, d: HFL pilots (no pretraining) with several (I_e, I_c, T) ->
   S_eff = gamma * y - (gamma * d) * y / t, linear least squares in
   (gamma, gamma * d).

The fit is written as a TOML file whose ``[allocation]`` table `plan --config`
reads directly; ``[calibration]`` records the pilot data, sizes and residuals.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence

import numpy as np
import torch
from scipy.optimize import curve_fit

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.config import toml_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_EPOCHS, check_range, check_seed
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.learning.aggregate import weighted_average
from crchfl_sumo.learning.model import State, build_model, model_from_state
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.learning.training import evaluate, train_vehicle
from crchfl_sumo.planning.problem import split_pretrain_batch

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationConfig:
    """Sizes of the pilot runs (stated, small: a few minutes on 2 CPU cores with the quick data set).

    metric: "loss" (fit on minus the test Loss, default: it moves smoothly) or
        "accuracy" (test Accuracy, coarse on small test sets and flat at the majority class).
    reference_fractions: centralized pilots on these fractions of all local samples.
    epochs: epochs of every centralized and pretraining pilot (as local
        training and stage I count: epochs over the data, not gradient steps).
    pretrain_fractions: pretraining pilots on these fractions of all local samples (x).
    hfl_runs: HFL pilots as (edge_interval, cloud_interval, cloud_rounds).
    """

    metric: Literal["loss", "accuracy"] = "loss"
    reference_fractions: tuple[float, ...] = (0.4, 0.55, 0.7, 0.85, 1.0)
    epochs: int = 20
    pretrain_fractions: tuple[float, ...] = (0.2, 0.4, 0.6)
    hfl_runs: tuple[tuple[int, int, int], ...] = ((5, 2, 1), (5, 2, 2), (10, 2, 2))

    def __post_init__(self) -> None:
        if self.metric not in ("loss", "accuracy"):
            raise CrchflError(f"calibration.metric: {self.metric!r} is unknown; use 'loss' or 'accuracy'")
        if len(self.reference_fractions) < 4:
            raise CrchflError("calibration.reference_fractions: give at least 4 sizes (the curve has 3 parameters)")
        for key in ("reference_fractions", "pretrain_fractions"):
            if any(not 0 < f <= 1 for f in getattr(self, key)) or not getattr(self, key):
                raise CrchflError(f"calibration.{key}: every fraction must lie in (0, 1]")
        check_range(self.epochs, "calibration.epochs", 1, MAX_EPOCHS, "a number of epochs")
        if len(self.hfl_runs) < 2 or any(not 1 <= n <= MAX_EPOCHS for r in self.hfl_runs for n in r):
            raise CrchflError(f"calibration.hfl_runs: give at least 2 runs of (I_e, I_c, T), each in 1 .. {MAX_EPOCHS}")
        if len({ie * ic * t for ie, ic, t in self.hfl_runs}) < 2:
            raise CrchflError("calibration.hfl_runs: the runs need at least 2 different I_e * I_c * T to fit d")


@dataclass(frozen=True)
class Fit:
    """The fitted weights of problem P and the curve they were read off."""

    alpha: float
    gamma: float
    d: float
    curve: tuple[float, float, float]  # (a, b, c) of score(S) = a - b * S^(-c)
    curve_rms: float  # residual of the reference fit, in score units
    alpha_rms: float  # residual of S_eff = alpha x, in samples
    gamma_rms: float  # residual of S_eff = gamma (1 - d / t) y, in samples


# ------------------------------------------------------------------ fitting (pure)


C_BOUNDS = (0.05, 2.0)  # exponent c: learning curves of this kind lie well inside; keeps noisy fits from degenerating
EXTRAPOLATION = 2.0  # effective samples are read off the curve up to this multiple of the largest measured size


def score_curve(samples: np.ndarray, a: float, b: float, c: float) -> np.ndarray:
    """score(S) = a - b * S^(-c): concave and increasing for b, c > 0."""
    return a - b * np.power(np.asarray(samples, dtype=float), -c)


def fit_score_curve(samples: Sequence[float], scores: Sequence[float]) -> tuple[tuple[float, float, float], float]:
    """Least-squares (a, b, c) of ``score_curve`` with b >= 0 and c in C_BOUNDS, and the RMS residual."""
    s = np.asarray(samples, dtype=float)
    v = np.asarray(scores, dtype=float)
    if len(s) < 3 or len(s) != len(v) or np.any(s <= 0):
        raise CrchflError("calibration: the reference curve needs >= 3 positive sizes with one score each")
    span = max(float(v.max() - v.min()), 1e-6)
    p0 = (float(v.max()) + 0.1 * span, span * float(s.min()) ** 0.5, 0.5)
    params, _ = curve_fit(
        score_curve, s, v, p0=p0, bounds=([-np.inf, 0.0, C_BOUNDS[0]], [np.inf, np.inf, C_BOUNDS[1]]), maxfev=20000
    )
    a, b, c = (float(p) for p in params)
    rms = float(np.sqrt(np.mean((score_curve(s, a, b, c) - v) ** 2)))
    return (a, b, c), rms


def effective_samples(curve: tuple[float, float, float], score: float, max_samples: float) -> float:
    """S with score_curve(S) = score, clipped to [0, max_samples] (scores at or above the asymptote a give max)."""
    a, b, c = curve
    if b <= 0 or score >= a:
        return float(max_samples)
    value = (b / (a - score)) ** (1.0 / c)
    return float(min(max(value, 0.0), max_samples))


def fit_alpha(uploaded: Sequence[float], effective: Sequence[float]) -> tuple[float, float]:
    """alpha of S_eff = alpha * x by least squares through the origin, and the RMS residual (samples)."""
    x = np.asarray(uploaded, dtype=float)
    e = np.asarray(effective, dtype=float)
    if len(x) == 0 or len(x) != len(e) or not np.any(x > 0):
        raise CrchflError("calibration: alpha needs pretraining pilots with x > 0")
    alpha = float(x @ e / (x @ x))
    return alpha, float(np.sqrt(np.mean((alpha * x - e) ** 2)))


def fit_gamma_d(
    epochs_total: Sequence[float], federated: Sequence[float], effective: Sequence[float]
) -> tuple[float, float, float]:
    """(gamma, d, RMS residual) of S_eff = gamma * (1 - d / t) * y.

    Linear least squares in (g, h) = (gamma, gamma * d): S_eff = g * y - h * y / t.
    """
    t = np.asarray(epochs_total, dtype=float)
    y = np.asarray(federated, dtype=float)
    e = np.asarray(effective, dtype=float)
    if len(t) < 2 or not (len(t) == len(y) == len(e)) or np.any(t <= 0):
        raise CrchflError("calibration: gamma and d need >= 2 HFL pilots with t = I_e * I_c * T > 0")
    design = np.column_stack([y, -y / t])
    (g, h), *_ = np.linalg.lstsq(design, e, rcond=None)
    residual = design @ np.array([g, h]) - e
    d = float(h / g) if g != 0 else 0.0
    return float(g), d, float(np.sqrt(np.mean(residual**2)))


def admissible(alpha: float, gamma: float, d: float) -> tuple[float, float, float]:
    """Clip to what problem P admits: alpha, gamma in [0, 1], d >= 0 (docs/calibration.md)."""
    return min(max(alpha, 0.0), 1.0), min(max(gamma, 0.0), 1.0), max(d, 0.0)


# ------------------------------------------------------------------ pilot runs


def _score(metrics, metric: str) -> float:
    return float(metrics.accuracy) if metric == "accuracy" else -float(metrics.loss)


def _train_and_score(
    state: State,
    train: Samples,
    test: Samples,
    epochs: int,
    model_config: ModelConfig,
    train_config: TrainConfig,
    seed: int,
    metric: str,
) -> tuple[float, float]:
    """(test score, wall seconds of the training alone)."""
    started = time.perf_counter()
    new_state, _ = train_vehicle(state, train, epochs, model_config, train_config, seed)
    train_s = time.perf_counter() - started
    model = model_from_state(model_config, new_state, torch.device("cpu"))
    return _score(evaluate(model, test, train_config), metric), train_s


def _prefix(samples: Samples, count: int, rng: np.random.Generator) -> Samples:
    return samples.subset(np.sort(rng.permutation(len(samples))[:count]))


def edge_groups(vehicles: Sequence[str]) -> list[list[str]]:
    """Vehicles grouped by town, one edge per town (vehicle ids start with the town: ``t01_data_0``)."""
    groups: dict[str, list[str]] = {}
    for vehicle in sorted(vehicles):
        groups.setdefault(vehicle.split("_")[0], []).append(vehicle)
    return list(groups.values())


def hfl_pilot(
    initial: State,
    vehicle_samples: Mapping[str, Samples],
    edge_interval: int,
    cloud_interval: int,
    cloud_rounds: int,
    model_config: ModelConfig,
    train_config: TrainConfig,
    seed: int,
) -> State:
    """HFL without a network: I_e local epochs, edge FedAvg, I_c times, then cloud FedAvg; T rounds."""
    groups = edge_groups(list(vehicle_samples))
    cloud = initial
    for round_index in range(cloud_rounds):
        edge_states: list[State] = [cloud for _ in groups]
        for step in range(cloud_interval):
            for e, group in enumerate(groups):
                trained = [
                    train_vehicle(
                        edge_states[e], vehicle_samples[v], edge_interval, model_config, train_config,
                        seed + 1000 * (round_index * cloud_interval + step) + i,
                    )[0]
                    for i, v in enumerate(group)
                ]
                edge_states[e] = weighted_average(trained, [len(vehicle_samples[v]) for v in group])
        cloud = weighted_average(edge_states, [sum(len(vehicle_samples[v]) for v in g) for g in groups])
    return cloud


def run_pilots(
    vehicle_samples: Mapping[str, Samples],
    test: Samples,
    config: CalibrationConfig,
    seed: int,
    model_config: ModelConfig | None = None,
    train_config: TrainConfig = TrainConfig(device="cpu"),
) -> dict[str, Any]:
    """Run every pilot; returns the measured data (sizes and scores) for ``fit_pilots``."""
    if not vehicle_samples or any(len(s) == 0 for s in vehicle_samples.values()) or len(test) == 0:
        raise CrchflError("calibrate: the data set needs training samples for every vehicle and a test set")
    height, width = test.image_hw
    model_config = model_config or ModelConfig(image_height=height, image_width=width)
    initial = {k: v.detach().clone() for k, v in build_model(model_config, seed).state_dict().items()}
    rng = np.random.default_rng(seed)
    everything = Samples.concat([vehicle_samples[v] for v in sorted(vehicle_samples)])
    total = len(everything)
    metric = config.metric

    reference_sizes = sorted({max(1, round(f * total)) for f in config.reference_fractions})
    reference_scores = []
    train_s = 0.0  # wall time of the reference training alone: this machine's speed (not part of the fit)
    for size in reference_sizes:
        subset = _prefix(everything, size, rng)
        score, seconds = _train_and_score(initial, subset, test, config.epochs, model_config, train_config, seed, metric)
        train_s += seconds
        reference_scores.append(score)
        log.info("calibrate: reference S=%d score %.4f", size, score)

    counts = {v: len(s) for v, s in vehicle_samples.items()}
    uploaded = sorted({max(1, round(f * total)) for f in config.pretrain_fractions})
    pretrain_scores = []
    for x in uploaded:
        shares = split_pretrain_batch(x, counts)
        batch = Samples.concat([_prefix(vehicle_samples[v], n, rng) for v, n in sorted(shares.items()) if n])
        score, _ = _train_and_score(initial, batch, test, config.epochs, model_config, train_config, seed + 1, metric)
        pretrain_scores.append(score)
        log.info("calibrate: pretraining x=%d score %.4f", x, score)

    hfl = []
    for ie, ic, rounds in config.hfl_runs:
        state = hfl_pilot(initial, vehicle_samples, ie, ic, rounds, model_config, train_config, seed + 2)
        model = model_from_state(model_config, state, torch.device("cpu"))
        score = _score(evaluate(model, test, train_config), metric)
        hfl.append({"edge_interval": ie, "cloud_interval": ic, "cloud_rounds": rounds, "score": score})
        log.info("calibrate: HFL (%d, %d, %d) score %.4f", ie, ic, rounds, score)

    return {
        "metric": metric,
        "local_samples": total,
        "test_samples": len(test),
        "epochs": config.epochs,
        "reference_samples": reference_sizes,
        "reference_scores": reference_scores,
        "pretrain_samples": uploaded,
        "pretrain_scores": pretrain_scores,
        "hfl": hfl,
        "train_s_per_sample_epoch": train_s / (config.epochs * sum(reference_sizes)),
    }


def fit_pilots(data: Mapping[str, Any]) -> tuple[Fit, dict[str, list[float]]]:
    """Fit the curve, alpha, gamma and d to ``run_pilots``' data; also returns the effective samples read off."""
    curve, curve_rms = fit_score_curve(data["reference_samples"], data["reference_scores"])
    s = data["local_samples"]
    cap = EXTRAPOLATION * max(data["reference_samples"])
    pretrain_eff = [effective_samples(curve, v, cap) for v in data["pretrain_scores"]]
    alpha, alpha_rms = fit_alpha(data["pretrain_samples"], pretrain_eff)
    t = [r["edge_interval"] * r["cloud_interval"] * r["cloud_rounds"] for r in data["hfl"]]
    y = [s * r["cloud_rounds"] for r in data["hfl"]]
    hfl_eff = [effective_samples(curve, r["score"], cap) for r in data["hfl"]]
    gamma, d, gamma_rms = fit_gamma_d(t, y, hfl_eff)
    fit = Fit(alpha, gamma, d, curve, curve_rms, alpha_rms, gamma_rms)
    return fit, {"pretrain_effective": pretrain_eff, "hfl_effective": hfl_eff, "hfl_t": t, "hfl_y": y}


# ------------------------------------------------------------------ file and command


def calibration_toml(fit: Fit, data: Mapping[str, Any], derived: Mapping[str, Any], seed: int, scenario: str) -> str:
    """The calibration file: ``[allocation]`` (read by `plan --config`) and ``[calibration]`` (the record)."""
    alpha, gamma, d = admissible(fit.alpha, fit.gamma, fit.d)
    record: dict[str, Any] = {
        "scenario": scenario,
        "seed": seed,
        "fitted_alpha": fit.alpha,
        "fitted_gamma": fit.gamma,
        "fitted_d": fit.d,
        "curve_a_b_c": list(fit.curve),
        "curve_rms": fit.curve_rms,
        "alpha_rms_samples": fit.alpha_rms,
        "gamma_rms_samples": fit.gamma_rms,
    }
    for key in ("metric", "local_samples", "test_samples", "epochs", "reference_samples", "reference_scores",
                "pretrain_samples", "pretrain_scores"):
        record[key] = data[key]
    for key in ("edge_interval", "cloud_interval", "cloud_rounds", "score"):
        record[f"hfl_{key}{'s' if key == 'score' else ''}"] = [r[key] for r in data["hfl"]]
    for key in ("pretrain_effective", "hfl_effective"):
        record[key] = derived[key]
    if "train_s_per_sample_epoch" in data:  # measured, so it differs from run to run; the fit does not use it
        record["train_s_per_sample_epoch"] = data["train_s_per_sample_epoch"]
    tables = {"allocation": {"alpha": alpha, "gamma": gamma, "d": d}, "calibration": record}
    return "# Written by `crchfl-sumo calibrate` (docs/calibration.md).\n" + toml_text(tables)


def calibrate_command(
    out: str | Path = "calibration.toml",
    seed: int = 0,
    scenario: str = "paper",
    dataset: str | Path | None = None,
    config: CalibrationConfig = CalibrationConfig(),
) -> Fit:
    """``crchfl-sumo calibrate [--out FILE] [--seed S] [--scenario NAME] [--dataset DIR]``.

    Without ``dataset`` generates the pilot data set (the quick reproduction's
    size) in ``OUT.data/`` (kept, reused on the next call). One torch thread:
    the pilots are small and the machine is shared.
    """
    from crchfl_sumo.data.dataset import load_samples, load_vehicle_samples

    check_seed(seed, "calibrate_command: seed")
    out = Path(out)
    if dataset is None:
        dataset = out.with_name(out.name + ".data")
        _generate_pilot_data(scenario, Path(dataset), seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        vehicles = load_vehicle_samples(dataset, "train")
        test = load_samples(dataset, "test")
        data = run_pilots(vehicles, test, config, seed)
    finally:
        torch.set_num_threads(threads)
    fit, derived = fit_pilots(data)
    atomic_write_text(out, calibration_toml(fit, data, derived, seed, scenario))
    log.info("calibrate: %s", fit)
    return fit


PILOT_TOWNS = (("town01", (73, 73), (106,)), ("town02", (65, 65, 39), (102,)))  # the quick reproduction's split


def _generate_pilot_data(scenario_name: str, data_dir: Path, seed: int) -> None:
    from crchfl_sumo.data.generation import generate_dataset
    from crchfl_sumo.data.settings import DatasetConfig, TownSplit
    from crchfl_sumo.sumo.scenario import load_scenario

    sizes = DatasetConfig(towns=tuple(TownSplit(t, train, test) for t, train, test in PILOT_TOWNS))
    generate_dataset(load_scenario(scenario_name), data_dir, seed, sizes)
