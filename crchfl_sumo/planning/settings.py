"""The resource optimizer's settings (TOML ``[allocation]``) and its calibration file, apart from problem.py:
a run config reads them without loading CVXPY."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from crchfl_sumo.core.config import from_mapping, read_toml
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_EPOCHS, MAX_RATE_BPS, MAX_SAMPLES, MAX_SIMULATED_S, check_range
from crchfl_sumo.sumo.sites import MAX_SITES

DEFAULT_SOLVER = "CLARABEL"  # installed with CVXPY
PAPER_LOCAL_SAMPLES = 2 * 2928 + 2586 + 2587 + 1555  # FACTS.md: the paper's five training sets


# Bounds of the planning settings that size the search (a larger value only eats memory and time).
MAX_EDGES = MAX_SITES
MAX_VEHICLES_PER_EDGE = 10_000
MAX_LOCAL_SAMPLES = MAX_SAMPLES
MAX_INTERVAL = 100
MAX_BUDGET_S = 365 * 86400.0  # the training's time budget W: a year


@dataclass(frozen=True)
class AllocationConfig:
    """Settings of the resource optimizer (TOML table ``[allocation]``).

    alpha, gamma, d: the weights of problem P. Defaults: `crchfl-sumo calibrate`
        on the paper scenario, seed 0, at the stated pilot size (fit 1.27, 0.275,
        9.30; alpha clipped to 1), data and residuals in docs/calibration.md.
    vehicles_per_edge: the planning topology (paper: Town01 2, Town02 3).
    local_samples: s = sum_k |T_nk|, all vehicles' training samples (paper: 12584).
    max_edge_interval, max_cloud_interval: search bounds of I_e and I_c.
    fix_edge_interval: fix I_e (the paper's ablation used 2, 3, 4); None searches.
    epoch_time_s: time of one local epoch [s] (vehicles train in parallel).
    training_time_budget_s: wall-clock budget W of the whole training [s].
    wireless_rate_bps, wireline_rate_bps: mean per-vehicle wireless rate and
        edge-cloud backhaul rate [bit/s].
    pretrain_time_per_sample_s: cloud pretraining compute per uploaded sample
        over all pretraining epochs [s].
        In a run (and in `plan --scenario` for the rate) these four come from the
        run itself, not from here: planning/timing.py.
    rate_window_s: simulated seconds of mobility over which the wireless rate is measured.
    calibration_file: a `crchfl-sumo calibrate` output (path relative to the
        current directory); its alpha, gamma and d replace the three above.
    solver: CVXPY solver for the continuous problem.
    """

    alpha: float = 1.0
    gamma: float = 0.275
    d: float = 9.3
    vehicles_per_edge: tuple[int, ...] = (2, 3)
    local_samples: int = PAPER_LOCAL_SAMPLES
    max_edge_interval: int = 10
    max_cloud_interval: int = 4
    fix_edge_interval: int | None = None
    epoch_time_s: float = 120.0
    training_time_budget_s: float = 7200.0
    wireless_rate_bps: float = 20e6
    wireline_rate_bps: float = 1e9
    pretrain_time_per_sample_s: float = 0.05
    rate_window_s: float = 300.0
    calibration_file: str | None = None
    solver: str = DEFAULT_SOLVER

    def __post_init__(self) -> None:
        for key in ("alpha", "gamma"):
            value = getattr(self, key)
            if not 0.0 <= value <= 1.0:
                raise CrchflError(f"allocation.{key} must lie in [0, 1] (paper, Section IV), got {value}")
        # d is in local epochs (the term d / t, t = I_e I_c T, of S_eff); no plan's t exceeds MAX_EPOCHS
        check_range(self.d, "allocation.d", 0, MAX_EPOCHS, "a number of epochs")
        if (not self.vehicles_per_edge or any(n < 0 for n in self.vehicles_per_edge) or sum(self.vehicles_per_edge) == 0
                or len(self.vehicles_per_edge) > MAX_EDGES or max(self.vehicles_per_edge) > MAX_VEHICLES_PER_EDGE):
            raise CrchflError(
                f"allocation.vehicles_per_edge must list up to {MAX_EDGES} counts in 0 .. {MAX_VEHICLES_PER_EDGE} "
                f"with at least one vehicle, got {self.vehicles_per_edge}"
            )
        if not 0 <= self.local_samples <= MAX_LOCAL_SAMPLES:
            raise CrchflError(f"allocation.local_samples must be in 0 .. {MAX_LOCAL_SAMPLES}, got {self.local_samples}")
        for key in ("max_edge_interval", "max_cloud_interval", "fix_edge_interval"):
            value = getattr(self, key)
            if value is not None and value > MAX_INTERVAL:
                raise CrchflError(
                    f"allocation.{key} must be at most {MAX_INTERVAL} (the search tries every interval up to it), "
                    f"got {value}"
                )
        if self.max_edge_interval < 2:
            raise CrchflError(
                f"allocation.max_edge_interval must be >= 2 (the paper requires 0 < cloud_interval < edge_interval), "
                f"got {self.max_edge_interval}"
            )
        if self.max_cloud_interval < 1:
            raise CrchflError(f"allocation.max_cloud_interval must be >= 1, got {self.max_cloud_interval}")
        if self.fix_edge_interval is not None and self.fix_edge_interval < 2:
            raise CrchflError(
                f"allocation.fix_edge_interval must be >= 2 (the paper requires 0 < cloud_interval < edge_interval), "
                f"got {self.fix_edge_interval}"
            )
        # a run derives these two from federation.compute_s_per_sample (planning/timing.py): bounded by W's bound
        check_range(self.epoch_time_s, "allocation.epoch_time_s", 0, MAX_BUDGET_S,
                    "seconds (0: training takes no time)")
        check_range(self.training_time_budget_s, "allocation.training_time_budget_s", 0, MAX_BUDGET_S, "seconds",
                    lo_open=True)
        for key in ("wireless_rate_bps", "wireline_rate_bps"):
            check_range(getattr(self, key), f"allocation.{key}", 0, MAX_RATE_BPS, "bit/s", lo_open=True)
        check_range(self.pretrain_time_per_sample_s, "allocation.pretrain_time_per_sample_s", 0, MAX_BUDGET_S,
                    "seconds a sample")
        check_range(self.rate_window_s, "allocation.rate_window_s", 0, MAX_SIMULATED_S, "simulated seconds",
                    lo_open=True)
        if self.solver != DEFAULT_SOLVER:  # CVXPY ships the default; asking it for others loads it (seconds)
            import cvxpy as cp

            if self.solver not in cp.installed_solvers():
                raise CrchflError(
                    f"allocation.solver {self.solver!r} is not installed; installed: {', '.join(cp.installed_solvers())}"
                )

    def edge_intervals(self) -> range:
        if self.fix_edge_interval is not None:
            return range(self.fix_edge_interval, self.fix_edge_interval + 1)
        return range(2, self.max_edge_interval + 1)

    def cloud_intervals(self, edge_interval: int) -> range:
        """0 < I_c < I_e, as written in the paper, and I_c <= max_cloud_interval."""
        return range(1, min(self.max_cloud_interval, edge_interval - 1) + 1)


def calibrated(config: AllocationConfig) -> AllocationConfig:
    """``config`` with alpha, gamma, d from its ``calibration_file`` (unchanged without one)."""
    if config.calibration_file is None:
        return config
    path = Path(config.calibration_file)
    if not path.is_file():
        raise CrchflError(
            f"allocation.calibration_file: {path} not found; write it with `crchfl-sumo calibrate --out {path}` "
            "or fix the path (relative to the current directory)"
        )
    table = read_toml(path).get("allocation", {})
    missing = [key for key in ("alpha", "gamma", "d") if key not in table]
    if missing:
        raise CrchflError(
            f"allocation.calibration_file: {path} has no {', '.join(missing)} in its [allocation] table; "
            "point it at a file written by `crchfl-sumo calibrate`"
        )
    weights = from_mapping(AllocationConfig, {k: table[k] for k in ("alpha", "gamma", "d")}, f"{path}: allocation")
    return dataclasses.replace(config, alpha=weights.alpha, gamma=weights.gamma, d=weights.d, calibration_file=None)
