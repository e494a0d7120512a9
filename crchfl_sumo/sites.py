"""Edge servers (road-side units) placed in the network frame, and the cloud.

A site is plain data: where the antenna stands. Which vehicles it serves is
mobility.py's business, what rate it gives is channel.py's.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import CrchflError


@dataclass(frozen=True)
class EdgeSite:
    """One edge server's antenna: name, position [m] in the network frame, height [m]."""

    name: str
    x_m: float
    y_m: float
    height_m: float = 10.0

    def __post_init__(self) -> None:
        if not self.name:
            raise CrchflError("edge_sites: every site needs a non-empty 'name'")
        if self.height_m <= 0:
            raise CrchflError(f"edge_sites.{self.name}.height_m must be > 0, got {self.height_m}")
