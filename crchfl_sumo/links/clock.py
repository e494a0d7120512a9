"""The federation's mobility clock: each vehicle's link over simulated time, and transfers over it.

A clock answers one question: over ``[from_s, to_s]``, what rate [bit/s]
does a vehicle get and which site serves it, step by step? Two kinds of
link are asked for: ``edge`` (the road-side units, the hierarchical schemes)
and ``macro`` (SFL's direct vehicle <-> cloud link over public macro cells).
It also tells where a vehicle is and how it moves (``pose``), from which
client selection predicts how long it stays in its cell (links/residence.py).

* ``SumoClock`` steps SUMO and the LinkModel(s) lazily, only as far as the
  latest question needs, and keeps every step's rate and serving site of the
  federated vehicles. The series is a pure function of the scenario, the
  seed and the link settings: the bandwidth of a cell is shared among the
  federated vehicles it serves (all marked transmitting), not among the ones
  that happen to transmit at that moment, and among the background users
  that ``[mobility]`` puts in it (a share of the other vehicles there, and a
  fixed number per cell). That keeps the clock independent
  of the learning loop, so a resumed run that re-runs SUMO from the start
  (libsumo is deterministic) sees exactly the same links.
* ``ScriptedClock`` plays fixed per-vehicle tracks: tests and the
  ``constant`` clock of run configs (no mobility at all).

``wireless_transfer`` integrates a transfer of N bytes over a vehicle's
series with ``transfer.transfer``, asking the clock for more time until the
outcome is settled, and applies the receiving-site rules of the handover
policies (docs/federation.md).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Literal, Mapping, Protocol, Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.links.channel import ChannelConfig, WirelineConfig
from crchfl_sumo.links.macro import MacroLinkConfig, macro_link_model
from crchfl_sumo.links.mobility import NO_SITE, LinkModel, MobilityConfig, background_users
from crchfl_sumo.links.residence import Pose
from crchfl_sumo.links.transfer import TransferConfig, TransferResult, transfer, wireline_transfer_time_s
from crchfl_sumo.sumo.scenario import Scenario

log = logging.getLogger(__name__)

LinkKind = Literal["edge", "macro"]
_EPS_S = 1e-9


@dataclass(frozen=True)
class LinkSeries:
    """One vehicle's link, sample by sample; each sample holds until the next.

    t_s [N] strictly increasing; rate_bps [N] (0 = no coverage); site [N]
    serving site index (-1 = none).
    """

    t_s: np.ndarray
    rate_bps: np.ndarray
    site: np.ndarray


class Clock(Protocol):
    """What the federation loop needs from mobility."""

    start_s: float  # simulated time the federation starts at
    step_s: float  # spacing of the samples

    def series(self, vehicle: str, kind: LinkKind, from_s: float, to_s: float) -> LinkSeries:
        """Samples of ``vehicle``'s link: the first at or before ``from_s``, the last at or after ``to_s``."""
        ...

    def handovers(self, until_s: float) -> int:
        """Changes of serving site (site to site, not to or from no coverage) of the federated vehicles
        on the run's link (edge; SFL: macro) up to ``until_s``."""
        ...

    def pose(self, vehicle: str, t_s: float) -> Pose | None:
        """``vehicle``'s position, speed and heading at its latest sample at or before ``t_s``;
        None where the clock has none (no mobility, or the vehicle is not driving then)."""
        ...


# ------------------------------------------------------------------ scripted


@dataclass(frozen=True)
class Segment:
    """From ``t_s`` on (until the next segment) the vehicle is served by ``site`` at ``rate_bps``."""

    t_s: float
    site: int
    rate_bps: float


class ScriptedClock:
    """Fixed piecewise-constant tracks per vehicle, sampled every ``step_s``.

    ``tracks[vehicle]`` are the edge-link segments (sorted by time, the first
    at 0); ``macro_tracks`` those of the macro link (default: the edge
    tracks). A vehicle without a track has no coverage. ``motion[vehicle]``
    is its pose at time 0, from which it drives straight on at that speed
    (the segments are the test's to make agree with it); without one,
    ``pose`` is None.
    """

    def __init__(
        self,
        tracks: Mapping[str, Sequence[Segment]],
        step_s: float = 1.0,
        macro_tracks: Mapping[str, Sequence[Segment]] | None = None,
        start_s: float = 0.0,
        motion: Mapping[str, Pose] | None = None,
    ) -> None:
        if not step_s > 0:
            raise ValueError(f"ScriptedClock: step_s must be > 0, got {step_s}")
        self.step_s = float(step_s)
        self.start_s = float(start_s)
        self._tracks = {"edge": dict(tracks), "macro": dict(tracks if macro_tracks is None else macro_tracks)}
        self._motion = dict(motion or {})
        for kind in self._tracks.values():
            for vehicle, segments in kind.items():
                times = [s.t_s for s in segments]
                if not segments or times != sorted(times) or times[0] > 0:
                    raise ValueError(f"ScriptedClock: track of {vehicle} must be time-sorted and start at 0")

    @classmethod
    def constant(
        cls, sites: Mapping[str, int], rate_bps: float, step_s: float = 1.0, macro_rate_bps: float | None = None
    ) -> "ScriptedClock":
        """Every vehicle served by its site at one rate for ever (no mobility)."""
        edge = {v: [Segment(0.0, s, rate_bps)] for v, s in sites.items()}
        macro = {v: [Segment(0.0, 0, rate_bps if macro_rate_bps is None else macro_rate_bps)] for v in sites}
        return cls(edge, step_s, macro)

    def series(self, vehicle: str, kind: LinkKind, from_s: float, to_s: float) -> LinkSeries:
        first = math.floor(from_s / self.step_s + _EPS_S)
        last = max(math.ceil(to_s / self.step_s - _EPS_S), first)
        t = np.arange(first, last + 1, dtype=np.float64) * self.step_s
        t[0] = min(t[0], from_s)  # times within _EPS_S count as equal: the series must still cover from_s
        segments = self._tracks[kind].get(vehicle, [Segment(0.0, NO_SITE, 0.0)])
        starts = np.array([s.t_s for s in segments])
        index = np.clip(np.searchsorted(starts, t + _EPS_S, side="right") - 1, 0, None)
        rate = np.array([seg.rate_bps for seg in segments], dtype=np.float64)[index]
        site = np.array([seg.site for seg in segments], dtype=np.int64)[index]
        return LinkSeries(t, np.where(site >= 0, rate, 0.0), site)

    def pose(self, vehicle: str, t_s: float) -> Pose | None:
        start = self._motion.get(vehicle)
        if start is None:
            return None
        t_s = math.floor(t_s / self.step_s + _EPS_S) * self.step_s  # the sample at or before t_s
        travelled_m = start.speed_mps * t_s
        return Pose(start.x_m + travelled_m * math.cos(start.heading_rad),
                    start.y_m + travelled_m * math.sin(start.heading_rad), start.speed_mps, start.heading_rad)

    def handovers(self, until_s: float) -> int:
        count = 0
        for segments in self._tracks["edge"].values():
            sites = [s.site for s in segments if s.t_s <= until_s + _EPS_S]
            count += sum(1 for a, b in zip(sites, sites[1:]) if a != b and a != NO_SITE and b != NO_SITE)
        return count


# ------------------------------------------------------------------ SUMO


class SumoClock:
    """SUMO + LinkModel(s) stepped lazily; use as a context manager (libsumo: one per process).

    ``vehicles`` are the federated vehicles (the data vehicles); only they
    enter the link models. ``kinds`` says which links to model: ``edge``
    uses the scenario's edge sites, ``macro`` SFL's macro cells.
    """

    def __init__(
        self,
        scenario: Scenario,
        vehicles: Sequence[str],
        seed: int,
        kinds: Sequence[LinkKind] = ("edge",),
        channel: ChannelConfig = ChannelConfig(),
        mobility: MobilityConfig = MobilityConfig(),
        macro: MacroLinkConfig = MacroLinkConfig(),
        collector=None,
    ) -> None:
        """``collector``: an online.OnlineCollector shown every frame (the ``online`` data mode)."""
        from crchfl_sumo.sumo.simulation import Simulation

        self.scenario = scenario
        self.vehicles = tuple(vehicles)
        self.step_s = scenario.step_length_s
        # The link models need only the federated vehicles; the online collector also what their cameras see.
        around_m = 0.0 if collector is None else collector.neighbourhood_m
        # Background vehicles that load the cells (mobility.background_active_share) need every vehicle's position.
        self._loaded = mobility.background_active_share > 0 or mobility.cell_background_users > 0
        focus = None if mobility.background_active_share > 0 else self.vehicles
        self._sim = Simulation(
            scenario, seed=seed, watch=(), keep_demand=self.vehicles, focus=focus, around_m=around_m
        )
        # Separate seeds per link kind, so adding the macro link leaves the edge link unchanged.
        seeds = np.random.SeedSequence([seed, 7919]).spawn(2)
        self._links: dict[str, LinkModel] = {}
        if "edge" in kinds:
            self._links["edge"] = LinkModel(scenario.edge_sites, channel, mobility, np.random.default_rng(seeds[0]))
        if "macro" in kinds:
            bounds = scenario.bounds
            box = (bounds.xmin_m, bounds.ymin_m, bounds.xmax_m, bounds.ymax_m)
            self._links["macro"] = macro_link_model(macro, box, channel, mobility, np.random.default_rng(seeds[1]))
        self.collector = collector
        self._column = {v: i for i, v in enumerate(self.vehicles)}
        # One row per step, one column per vehicle, grown by doubling: a series is a slice, not a list copy.
        self._steps = 0
        self._t = np.zeros(64)
        self._rate = {k: np.zeros((64, len(self.vehicles))) for k in self._links}
        self._site = {k: np.full((64, len(self.vehicles)), NO_SITE, dtype=np.int64) for k in self._links}
        self._handover_t: dict[str, list[float]] = {k: [] for k in self._links}  # site-to-site changes
        # x, y, speed, heading per step and vehicle (NaN: not driving then); float32 keeps 200 clients small
        self._pose = np.full((64, len(self.vehicles), 4), np.nan, dtype=np.float32)
        self.start_s = 0.0

    def __enter__(self) -> "SumoClock":
        self._sim.__enter__()
        self._advance()  # the first frame: the federation starts at its time
        self.start_s = float(self._t[0])
        return self

    def __exit__(self, *exc_info) -> None:
        self._sim.close()

    @property
    def t_s(self) -> float:
        """Simulated time of the latest step."""
        return float(self._t[self._steps - 1])

    def _advance(self) -> None:
        frame = self._sim.step()
        if self.collector is not None:
            self.collector.observe(frame)
        keep = np.isin(frame.ids, self.vehicles)
        mine = frame.select(keep)
        if self._steps == len(self._t):
            self._grow()
        row = self._steps
        self._t[row] = float(frame.t_s)
        columns = [self._column[str(v)] for v in mine.ids]  # absent vehicles keep 0 bit/s and no site
        self._pose[row, columns] = np.stack([mine.x_m, mine.y_m, mine.speed_mps, mine.heading_rad], axis=1)
        others = frame.select(~keep) if self._loaded else None  # a copy a step: only when the traffic loads
        for kind, links in self._links.items():
            users = None if others is None else background_users(links.sites, others.x_m, others.y_m, links.mobility)
            snapshot = links.step(mine, background_users=users)
            self._handover_t[kind].extend(
                h.t_s for h in snapshot.handovers if h.from_site != NO_SITE and h.to_site != NO_SITE
            )
            self._rate[kind][row, columns] = snapshot.rate_bps
            self._site[kind][row, columns] = snapshot.site
        self._steps += 1

    def _grow(self) -> None:
        rows = len(self._t)
        self._t = np.concatenate([self._t, np.zeros(rows)])
        self._pose = np.concatenate([self._pose, np.full_like(self._pose, np.nan)])
        for kind in self._links:
            self._rate[kind] = np.concatenate([self._rate[kind], np.zeros_like(self._rate[kind])])
            self._site[kind] = np.concatenate([self._site[kind], np.full_like(self._site[kind], NO_SITE)])

    def handovers(self, until_s: float) -> int:
        while self.t_s < until_s - _EPS_S:
            self._advance()
        kind = "edge" if "edge" in self._links else "macro"
        return sum(1 for t in self._handover_t[kind] if t <= until_s + _EPS_S)

    def pose(self, vehicle: str, t_s: float) -> Pose | None:
        column = self._column.get(vehicle)
        if column is None:
            raise CrchflError(f"vehicle '{vehicle}' is not one of the clock's vehicles {list(self.vehicles)}")
        while self.t_s < t_s - _EPS_S:
            self._advance()
        row = max(int(np.searchsorted(self._t[: self._steps], t_s + _EPS_S, side="right")) - 1, 0)
        x_m, y_m, speed_mps, heading_rad = (float(value) for value in self._pose[row, column])
        return None if math.isnan(x_m) else Pose(x_m, y_m, speed_mps, heading_rad)

    def collected(self, vehicle: str, t_s: float):
        """The online collector's labelled samples of ``vehicle`` at ``t_s`` (None if none)."""
        while self.t_s < t_s - _EPS_S:
            self._advance()
        return self.collector.collected(vehicle, t_s)

    def series(self, vehicle: str, kind: LinkKind, from_s: float, to_s: float) -> LinkSeries:
        if kind not in self._links:
            raise ValueError(f"SumoClock: link kind {kind!r} was not requested")
        column = self._column.get(vehicle)
        if column is None:
            raise CrchflError(f"vehicle '{vehicle}' is not one of the clock's vehicles {list(self.vehicles)}")
        while self.t_s < to_s - _EPS_S:
            self._advance()
        t = self._t[: self._steps]
        first = max(int(np.searchsorted(t, from_s + _EPS_S, side="right")) - 1, 0)
        last = int(np.searchsorted(t, to_s - _EPS_S, side="left"))
        sl = slice(first, last + 1)
        times = t[sl].copy()
        times[0] = min(times[0], from_s)  # times within _EPS_S count as equal: the series must still cover from_s
        return LinkSeries(times, self._rate[kind][sl, column].copy(), self._site[kind][sl, column].copy())


# ------------------------------------------------------------------ transfers


@dataclass(frozen=True)
class WirelessOutcome:
    """One wireless transfer on the clock.

    ok: every byte arrived; end_s: arrival, or when it was given up;
    sent_bytes: bytes delivered by end_s; site: the site serving the vehicle
    when the last byte arrived (-1 if it failed); reason: "done", "outage"
    or "deadline" (transfer.TransferResult).
    """

    ok: bool
    start_s: float
    end_s: float
    sent_bytes: float
    site: int
    reason: str


def wireless_transfer(
    clock: Clock,
    vehicle: str,
    kind: LinkKind,
    start_s: float,
    size_bytes: float,
    cfg: TransferConfig,
    *,
    only_site: int | None = None,
    horizon_s: float = 60.0,
    max_span_s: float = 86400.0,
) -> WirelessOutcome:
    """Send ``size_bytes`` between ``vehicle`` and its network from ``start_s`` on.

    ``only_site``: the transfer runs only while that site serves the vehicle
    (rate 0 elsewhere, an outage for ``cfg``); None: any serving site carries
    it. The clock is asked for ``horizon_s`` at first, then for twice as
    much, until the outcome lies within known time; a transfer unsettled
    after ``max_span_s`` is given up ("outage").
    """
    span_s = horizon_s
    while True:
        link = clock.series(vehicle, kind, start_s, start_s + span_s)
        rate = link.rate_bps if only_site is None else np.where(link.site == only_site, link.rate_bps, 0.0)
        result = transfer(link.t_s, rate, start_s, size_bytes, cfg)
        if result.end_t_s <= link.t_s[-1] + _EPS_S:
            break
        if span_s >= max_span_s:
            return WirelessOutcome(False, start_s, start_s + max_span_s, result.sent_bytes, NO_SITE, "outage")
        span_s = min(2.0 * span_s, max_span_s)
    site = NO_SITE
    if result.ok:
        # the sample whose rate carried the last bit
        i = int(np.searchsorted(link.t_s, result.end_t_s - _EPS_S, side="left")) - 1
        i = min(max(i, int(np.searchsorted(link.t_s, start_s + _EPS_S, side="right")) - 1), len(link.t_s) - 1)
        site = int(link.site[i]) if only_site is None else only_site
    return WirelessOutcome(result.ok, start_s, result.end_t_s, result.sent_bytes, site, result.reason)


def with_deadline(cfg: TransferConfig, deadline_s: float) -> TransferConfig:
    """``cfg`` with its whole-transfer deadline cut to ``deadline_s`` (if that is shorter)."""
    return dataclasses.replace(cfg, deadline_s=min(cfg.deadline_s, deadline_s))


# ------------------------------------------------------------------ downloads across handovers

DownloadHandover = Literal["relay", "restart", "drop"]
DOWNLOAD_HANDOVERS = ("relay", "restart", "drop")


@dataclass(frozen=True)
class Relay:
    """Bytes of a download moved over the wireline from the site that held them to the vehicle's new site."""

    from_site: int
    to_site: int
    start_s: float  # the handover
    end_s: float  # arrival at the new site, which sends them on from then
    size_bytes: float


def edge_download(
    clock: Clock,
    vehicle: str,
    site: int,
    start_s: float,
    size_bytes: float,
    cfg: TransferConfig,
    wireline: WirelineConfig,
    policy: DownloadHandover,
    *,
    horizon_s: float = 60.0,
    max_span_s: float = 86400.0,
) -> tuple[WirelessOutcome, tuple[Relay, ...]]:
    """Edge ``site`` sends ``size_bytes`` to ``vehicle`` from ``start_s``; ``policy`` says what a handover does.

    drop: the download runs only while ``site`` serves the vehicle (time
    elsewhere is an outage for ``cfg``). relay: when another site serves the
    vehicle, the bytes not yet sent go over the wireline from the site holding
    them to the new one (latency + size / rate), which sends them on once they
    are there. restart: the same with the whole model, sent again from its
    first byte. Coverage gaps are outages under ``cfg`` in all three, and
    ``cfg.deadline_s`` counts from ``start_s``. ``sent_bytes`` counts every
    byte sent over the air (a restart's lost ones too).
    """
    if policy == "drop":
        out = wireless_transfer(clock, vehicle, "edge", start_s, size_bytes, cfg, only_site=site,
                                horizon_s=horizon_s, max_span_s=max_span_s)
        return out, ()
    relays: list[Relay] = []
    holder, leg_start_s, left, aired = site, start_s, float(size_bytes), 0.0
    while True:
        deadline_left_s = start_s + cfg.deadline_s - leg_start_s
        if deadline_left_s <= _EPS_S:
            return WirelessOutcome(False, start_s, start_s + cfg.deadline_s, aired, NO_SITE, "deadline"), tuple(relays)
        result, handover = _download_leg(
            clock, vehicle, holder, leg_start_s, left, with_deadline(cfg, deadline_left_s), horizon_s, max_span_s
        )
        aired += result.sent_bytes
        if handover is None:
            out = WirelessOutcome(result.ok, start_s, result.end_t_s, aired, holder if result.ok else NO_SITE,
                                  result.reason)
            return out, tuple(relays)
        handover_s, new_site = handover
        left = left - result.sent_bytes if policy == "relay" else float(size_bytes)
        arrival_s = handover_s + wireline_transfer_time_s(left, wireline)
        relays.append(Relay(holder, new_site, handover_s, arrival_s, left))
        holder, leg_start_s = new_site, arrival_s


def _download_leg(clock, vehicle, site, start_s, size_bytes, cfg, horizon_s, max_span_s):
    """One leg of a download from ``site``: (result, None) if it settles there, else (result so far,
    (handover time, the new site)) when another site takes the vehicle over first."""
    span_s = horizon_s
    while True:
        link = clock.series(vehicle, "edge", start_s, start_s + span_s)
        rate = np.where(link.site == site, link.rate_bps, 0.0)
        moved = np.flatnonzero((link.site != site) & (link.site != NO_SITE))
        if len(moved):
            i = int(moved[0])
            handover_s = max(float(link.t_s[i]), start_s)
            # the leg's series ends at the handover (rate 0 from then: nothing more is sent from here)
            t = np.append(link.t_s[:i], handover_s) if i else np.array([start_s])
            r = np.append(rate[:i], 0.0) if i else np.array([0.0])
            result = transfer(t, r, start_s, size_bytes, cfg)
            if result.ok or result.end_t_s < handover_s - _EPS_S:
                return result, None
            return result, (handover_s, int(link.site[i]))
        result = transfer(link.t_s, rate, start_s, size_bytes, cfg)
        if result.end_t_s <= link.t_s[-1] + _EPS_S:
            return result, None
        if span_s >= max_span_s:
            return TransferResult(False, start_s + max_span_s, result.sent_bytes, result.stalled_s, "outage"), None
        span_s = min(2.0 * span_s, max_span_s)
