"""Wireless link budget: geometry -> path loss -> SNR -> rate [bit/s].

Pure functions over numpy arrays, plus the frozen settings they read. Models:

- path loss and LOS probability: 3GPP TR 38.901 V17 Table 7.4.1-1 (path loss)
  and Table 7.4.2-1 (LOS probability), scenarios UMi street canyon (edge
  sites: road-side units, 10 m masts) and UMa (macro cells, for SFL's direct
  vehicle <-> cloud link);
- log-normal shadowing with the TR's sigma per LOS/NLOS, correlated along the
  vehicle's path by an AR(1) in travelled distance (exponential
  autocorrelation, decorrelation distance from TR 38.901 Table 7.5-6);
- Rayleigh block fading (exponential power gain);
- thermal noise -174 dBm/Hz + 10 log10(B) + noise figure;
- attenuated, capped Shannon rate (TR 36.942 Annex A.1 style).

The stateful parts (which draw belongs to which vehicle, when to redraw) live
in mobility.LinkModel; everything here is a function of its arguments.
See docs/links.md for every default and its source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_RATE_BPS, check_range

SPEED_OF_LIGHT_MPS = 299_792_458.0
THERMAL_NOISE_DBM_PER_HZ = -174.0  # kT at 290 K
ENVIRONMENT_HEIGHT_M = 1.0  # h_E of TR 38.901 Note 1 (UMi always; UMa for h_UT < 13 m)

Scenario = Literal["umi", "uma"]
LosMode = Literal["random", "expected", "los", "nlos"]


@dataclass(frozen=True)
class ScenarioParams:
    """The numbers of one TR 38.901 scenario; the formulas are shared (see below).

    LOS:  PL1 = los_a + los_b log10(d3D) + 20 log10(fc)            (d2D <= d'BP)
          PL2 = los_a + 40 log10(d3D) + 20 log10(fc)
                - los_c log10(d'BP^2 + (hBS - hUT)^2)                (d2D >  d'BP)
    NLOS: max(PL_LOS, nlos_a + nlos_b log10(d3D) + nlos_f log10(fc) - nlos_h (hUT - 1.5))
    P_LOS = 1 for d2D <= 18 m, else 18/d2D + exp(-d2D/los_prob_scale_m)(1 - 18/d2D),
            times (1 + C'(hUT) 5/4 (d2D/100)^3 exp(-d2D/150)) where los_prob_height_term.
    (d in m, fc in GHz.)
    """

    los_a: float
    los_b: float
    los_c: float
    nlos_a: float
    nlos_b: float
    nlos_f: float
    nlos_h: float
    los_prob_scale_m: float  # Table 7.4.2-1
    los_prob_height_term: bool  # UMa's C'(hUT) factor
    shadow_sigma_los_db: float  # Table 7.4.1-1
    shadow_sigma_nlos_db: float  # Table 7.4.1-1
    shadow_decorrelation_los_m: float  # Table 7.5-6, "SF" correlation distance
    shadow_decorrelation_nlos_m: float
    los_state_decorrelation_m: float  # Table 7.6.3.1-2 (spatially consistent LOS state)
    min_distance_2d_m: float  # lower end of the formulas' validity range


SCENARIOS: dict[str, ScenarioParams] = {
    "umi": ScenarioParams(
        los_a=32.4, los_b=21.0, los_c=9.5,
        nlos_a=22.4, nlos_b=35.3, nlos_f=21.3, nlos_h=0.3,
        los_prob_scale_m=36.0, los_prob_height_term=False,
        shadow_sigma_los_db=4.0, shadow_sigma_nlos_db=7.82,
        shadow_decorrelation_los_m=10.0, shadow_decorrelation_nlos_m=13.0,
        los_state_decorrelation_m=50.0, min_distance_2d_m=10.0,
    ),  # fmt: skip
    "uma": ScenarioParams(
        los_a=28.0, los_b=22.0, los_c=9.0,
        nlos_a=13.54, nlos_b=39.08, nlos_f=20.0, nlos_h=0.6,
        los_prob_scale_m=63.0, los_prob_height_term=True,
        shadow_sigma_los_db=4.0, shadow_sigma_nlos_db=6.0,
        shadow_decorrelation_los_m=37.0, shadow_decorrelation_nlos_m=50.0,
        los_state_decorrelation_m=50.0, min_distance_2d_m=10.0,
    ),  # fmt: skip
}


MAX_FADING_BLOCKS = 1024  # fading gains kept per vehicle and step
MAX_LATENCY_S = 60.0  # a backhaul's one-way latency: a minute, beyond any network's (geostationary: 0.25 s)
# Channel settings' physical ranges (generous: any real radio lies well inside them).
PHYSICAL_RANGES = {
    "bandwidth_hz": (1e3, 10e9, "Hz"),
    "tx_power_dbm": (-50.0, 60.0, "dBm"),
    "vehicle_antenna_gain_dbi": (-30.0, 40.0, "dBi"),
    "site_antenna_gain_dbi": (-30.0, 40.0, "dBi"),
    "vehicle_antenna_height_m": (0.0, 100.0, "m"),
    "noise_figure_db": (0.0, 30.0, "dB"),
    "fading_min_speed_mps": (0.0, 200.0, "m/s"),
    "max_bps_per_hz": (0.0, 100.0, "bit/s/Hz"),
    "min_snr_db": (-50.0, 50.0, "dB"),
}


@dataclass(frozen=True)
class ChannelConfig:
    """Radio settings of one kind of wireless link (TOML ``[channel]``).

    Defaults describe an edge site: a road-side unit on a 10 m mast in an
    urban street canyon, C-V2X in the 5.9 GHz ITS band (NR band n47), 20 MHz,
    with UE-class radios at both ends (23 dBm, 3 dBi, 9 dB noise figure), so
    the link budget is the same up- and downlink.
    """

    scenario: Scenario = "umi"
    carrier_hz: float = 5.9e9
    bandwidth_hz: float = 20e6  # one cell's channel, shared by its vehicles
    tx_power_dbm: float = 23.0
    vehicle_antenna_gain_dbi: float = 3.0
    site_antenna_gain_dbi: float = 3.0
    vehicle_antenna_height_m: float = 1.5
    noise_figure_db: float = 9.0
    # How each link's LOS state is decided (docs/links.md): "random" draws a
    # spatially consistent state from the LOS probability, "expected" weights
    # LOS and NLOS path loss [dB] by that probability, "los"/"nlos" force one.
    los_mode: LosMode = "random"
    shadowing: bool = True
    fading: bool = True
    # Fading is redrawn once per coherence time 0.423 / f_D, f_D = v f_c / c;
    # a stopped car still sees moving scatterers, hence the floor speed.
    fading_min_speed_mps: float = 1.0
    # When a simulation step spans many coherence times, the step's rate is
    # the mean over at most this many independent fading blocks.
    fading_max_blocks_per_step: int = 16
    efficiency: float = 0.6  # fraction of Shannon capacity achieved
    max_bps_per_hz: float = 5.55  # NR 64QAM top CQI (TS 38.214 Table 5.2.2.1-2)
    min_snr_db: float = -10.0  # below this the link carries nothing

    def __post_init__(self) -> None:
        positive = {
            "carrier_hz": self.carrier_hz,
            "bandwidth_hz": self.bandwidth_hz,
            "vehicle_antenna_height_m": self.vehicle_antenna_height_m,
            "fading_min_speed_mps": self.fading_min_speed_mps,
            "max_bps_per_hz": self.max_bps_per_hz,
        }
        for key, value in positive.items():
            if not value > 0:
                raise CrchflError(f"channel.{key} must be > 0, got {value}")
        if self.scenario not in SCENARIOS:
            raise CrchflError(f"channel.scenario must be one of {sorted(SCENARIOS)}, got {self.scenario!r}")
        if not 0.5e9 <= self.carrier_hz <= 100e9:
            raise CrchflError(
                f"channel.carrier_hz = {self.carrier_hz:g} is outside TR 38.901's 0.5-100 GHz; "
                "give the carrier in Hz, e.g. 5.9e9"
            )
        if not 0 < self.efficiency <= 1:
            raise CrchflError(f"channel.efficiency must be in (0, 1], got {self.efficiency}")
        if not 1 <= self.fading_max_blocks_per_step <= MAX_FADING_BLOCKS:
            raise CrchflError(
                f"channel.fading_max_blocks_per_step must be in 1 .. {MAX_FADING_BLOCKS} (each vehicle keeps this "
                f"many fading gains), got {self.fading_max_blocks_per_step}"
            )
        for key, (lo, hi, unit) in PHYSICAL_RANGES.items():  # beyond these the link budget is no radio's
            value = getattr(self, key)
            if not lo <= value <= hi:
                raise CrchflError(f"channel.{key} = {value:g} is outside {lo:g} .. {hi:g} {unit}; give a radio's value")
        if self.vehicle_antenna_height_m <= ENVIRONMENT_HEIGHT_M:
            raise CrchflError(
                f"channel.vehicle_antenna_height_m must exceed {ENVIRONMENT_HEIGHT_M} m "
                f"(TR 38.901 uses 1.5-22.5 m), got {self.vehicle_antenna_height_m}"
            )

    @property
    def params(self) -> ScenarioParams:
        return SCENARIOS[self.scenario]


@dataclass(frozen=True)
class WirelineConfig:
    """Edge <-> cloud backhaul (TOML ``[wireline]``): a dedicated link per edge site.

    Defaults: 1 Gbit/s Ethernet/fibre metro backhaul, 10 ms one-way latency.
    """

    rate_bps: float = 1e9
    latency_s: float = 0.010

    def __post_init__(self) -> None:
        check_range(self.rate_bps, "wireline.rate_bps", 0, MAX_RATE_BPS, "bit/s", lo_open=True)
        check_range(self.latency_s, "wireline.latency_s", 0, MAX_LATENCY_S, "seconds")


# --- unit conversions -------------------------------------------------------


def db_to_linear(value_db):
    return np.power(10.0, np.asarray(value_db, dtype=np.float64) / 10.0)


def linear_to_db(value):
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(np.asarray(value, dtype=np.float64))


# --- TR 38.901 path loss ------------------------------------------------------


def breakpoint_distance_m(site_height_m, vehicle_height_m, carrier_hz):
    """d'_BP = 4 h'_BS h'_UT f_c / c, heights reduced by h_E = 1 m (TR 38.901 Note 1)."""
    h_bs = np.asarray(site_height_m, dtype=np.float64) - ENVIRONMENT_HEIGHT_M
    h_ut = np.asarray(vehicle_height_m, dtype=np.float64) - ENVIRONMENT_HEIGHT_M
    return 4.0 * h_bs * h_ut * carrier_hz / SPEED_OF_LIGHT_MPS


def distance_3d_m(distance_2d_m, site_height_m, vehicle_height_m):
    dh = np.asarray(site_height_m, dtype=np.float64) - vehicle_height_m
    return np.hypot(np.asarray(distance_2d_m, dtype=np.float64), dh)


def los_path_loss_db(distance_2d_m, site_height_m, cfg: ChannelConfig):
    """LOS path loss [dB] of TR 38.901 Table 7.4.1-1 for ``cfg.scenario``."""
    return path_loss_pair_db(distance_2d_m, site_height_m, cfg)[0]


def nlos_path_loss_db(distance_2d_m, site_height_m, cfg: ChannelConfig):
    """NLOS path loss [dB]: max(LOS, PL'_NLOS), TR 38.901 Table 7.4.1-1."""
    return path_loss_pair_db(distance_2d_m, site_height_m, cfg)[1]


def path_loss_pair_db(distance_2d_m, site_height_m, cfg: ChannelConfig):
    """(LOS, NLOS) path loss [dB] of TR 38.901 Table 7.4.1-1, sharing the geometry and log10(d3D).

    A link model needs both for every link and step; computed together, the
    distance and its logarithm are taken once instead of three times.
    """
    d2, h_bs, d3, fc_ghz = _geometry(distance_2d_m, site_height_m, cfg)
    sp, h_ut = cfg.params, cfg.vehicle_antenna_height_m
    d_bp = breakpoint_distance_m(h_bs, h_ut, cfg.carrier_hz)
    log_d3 = np.log10(d3)
    pl1 = sp.los_a + sp.los_b * log_d3 + 20.0 * np.log10(fc_ghz)
    pl2 = sp.los_a + 40.0 * log_d3 + 20.0 * np.log10(fc_ghz) - sp.los_c * np.log10(d_bp**2 + (h_bs - h_ut) ** 2)
    los = np.where(d2 <= d_bp, pl1, pl2)
    nlos = sp.nlos_a + sp.nlos_b * log_d3 + sp.nlos_f * np.log10(fc_ghz) - sp.nlos_h * (h_ut - 1.5)
    return los, np.maximum(los, nlos)


def path_loss_db(distance_2d_m, site_height_m, los, cfg: ChannelConfig):
    """Path loss [dB] for LOS state ``los`` (bool array; True = LOS)."""
    return np.where(np.asarray(los, dtype=bool), *path_loss_pair_db(distance_2d_m, site_height_m, cfg))


def expected_path_loss_db(distance_2d_m, site_height_m, cfg: ChannelConfig):
    """LOS-probability-weighted path loss [dB]; rate is near-linear in dB, so this tracks mean rate."""
    p = los_probability(distance_2d_m, cfg.scenario, cfg.vehicle_antenna_height_m)
    los, nlos = path_loss_pair_db(distance_2d_m, site_height_m, cfg)
    return p * los + (1.0 - p) * nlos


def _geometry(distance_2d_m, site_height_m, cfg: ChannelConfig):
    # The formulas hold from 10 m; closer in, the 10 m value is used.
    d2 = np.maximum(np.asarray(distance_2d_m, dtype=np.float64), cfg.params.min_distance_2d_m)
    h_bs = np.asarray(site_height_m, dtype=np.float64)
    d3 = distance_3d_m(d2, h_bs, cfg.vehicle_antenna_height_m)
    return d2, h_bs, d3, cfg.carrier_hz / 1e9


def los_probability(distance_2d_m, scenario: Scenario = "umi", vehicle_height_m: float = 1.5):
    """Probability of line of sight, TR 38.901 Table 7.4.2-1 (outdoor users)."""
    sp = SCENARIOS[scenario]
    d2 = np.maximum(np.asarray(distance_2d_m, dtype=np.float64), 1e-9)
    near = 18.0 / d2
    p = near + np.exp(-d2 / sp.los_prob_scale_m) * (1.0 - near)
    if sp.los_prob_height_term and vehicle_height_m > 13.0:
        c_prime = ((vehicle_height_m - 13.0) / 10.0) ** 1.5
        p = p * (1.0 + c_prime * 1.25 * (d2 / 100.0) ** 3 * np.exp(-d2 / 150.0))
    return np.where(d2 <= 18.0, 1.0, p)


def shadow_sigma_db(los, cfg: ChannelConfig):
    """Shadowing standard deviation [dB] per link, from its LOS state (bool array)."""
    return np.where(np.asarray(los, dtype=bool), cfg.params.shadow_sigma_los_db, cfg.params.shadow_sigma_nlos_db)


def shadow_decorrelation_m(los, cfg: ChannelConfig):
    """Shadowing decorrelation distance [m] per link, from its LOS state."""
    return np.where(
        np.asarray(los, dtype=bool),
        cfg.params.shadow_decorrelation_los_m,
        cfg.params.shadow_decorrelation_nlos_m,
    )


# --- correlated random processes ---------------------------------------------


def ar1_step(previous, travelled_m, decorrelation_m, innovation):
    """Advance a unit-variance Gaussian process by ``travelled_m`` along the path.

    Exponential autocorrelation exp(-d / d_corr) (Gudmundson; TR 38.901 7.6.3):
    x' = rho x + sqrt(1 - rho^2) n with rho = exp(-d / d_corr), n ~ N(0, 1).
    The stationary variance stays 1 for any step length.
    """
    rho = np.exp(-np.abs(np.asarray(travelled_m, dtype=np.float64)) / decorrelation_m)
    return rho * previous + np.sqrt(1.0 - rho**2) * innovation


_erf = np.frompyfunc(math.erf, 1, 1)


def standard_normal_cdf(x):
    """Phi(x), for turning a correlated Gaussian state into a uniform one."""
    x = np.asarray(x, dtype=np.float64)
    return 0.5 * (1.0 + np.asarray(_erf(x / math.sqrt(2.0)), dtype=np.float64))


# Abramowitz & Stegun 26.2.17: Phi(x) for x >= 0 within 7.5e-8, from one exp.
_AS_P = 0.2316419
_AS_B = (0.319381530, -0.356563782, 1.781477937, -1.821255978, 1.330274429)
_AS_TIE = 1e-6  # far above the approximation's error: beyond it, the approximation decides


def below_standard_normal_cdf(x, p):
    """``standard_normal_cdf(x) < p``, elementwise, with the same answer at numpy speed.

    math.erf runs one Python call an element (a millisecond for a few thousand
    links); a polynomial approximation decides every element farther than
    _AS_TIE from its threshold, and the few near ties go to the exact formula.
    """
    x, p = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(p, dtype=np.float64))
    a = np.abs(x)
    t = 1.0 / (1.0 + _AS_P * a)
    b1, b2, b3, b4, b5 = _AS_B
    tail = np.exp(-0.5 * a * a) / math.sqrt(2.0 * math.pi) * (t * (b1 + t * (b2 + t * (b3 + t * (b4 + t * b5)))))
    approx = np.where(x >= 0.0, 1.0 - tail, tail)
    below = approx < p
    tie = np.abs(approx - p) <= _AS_TIE
    if tie.any():
        below[tie] = standard_normal_cdf(x[tie]) < p[tie]
    return below


def coherence_time_s(speed_mps, carrier_hz: float, min_speed_mps: float = 1.0):
    """Channel coherence time 0.423 / f_D with Doppler f_D = v f_c / c (Clarke's model)."""
    speed = np.maximum(np.asarray(speed_mps, dtype=np.float64), min_speed_mps)
    return 0.423 * SPEED_OF_LIGHT_MPS / (speed * carrier_hz)


# --- link budget and rate ------------------------------------------------------


def noise_power_dbm(bandwidth_hz, noise_figure_db):
    """Thermal noise power [dBm] in ``bandwidth_hz`` behind a receiver of given noise figure."""
    return THERMAL_NOISE_DBM_PER_HZ + 10.0 * np.log10(np.asarray(bandwidth_hz, dtype=np.float64)) + noise_figure_db


def received_power_dbm(path_loss, shadowing_db, cfg: ChannelConfig):
    """Large-scale received power [dBm]: P_tx + G_vehicle + G_site - PL - shadowing."""
    return cfg.tx_power_dbm + cfg.vehicle_antenna_gain_dbi + cfg.site_antenna_gain_dbi - path_loss - shadowing_db


def snr_db(rx_power_dbm, cfg: ChannelConfig):
    """SNR [dB] over the cell's whole bandwidth.

    Sharing keeps this SNR: NR uplink power control scales power with the
    allocated bandwidth (constant power spectral density, TS 38.213 7.1.1),
    so a vehicle with 1/N of the band sees the same SNR on it.
    """
    return np.asarray(rx_power_dbm, dtype=np.float64) - noise_power_dbm(cfg.bandwidth_hz, cfg.noise_figure_db)


def shannon_rate_bps(snr_linear, bandwidth_hz, max_bps_per_hz=math.inf, efficiency=1.0, min_snr_linear=0.0):
    """Achievable rate [bit/s]: B * min(efficiency * log2(1 + SNR), cap); 0 below the minimum SNR."""
    snr = np.asarray(snr_linear, dtype=np.float64)
    spectral = np.minimum(efficiency * np.log2(1.0 + np.maximum(snr, 0.0)), max_bps_per_hz)
    return np.where(snr >= min_snr_linear, np.asarray(bandwidth_hz, dtype=np.float64) * spectral, 0.0)


def link_rate_bps(snr_linear, share, cfg: ChannelConfig):
    """Rate [bit/s] of a vehicle holding ``share`` (0..1) of the cell's bandwidth at this SNR."""
    return shannon_rate_bps(
        snr_linear,
        np.asarray(share, dtype=np.float64) * cfg.bandwidth_hz,
        cfg.max_bps_per_hz,
        cfg.efficiency,
        float(db_to_linear(cfg.min_snr_db)),
    )


def wireline_rate_bps(cfg: WirelineConfig) -> float:
    """Rate [bit/s] of one edge <-> cloud backhaul link (dedicated per site)."""
    return cfg.rate_bps
