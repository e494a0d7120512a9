"""The data side's settings, apart from the modules that import torch: a data set's size and split
(DatasetConfig, TownSplit, the paper's PAPER_TOWNS) and the online data mode's (OnlineConfig).

Also the data side's size bounds that torch-free settings share (a vehicle's samples, the sample period).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range

MAX_SAMPLES_PER_VEHICLE = 100_000  # the paper's largest is 2928; more only fills the disk (98 KB each)
MAX_SAMPLE_PERIOD_S = 60.0  # samples a minute apart are no driving sequence (paper: 0.25 s)
PAPER_SAMPLE_PERIOD_S = 0.25  # the paper's: four samples a second (dataset.DatasetConfig's default)
MAX_STANDING_SAMPLE_EVERY = 1000  # longer than any wait at a signal, at any sample period


@dataclass(frozen=True)
class OnlineConfig:
    """Settings of the online data mode (TOML ``[online]``).

    max_samples: collected samples a vehicle keeps, the newest (each is four
        uint8 images: about 98 KB at 64 x 128, so 2000 take about 200 MB a vehicle).
    """

    max_samples: int = 2000

    def __post_init__(self) -> None:
        check_range(self.max_samples, "online.max_samples", 1, MAX_SAMPLES_PER_VEHICLE, "a number of samples a vehicle")


@dataclass(frozen=True)
class TownSplit:
    """Sample counts of one town: one entry per training vehicle and per test vehicle."""

    town: str
    train_samples: tuple[int, ...]
    test_samples: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not self.town:
            raise CrchflError("dataset.towns: every town needs a non-empty 'town'")
        for name in ("train_samples", "test_samples"):
            counts = getattr(self, name)
            if any(not 1 <= n <= MAX_SAMPLES_PER_VEHICLE for n in counts):
                raise CrchflError(
                    f"dataset.towns.{self.town}.{name}: every count must be in 1 .. {MAX_SAMPLES_PER_VEHICLE}, "
                    f"got {list(counts)}"
                )
        if not self.train_samples:
            raise CrchflError(f"dataset.towns.{self.town}.train_samples: give at least one training vehicle")


# The paper's data set (FACTS.md): 2 + 3 training vehicles and one test set per town.
PAPER_TOWNS = (
    TownSplit("town01", train_samples=(2928, 2928), test_samples=(1061,)),
    TownSplit("town02", train_samples=(2586, 2587, 1555), test_samples=(1020,)),
)


MAX_LANE_CHANGE_S = 60.0


@dataclass(frozen=True)
class DatasetConfig:
    """How big a data set is and how its samples are charged.

    sample_period_s: simulated time between two samples of a vehicle (paper: 0.25 s).
    towns: per-town sample counts (default: the paper's split).
    compression: HDF5 filter for the images, 'lzf' (default: fast), 'gzip' or 'none'.
    recovery_share: share of each vehicle's moving samples rendered from a
        perturbed pose and labelled to steer back (data/recovery.py); 0 turns it off.
    recovery_lateral_m, recovery_yaw_deg: the perturbation is drawn uniformly
        within +-recovery_lateral_m sideways and +-recovery_yaw_deg in heading.
        1 m keeps the car's side within a 4 m lane (1.8 m wide car: 1.1 m to
        the line); 15 deg gives labels up to the outer steer classes.
    recovery_queue_share: share of the standing samples with a standing leader
        2 to 5 m ahead rendered moved closer to it (0.5 to 2 m, nearer than SUMO
        ever stands) and labelled to stay (data/recovery.py); 0 (default) turns
        it off: measured, it did not help (docs/dataset.md).
    recovery_red_share: share of the standing samples within 3 m of a red
        stop line rendered moved 1 to 6 m back from it and labelled to stay
        (data/recovery.py); 0 turns it off. The default 0.5 fills the gap
        that made models cross on red after creeping up to the line
        (docs/model.md, "Red-line samples").
    lane_change_s: how long SUMO takes to move a data vehicle over to another
        lane (its --lanechange.duration; SUMO's default 0 jumps in one step), so
        that the track, the images and the steer labels of a lane change are a
        smooth sideways move. 3 s is 42 m at the towns' 13.9 m/s, about the
        30 m over which a planned route changes lanes (sumo/route.py). It changes
        nothing on roads of one lane per direction (Town01, Town02).
    standing_sample_every: a standing data vehicle (slower than the expert's
        stop_speed_mps, 0.1 m/s) is sampled at one sampling step in this many (those
        at whole multiples of it since the run's start); 1 samples it like a
        moving one. The default 4 (once a second at the paper's 0.25 s) keeps a
        red light's wait from filling a vehicle's sample count with
        near-identical standing images: the vehicle drives on, and its count
        holds more moving samples (docs/dataset.md).

    What a sample costs in the byte ledger is the ledger's setting
    (``ledger.sample_size``); ``measured_sample_bytes`` supplies the measured size.
    """

    sample_period_s: float = PAPER_SAMPLE_PERIOD_S
    towns: tuple[TownSplit, ...] = PAPER_TOWNS
    compression: Literal["lzf", "gzip", "none"] = "lzf"
    recovery_share: float = 0.25
    recovery_lateral_m: float = 1.0
    recovery_yaw_deg: float = 15.0
    recovery_queue_share: float = 0.0
    lane_change_s: float = 3.0
    # Written out even at its default: a folder started when the default was 0 (a reproduce.json that
    # leaves the key out) is refused on resume instead of mixing two recipes.
    recovery_red_share: float = 0.5
    # Written out where not 1: a folder started when sampling ignored standing is refused on resume.
    standing_sample_every: int = 4

    def __post_init__(self) -> None:
        for name in ("recovery_share", "recovery_queue_share", "recovery_red_share"):
            if not 0 <= getattr(self, name) <= 1:
                raise CrchflError(f"dataset.{name} must lie in [0, 1], got {getattr(self, name)}")
        if not 0 <= self.recovery_lateral_m <= 2:
            raise CrchflError(
                f"dataset.recovery_lateral_m must lie in [0, 2] (half a 4 m lane), got {self.recovery_lateral_m}"
            )
        if not 0 <= self.recovery_yaw_deg <= 45:
            raise CrchflError(f"dataset.recovery_yaw_deg must lie in [0, 45], got {self.recovery_yaw_deg}")
        # a lane change of a minute is a drift, not a manoeuvre
        check_range(self.lane_change_s, "dataset.lane_change_s", 0, MAX_LANE_CHANGE_S, "seconds")
        check_range(self.sample_period_s, "dataset.sample_period_s", 0, MAX_SAMPLE_PERIOD_S, "simulated seconds",
                    lo_open=True)
        every = self.standing_sample_every
        if isinstance(every, bool) or not isinstance(every, int) or not 1 <= every <= MAX_STANDING_SAMPLE_EVERY:
            raise CrchflError(
                f"dataset.standing_sample_every: {every!r} is not a whole number of sampling steps in "
                f"1 .. {MAX_STANDING_SAMPLE_EVERY}; give 1 to sample a standing vehicle like a moving one"
            )
        names = [t.town for t in self.towns]
        if not names:
            raise CrchflError("dataset.towns: list at least one town")
        if len(set(names)) != len(names):
            raise CrchflError(f"dataset.towns: each town may appear once, got {names}")


@dataclass(frozen=True)
class PlannedShard:
    """One shard a generation run must produce: file name, town, split and size."""

    file: str
    town: str
    split: str
    index: int  # vehicle number within (town, split)
    samples: int


def shard_plan(config: DatasetConfig) -> list[PlannedShard]:
    """The shards of a data set, in generation order; names are stable so a rerun can resume."""
    plan = []
    for town in config.towns:
        for split, counts in (("train", town.train_samples), ("test", town.test_samples)):
            for index, samples in enumerate(counts):
                plan.append(PlannedShard(f"{town.town}-{split}-{index}.h5", town.town, split, index, samples))
    return plan
