"""Which edge site serves each vehicle, and at what rate, step by step.

``LinkModel`` turns a stream of Frames into LinkSnapshots (links/snapshots.py): per vehicle the
serving site (-1 = none), the large-scale received power and SNR, and the rate
[bit/s] after bandwidth sharing and fading. It owns the only state this needs:
the random processes of every (vehicle, site) link (LOS state, shadowing,
fading), carried from step to step by vehicle id, and the association with its
handover timers. Everything is vectorised over vehicles x sites.

Association (docs/links.md): strongest large-scale received power among the
sites in coverage (within ``coverage_radius_m`` and above ``min_rx_power_dbm``).
A serving vehicle moves to another site only after that site has beaten the
serving one by ``handover_margin_db`` at every step for ``time_to_trigger_s``
(3GPP event A3 with hysteresis and time-to-trigger). Fast fading is left out
of the comparison, as real handovers compare layer-3 filtered power: fading
decorrelates within milliseconds and would only make vehicles ping-pong.
With ``l3_filter_s`` > 0 the compared power is also smoothed over time
(TS 38.331 layer-3 filtering), which damps the seconds-long swings of the
LOS state and shadowing that the margin and time-to-trigger alone let through.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_seed
from crchfl_sumo.links import channel as ch
from crchfl_sumo.links.channel import ChannelConfig
from crchfl_sumo.links.snapshots import Handover, LinkSnapshot
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.sumo.sites import EdgeSite

log = logging.getLogger(__name__)

NO_SITE = -1
_EPS_S = 1e-9  # float slack when comparing simulated times
# TS 38.331 5.5.3.2: F = (1 - a) F + a M with a = 1 / 2^(k / 4), k = filterCoefficient
# (default fc4: a = 1/2), at the 200 ms sample rate the coefficient assumes;
# as a time constant: (1 - a) = exp(-0.2 s / tau).
L3_FILTER_FC4_S = 0.2 / math.log(2.0)


@dataclass(frozen=True)
class MobilityConfig:
    """Association and handover settings (TOML ``[mobility]``)."""

    coverage_radius_m: float = 300.0  # a road-side unit's service range
    min_rx_power_dbm: float = -100.0  # about -8 dB SNR with the default channel
    handover_margin_db: float = 3.0  # A3 offset + hysteresis
    time_to_trigger_s: float = 2.56  # TS 38.331 TimeToTrigger ms2560
    l3_filter_s: float = L3_FILTER_FC4_S  # time constant of the layer-3 filter on the compared power; 0 = off
    radio_link_failure_s: float = 1.0  # TS 38.331 T310 ms1000: how long a site may stay below min_rx_power_dbm
    # Other users of a cell's bandwidth besides the federated vehicles (docs/links.md, "Cells that the
    # traffic loads"): each background vehicle within a site's coverage, served by its nearest site, is an
    # active user with this probability (its expected load), and every cell has this many other users.
    background_active_share: float = 0.0
    cell_background_users: float = 0.0

    def __post_init__(self) -> None:
        if not self.coverage_radius_m > 0:
            raise CrchflError(f"mobility.coverage_radius_m must be > 0, got {self.coverage_radius_m}")
        if not self.handover_margin_db >= 0:
            raise CrchflError(f"mobility.handover_margin_db must be >= 0, got {self.handover_margin_db}")
        if not self.time_to_trigger_s >= 0:
            raise CrchflError(f"mobility.time_to_trigger_s must be >= 0, got {self.time_to_trigger_s}")
        if not (math.isfinite(self.l3_filter_s) and self.l3_filter_s >= 0):
            raise CrchflError(f"mobility.l3_filter_s must be a time >= 0 (0 = no filter), got {self.l3_filter_s}")
        if not (math.isfinite(self.radio_link_failure_s) and self.radio_link_failure_s >= 0):
            raise CrchflError(
                f"mobility.radio_link_failure_s must be a time >= 0 (0 = leave a weak site at once), "
                f"got {self.radio_link_failure_s}"
            )
        if not -200.0 <= self.min_rx_power_dbm <= 0.0:
            raise CrchflError(
                f"mobility.min_rx_power_dbm must be a received power in -200 .. 0 dBm, got {self.min_rx_power_dbm}"
            )
        if self.coverage_radius_m > 100e3:
            raise CrchflError(
                f"mobility.coverage_radius_m must be at most 100 km (100000), got {self.coverage_radius_m}"
            )
        if self.handover_margin_db > 60.0:
            raise CrchflError(f"mobility.handover_margin_db must be at most 60 dB, got {self.handover_margin_db}")
        for key in ("time_to_trigger_s", "l3_filter_s", "radio_link_failure_s"):
            if getattr(self, key) > 3600.0:
                raise CrchflError(f"mobility.{key} must be at most 3600 s, got {getattr(self, key)}")
        if not (isinstance(self.background_active_share, (int, float)) and 0.0 <= self.background_active_share <= 1.0):
            raise CrchflError(
                f"mobility.background_active_share must be a share in [0, 1], got {self.background_active_share!r}"
            )
        # a cell of more than 10000 other users leaves the federated vehicles nothing to measure
        if not (isinstance(self.cell_background_users, (int, float)) and 0.0 <= self.cell_background_users <= 1e4):
            raise CrchflError(
                f"mobility.cell_background_users must be a number of users in [0, 10000], got {self.cell_background_users!r}"
            )


@dataclass
class _State:
    """Per-vehicle (rows) and per-link (rows x sites) state, rows aligned with ``ids``."""

    ids: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    los_z: np.ndarray  # [V, S] Gaussian behind the spatially consistent LOS state
    shadow_z: np.ndarray  # [V, S] unit-variance shadowing process
    filtered_dbm: np.ndarray  # [V, S] layer-3 filtered received power (NaN: no history)
    serving: np.ndarray  # [V]
    weak_since_s: np.ndarray  # [V] since when the serving site is below min_rx_power_dbm (NaN: it is not)
    beats_since_s: np.ndarray  # [V, S] since when a site beats the serving one by the margin (NaN: not now)
    fade_gain: np.ndarray  # [V, K] Rayleigh power gains of the current blocks
    fade_blocks: np.ndarray  # [V] how many of the K columns are in use
    fade_until_s: np.ndarray  # [V] when the current blocks expire
    fade_site: np.ndarray  # [V] site the current blocks belong to

    @classmethod
    def empty(cls, n_sites: int, n_blocks: int) -> "_State":
        f = np.zeros(0)
        return cls(
            ids=np.zeros(0, dtype=str),
            x_m=f,
            y_m=f,
            los_z=np.zeros((0, n_sites)),
            shadow_z=np.zeros((0, n_sites)),
            filtered_dbm=np.zeros((0, n_sites)),
            serving=np.zeros(0, dtype=np.int64),
            weak_since_s=f,
            beats_since_s=np.zeros((0, n_sites)),
            fade_gain=np.ones((0, n_blocks)),
            fade_blocks=np.zeros(0, dtype=np.int64),
            fade_until_s=f,
            fade_site=np.zeros(0, dtype=np.int64),
        )

    def carried_to(self, ids: np.ndarray, x_m: np.ndarray, y_m: np.ndarray) -> tuple["_State", np.ndarray]:
        """State re-indexed to ``ids``; new vehicles get fresh rows. Also returns the 'is new' mask."""
        n = len(ids)
        _, new_rows, old_rows = np.intersect1d(ids, self.ids, assume_unique=True, return_indices=True)
        is_new = np.ones(n, dtype=bool)
        is_new[new_rows] = False
        source = np.zeros(n, dtype=np.intp)
        source[new_rows] = old_rows
        fresh = np.flatnonzero(is_new)

        def take(old: np.ndarray, fill) -> np.ndarray:
            # one gather of whole rows, then the few new rows filled (a step's arrays are mostly carried)
            if not len(old):
                return np.full((n, *old.shape[1:]), fill, dtype=old.dtype)
            out = old[source]
            out[fresh] = fill
            return out

        state = _State(
            ids=ids,
            x_m=np.where(is_new, x_m, take(self.x_m, 0.0)),
            y_m=np.where(is_new, y_m, take(self.y_m, 0.0)),
            los_z=take(self.los_z, 0.0),
            shadow_z=take(self.shadow_z, 0.0),
            filtered_dbm=take(self.filtered_dbm, np.nan),
            serving=take(self.serving, NO_SITE),
            weak_since_s=take(self.weak_since_s, np.nan),
            beats_since_s=take(self.beats_since_s, np.nan),
            fade_gain=take(self.fade_gain, 1.0),
            fade_blocks=take(self.fade_blocks, 0),
            fade_until_s=take(self.fade_until_s, -np.inf),
            fade_site=take(self.fade_site, NO_SITE),
        )
        return state, is_new


class LinkModel:
    """Association + rates of vehicles to a fixed set of sites, advanced one Frame at a time.

    Same sites, configs, seed and frames -> identical snapshots. Vehicles are
    matched between frames by id; a vehicle that reappears starts afresh.
    """

    def __init__(
        self,
        sites: Sequence[EdgeSite],
        channel: ChannelConfig = ChannelConfig(),
        mobility: MobilityConfig = MobilityConfig(),
        seed: int | np.random.Generator = 0,
    ) -> None:
        if len(sites) == 0:
            raise CrchflError("edge_sites: a link model needs at least one site; add one to the scenario")
        if not isinstance(seed, np.random.Generator):
            check_seed(seed, "LinkModel: seed")
        self.sites = tuple(sites)
        for site in self.sites:
            if site.height_m <= ch.ENVIRONMENT_HEIGHT_M:
                raise CrchflError(
                    f"edge_sites.{site.name}.height_m = {site.height_m} m: the path-loss model needs a mast "
                    f"above {ch.ENVIRONMENT_HEIGHT_M} m (TR 38.901 UMi uses 10 m)"
                )
        self.channel = channel
        self.mobility = mobility
        self._site_x_m = np.array([s.x_m for s in self.sites], dtype=np.float64)
        self._site_y_m = np.array([s.y_m for s in self.sites], dtype=np.float64)
        self._site_h_m = np.array([s.height_m for s in self.sites], dtype=np.float64)
        self._rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self._state = _State.empty(len(self.sites), channel.fading_max_blocks_per_step)
        self._t_prev_s: float | None = None

    def step(
        self, frame: Frame, active: np.ndarray | None = None, background_users: np.ndarray | None = None
    ) -> LinkSnapshot:
        """Advance to ``frame`` and return every vehicle's link.

        ``active`` (bool [V], default all) marks the vehicles that currently
        transmit: a cell's bandwidth is split equally among its active
        vehicles and its ``background_users`` (float [S], expected users of
        each site other than the frame's vehicles; default none); an inactive
        vehicle is quoted the rate it would get by joining them.
        """
        t_s = float(frame.t_s)
        if self._t_prev_s is not None and t_s < self._t_prev_s - _EPS_S:
            raise ValueError(f"LinkModel.step: time went backwards ({t_s} < {self._t_prev_s})")
        dt_s = 0.0 if self._t_prev_s is None else t_s - self._t_prev_s
        cfg, mob, sp = self.channel, self.mobility, self.channel.params
        n, n_sites = len(frame), len(self.sites)
        active = np.ones(n, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        if active.shape != (n,):
            raise ValueError(f"LinkModel.step: active has shape {active.shape}, expected ({n},)")

        prev, is_new = self._state.carried_to(np.asarray(frame.ids), frame.x_m, frame.y_m)
        # New rows restart their processes: infinite travel makes the AR(1) forget.
        travelled_m = np.where(is_new, np.inf, np.hypot(frame.x_m - prev.x_m, frame.y_m - prev.y_m))[:, None]
        d2d_m = np.hypot(frame.x_m[:, None] - self._site_x_m, frame.y_m[:, None] - self._site_y_m)

        # LOS weight per link: 1 = LOS, 0 = NLOS, in between for "expected".
        los_z = ch.ar1_step(
            prev.los_z, travelled_m, sp.los_state_decorrelation_m, self._rng.standard_normal((n, n_sites))
        )
        p_los = ch.los_probability(d2d_m, cfg.scenario, cfg.vehicle_antenna_height_m)
        los_weight = {
            "random": lambda: ch.below_standard_normal_cdf(los_z, p_los).astype(np.float64),
            "expected": lambda: p_los,
            "los": lambda: np.ones_like(p_los),
            "nlos": lambda: np.zeros_like(p_los),
        }[cfg.los_mode]()
        los_db, nlos_db = ch.path_loss_pair_db(d2d_m, self._site_h_m, cfg)
        path_loss = los_weight * los_db + (1.0 - los_weight) * nlos_db
        sigma_db = los_weight * sp.shadow_sigma_los_db + (1.0 - los_weight) * sp.shadow_sigma_nlos_db
        decorrelation_m = (
            los_weight * sp.shadow_decorrelation_los_m + (1.0 - los_weight) * sp.shadow_decorrelation_nlos_m
        )
        shadow_z = ch.ar1_step(
            prev.shadow_z, travelled_m, decorrelation_m, self._rng.standard_normal((n, n_sites))
        )
        shadowing_db = sigma_db * shadow_z if cfg.shadowing else 0.0
        rx_dbm = ch.received_power_dbm(path_loss, shadowing_db, cfg)  # [V, S]

        # Association compares the (optionally layer-3 filtered) power; the rate below uses this step's.
        filtered_dbm = l3_filter(prev.filtered_dbm, rx_dbm, dt_s, mob.l3_filter_s)
        in_range = d2d_m <= mob.coverage_radius_m
        eligible = in_range & (filtered_dbm >= mob.min_rx_power_dbm)
        serving, beats_since_s, weak_since_s = associate(
            prev.serving, prev.beats_since_s, prev.weak_since_s, filtered_dbm, in_range, eligible, t_s, mob
        )

        rows = np.arange(n)
        has_site = serving >= 0
        site_col = np.where(has_site, serving, 0)
        rx_serving = np.where(has_site, rx_dbm[rows, site_col], np.nan)
        snr_serving_db = ch.snr_db(rx_serving, cfg)

        background = np.zeros(n_sites) if background_users is None else np.asarray(background_users, np.float64)
        if background.shape != (n_sites,):
            raise ValueError(f"LinkModel.step: background_users has shape {background.shape}, expected ({n_sites},)")
        load = np.bincount(serving[has_site & active], minlength=n_sites)
        cell_load = np.where(has_site, load[site_col] + (~active), 0)
        # Equal shares of the cell's time-frequency resources (round robin; a proportional-fair scheduler
        # over users of i.i.d. fading gives each user the same long-run share): 1 / (users in the cell).
        users = cell_load + np.where(has_site, background[site_col], 0.0)
        share = np.where(has_site, 1.0 / np.maximum(users, 1.0), 0.0)

        gains, blocks, until_s = self._fading(prev, is_new, serving, frame.speed_mps, t_s, dt_s)
        snr_lin = np.where(has_site, ch.db_to_linear(np.nan_to_num(snr_serving_db, nan=-np.inf)), 0.0)
        block_rates = ch.link_rate_bps(snr_lin[:, None] * gains, share[:, None], cfg)  # [V, K]
        in_use = np.arange(gains.shape[1])[None, :] < blocks[:, None]
        rate_bps = np.where(has_site, (block_rates * in_use).sum(axis=1) / np.maximum(blocks, 1), 0.0)

        changed = np.flatnonzero(serving != prev.serving)
        handovers = tuple(
            Handover(t_s, str(frame.ids[i]), int(prev.serving[i]), int(serving[i])) for i in changed
        )
        for h in handovers:
            log.debug("t=%.2f s: %s site %d -> %d", h.t_s, h.vehicle_id, h.from_site, h.to_site)

        self._state = dataclasses.replace(
            prev,
            x_m=np.asarray(frame.x_m, dtype=np.float64).copy(),
            y_m=np.asarray(frame.y_m, dtype=np.float64).copy(),
            los_z=los_z,
            shadow_z=shadow_z,
            filtered_dbm=filtered_dbm,
            serving=serving,
            weak_since_s=weak_since_s,
            beats_since_s=beats_since_s,
            fade_gain=gains,
            fade_blocks=blocks,
            fade_until_s=until_s,
            fade_site=serving.copy(),
        )
        self._t_prev_s = t_s
        return LinkSnapshot(
            t_s=t_s,
            ids=np.asarray(frame.ids).copy(),
            site=serving.copy(),
            rx_power_dbm=rx_serving,
            snr_db=snr_serving_db,
            rate_bps=rate_bps,
            cell_load=cell_load.astype(np.int64),
            handovers=handovers,
        )

    def _fading(self, prev: _State, is_new, serving, speed_mps, t_s: float, dt_s: float):
        """Block fading: keep each vehicle's gains until their coherence time runs out.

        When the last step spanned several coherence times, the step's rate is
        averaged over that many fresh blocks (at most K).
        """
        cfg = self.channel
        n, k = prev.fade_gain.shape
        draws = self._rng.exponential(1.0, size=(n, k))  # drawn every step: a fixed stream
        if not cfg.fading:
            return np.ones((n, k)), np.ones(n, dtype=np.int64), np.full(n, np.inf)
        coherence_s = ch.coherence_time_s(speed_mps, cfg.carrier_hz, cfg.fading_min_speed_mps)
        redraw = is_new | (serving != prev.fade_site) | (t_s >= prev.fade_until_s - _EPS_S)
        fresh_blocks = np.clip(np.floor(dt_s / coherence_s + _EPS_S), 1, k).astype(np.int64)
        gains = np.where(redraw[:, None], draws, prev.fade_gain)
        blocks = np.where(redraw, fresh_blocks, prev.fade_blocks)
        until_s = np.where(redraw, t_s + fresh_blocks * coherence_s, prev.fade_until_s)
        return gains, blocks, until_s


def background_users(
    sites: Sequence[EdgeSite], x_m: np.ndarray, y_m: np.ndarray, config: MobilityConfig
) -> np.ndarray:
    """Expected other users per site, float [S]: ``config.background_active_share`` of the background
    vehicles at (x_m, y_m) within a site's coverage, each counted at its nearest site (the strongest
    mean power where masts and channels are alike), plus ``config.cell_background_users`` everywhere."""
    extra = np.full(len(sites), float(config.cell_background_users))
    if config.background_active_share == 0.0 or len(x_m) == 0:
        return extra
    site_x = np.array([s.x_m for s in sites])
    site_y = np.array([s.y_m for s in sites])
    d_m = np.hypot(np.asarray(x_m, np.float64)[:, None] - site_x, np.asarray(y_m, np.float64)[:, None] - site_y)
    nearest = d_m.argmin(axis=1)
    covered = d_m[np.arange(len(nearest)), nearest] <= config.coverage_radius_m
    return extra + config.background_active_share * np.bincount(nearest[covered], minlength=len(sites))


def l3_filter(previous_dbm: np.ndarray, measured_dbm: np.ndarray, dt_s: float, time_constant_s: float) -> np.ndarray:
    """Layer-3 filter F = F_prev + a (M - F_prev), a = 1 - exp(-dt / tau), in dB (pure).

    The time-continuous form of TS 38.331's F_n = (1 - a) F_n-1 + a M_n, so that
    steps of any length filter alike; tau = 0 passes M through, and a link
    without history (NaN) starts at its measurement.
    """
    if time_constant_s <= 0.0:
        return measured_dbm
    weight = 1.0 - math.exp(-dt_s / time_constant_s)
    return np.where(np.isnan(previous_dbm), measured_dbm, previous_dbm + weight * (measured_dbm - previous_dbm))


def associate(serving, beats_since_s, weak_since_s, rx_dbm, in_range, eligible, t_s: float, mob: MobilityConfig):
    """One association step, vectorised over vehicles x sites (pure).

    serving [V] int (-1 none), beats_since_s [V, S] (NaN where a site does not
    beat the serving one), weak_since_s [V] (NaN while the serving site is
    strong enough), rx_dbm, in_range and eligible [V, S]. Returns the new
    (serving, beats_since_s, weak_since_s).

    A vehicle without a site, one that left its site's range, or one whose
    site has stayed below ``min_rx_power_dbm`` for ``radio_link_failure_s``
    (T310) attaches at once to the strongest eligible site (or to none).
    Otherwise a site that beats the serving one by the margin starts a timer;
    the strongest site whose timer reached the time-to-trigger takes over.
    """
    n, n_sites = rx_dbm.shape
    rows = np.arange(n)
    masked = np.where(eligible, rx_dbm, -np.inf)
    best = np.where(eligible.any(axis=1), np.argmax(masked, axis=1), NO_SITE)

    serving_col = np.where(serving >= 0, serving, 0)
    reachable = (serving >= 0) & in_range[rows, serving_col]
    weak = reachable & ~eligible[rows, serving_col]
    weak_since_s = np.where(weak, np.where(np.isnan(weak_since_s), t_s, weak_since_s), np.nan)
    link_failed = weak & (t_s - weak_since_s >= mob.radio_link_failure_s - _EPS_S)
    keeps = reachable & ~link_failed
    rx_serving = np.where(keeps, rx_dbm[rows, serving_col], np.inf)
    others = np.arange(n_sites)[None, :] != serving[:, None]
    beats = keeps[:, None] & others & eligible & (rx_dbm > rx_serving[:, None] + mob.handover_margin_db)
    since_s = np.where(beats, np.where(np.isnan(beats_since_s), t_s, beats_since_s), np.nan)
    ready = beats & (t_s - since_s >= mob.time_to_trigger_s - _EPS_S)
    target = np.argmax(np.where(ready, rx_dbm, -np.inf), axis=1)

    new_serving = np.where(keeps, np.where(ready.any(axis=1), target, serving), best)
    # Timers measure against the serving site: a new serving site restarts them.
    moved = new_serving != serving
    since_s = np.where(moved[:, None], np.nan, since_s)
    weak_since_s = np.where(moved, np.nan, weak_since_s)
    return new_serving.astype(np.int64), since_s, weak_since_s


PING_PONG_S = 5.0  # a handover undone within this time counts as a ping-pong


def ping_pongs(handovers: Sequence[Handover], within_s: float = PING_PONG_S) -> int:
    """How many site-to-site handovers went back to the site served before within ``within_s`` (pure).

    Per vehicle, in time order, only changes between two sites count (attaches
    and losses of coverage are not handovers): A -> B at t0 followed by
    B -> A at t1 <= t0 + within_s is one ping-pong.
    """
    by_vehicle: dict[str, list[Handover]] = {}
    for h in sorted(handovers, key=lambda h: h.t_s):
        if h.from_site != NO_SITE and h.to_site != NO_SITE:
            by_vehicle.setdefault(h.vehicle_id, []).append(h)
    return sum(
        1
        for changes in by_vehicle.values()
        for first, then in itertools.pairwise(changes)
        if then.to_site == first.from_site and then.t_s - first.t_s <= within_s + _EPS_S
    )
