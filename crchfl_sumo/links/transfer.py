"""How long a transfer of N bytes takes over a link whose rate changes as the vehicle moves.

A wireless link is a rate series (t_s, rate_bps), constant from one sample to
the next and the last sample held for ever (append a (t_end, 0) sample to end
a trace). The transfer's bits are the integral of the rate from its start, so
a vehicle that drives into a better cell finishes sooner than
"size / rate at the start" says. A stretch of zero rate is an outage: the
transfer either waits for coverage (``on_outage = "stall"``, at most
``max_outage_s`` per outage) or fails at once (``"fail"``). ``deadline_s``
bounds the whole transfer under either policy. Wireline links are a latency
plus size over a constant rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from crchfl_sumo.core.numbers import MAX_SIMULATED_S, check_range
from crchfl_sumo.links.channel import WirelineConfig

OutagePolicy = Literal["stall", "fail"]


@dataclass(frozen=True)
class TransferConfig:
    """What a wireless transfer does when the vehicle loses coverage (TOML ``[transfer]``)."""

    on_outage: OutagePolicy = "stall"
    max_outage_s: float = 30.0  # longest single outage a stalled transfer survives
    deadline_s: float = math.inf  # longest whole transfer, start to finish

    def __post_init__(self) -> None:
        # a simulated day at most: the longest a command simulates. inf: no limit (the loop's "wait" policy stalls
        # until the aggregation deadline; a config file cannot give it, its default being finite: core.config)
        check_range(self.max_outage_s, "transfer.max_outage_s", 0, MAX_SIMULATED_S, "simulated seconds", inf_ok=True)
        check_range(self.deadline_s, "transfer.deadline_s", 0, MAX_SIMULATED_S, "simulated seconds (or inf: none)",
                    lo_open=True, inf_ok=True)


@dataclass(frozen=True)
class TransferResult:
    """Outcome of one transfer.

    ok          True if every byte arrived
    end_t_s     finish time if ok, else the time the transfer was given up
    sent_bytes  bytes delivered by end_t_s
    stalled_s   time spent without coverage between start and end_t_s
    reason      "done", "outage" (coverage lost: policy "fail", or an outage
                longer than max_outage_s) or "deadline"
    """

    ok: bool
    end_t_s: float
    sent_bytes: float
    stalled_s: float
    reason: Literal["done", "outage", "deadline"]

    def duration_s(self, start_t_s: float) -> float:
        return self.end_t_s - start_t_s


def transfer(
    t_s,
    rate_bps,
    start_t_s: float,
    size_bytes: float,
    cfg: TransferConfig = TransferConfig(),
) -> TransferResult:
    """Send ``size_bytes`` from ``start_t_s`` over the piecewise-constant rate series (t_s, rate_bps)."""
    t, rate = _check_series(t_s, rate_bps, start_t_s)
    if not size_bytes >= 0:
        raise ValueError(f"transfer: size_bytes must be >= 0, got {size_bytes}")
    starts, ends, rates = _segments_from(t, rate, start_t_s)
    deadline_t = start_t_s + cfg.deadline_s
    left_bits = 8.0 * size_bytes
    sent_bits = stalled_s = 0.0
    if left_bits == 0:
        return TransferResult(True, float(start_t_s), 0.0, 0.0, "done")
    # Closed form per segment; segments are the rate's changes, not the vehicles.
    for a, b, r in zip(starts.tolist(), ends.tolist(), rates.tolist()):
        if r > 0:
            finish_t = a + left_bits / r
            if finish_t <= min(b, deadline_t):
                return TransferResult(True, float(finish_t), float(size_bytes), stalled_s, "done")
            if b >= deadline_t:
                sent_bits += r * (deadline_t - a)
                break
            sent_bits += r * (b - a)
            left_bits -= r * (b - a)
            continue
        # An outage (runs of zero rate are merged, so b is where coverage returns).
        if cfg.on_outage == "fail":
            return TransferResult(False, float(a), sent_bits / 8.0, stalled_s, "outage")
        give_up_t = a + cfg.max_outage_s
        if b > give_up_t and give_up_t < deadline_t:
            stalled_s += cfg.max_outage_s
            return TransferResult(False, float(give_up_t), sent_bits / 8.0, stalled_s, "outage")
        if b >= deadline_t:
            stalled_s += deadline_t - a
            break
        stalled_s += b - a
    return TransferResult(False, float(deadline_t), sent_bits / 8.0, stalled_s, "deadline")


def _segments_from(t: np.ndarray, rate: np.ndarray, start_t_s: float):
    """(starts, ends, rates) of constant-rate segments from ``start_t_s`` on, equal neighbours merged."""
    first = np.searchsorted(t, start_t_s, side="right") - 1
    t, rate = t[first:].copy(), rate[first:]
    t[0] = start_t_s
    change = np.ones(len(rate), dtype=bool)
    change[1:] = rate[1:] != rate[:-1]
    starts, rates = t[change], rate[change]
    ends = np.append(starts[1:], math.inf)
    return starts, ends, rates


def _check_series(t_s, rate_bps, start_t_s: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t_s, dtype=np.float64)
    rate = np.asarray(rate_bps, dtype=np.float64)
    if t.ndim != 1 or t.shape != rate.shape or len(t) == 0:
        raise ValueError(f"transfer: t_s and rate_bps must be equal-length 1-D arrays, got {t.shape}, {rate.shape}")
    if np.any(np.diff(t) <= 0):
        raise ValueError("transfer: t_s must be strictly increasing")
    if np.any(~np.isfinite(rate)) or np.any(rate < 0):
        raise ValueError("transfer: rate_bps must be finite and >= 0")
    if start_t_s < t[0]:
        raise ValueError(f"transfer: start {start_t_s} s precedes the rate series (from {t[0]} s)")
    return t, rate


def wireline_transfer_time_s(size_bytes: float, cfg: WirelineConfig) -> float:
    """Seconds to move ``size_bytes`` over a wireline link: latency + size / rate."""
    if not size_bytes >= 0:
        raise ValueError(f"wireline_transfer_time_s: size_bytes must be >= 0, got {size_bytes}")
    return cfg.latency_s + 8.0 * size_bytes / cfg.rate_bps
