"""The data side's settings that a run config holds, apart from the modules that import torch: the online data mode's.

Also the data side's size bounds that torch-free settings share (a vehicle's samples, the sample period).
"""

from __future__ import annotations

from dataclasses import dataclass

from crchfl_sumo.core.numbers import check_range

MAX_SAMPLES_PER_VEHICLE = 100_000  # the paper's largest is 2928; more only fills the disk (98 KB each)
MAX_SAMPLE_PERIOD_S = 60.0  # samples a minute apart are no driving sequence (paper: 0.25 s)
PAPER_SAMPLE_PERIOD_S = 0.25  # the paper's: four samples a second (dataset.DatasetConfig's default)


@dataclass(frozen=True)
class OnlineConfig:
    """Settings of the online data mode (TOML ``[online]``).

    max_samples: collected samples a vehicle keeps, the newest (each is four
        uint8 images: about 98 KB at 64 x 128, so 2000 take about 200 MB a vehicle).
    """

    max_samples: int = 2000

    def __post_init__(self) -> None:
        check_range(self.max_samples, "online.max_samples", 1, MAX_SAMPLES_PER_VEHICLE, "a number of samples a vehicle")
