"""The data side's settings that a run config holds, apart from the modules that import torch: the online data mode's.
"""

from __future__ import annotations

from dataclasses import dataclass

from crchfl_sumo.core.errors import CrchflError


@dataclass(frozen=True)
class OnlineConfig:
    """Settings of the online data mode (TOML ``[online]``).

    max_samples: collected samples a vehicle keeps, the newest (each is four
        uint8 images: about 98 KB at 64 x 128, so 2000 take about 200 MB a vehicle).
    """

    max_samples: int = 2000

    def __post_init__(self) -> None:
        if self.max_samples < 1:
            raise CrchflError(f"online.max_samples: {self.max_samples} must be >= 1")
