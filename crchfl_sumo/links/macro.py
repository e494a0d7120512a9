"""SFL's links: vehicles straight to the cloud over a grid of macro cells (the same association and rate models as the edges, other sites and radio settings).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.links.channel import ChannelConfig
from crchfl_sumo.links.mobility import LinkModel, MobilityConfig
from crchfl_sumo.sumo.sites import MAX_HEIGHT_M, EdgeSite, hex_lattice


@dataclass(frozen=True)
class MacroLinkConfig:
    """SFL's long-range vehicle <-> cloud link over public macro cells (TOML ``[sfl_link]``).

    The vehicle side (transmit power, antenna, fading, rate model) comes from
    ``[channel]``; these keys set the macro side: TR 38.901 UMa, NR band n78
    at 3.5 GHz, 25 m masts on a hexagonal grid of 500 m inter-site distance
    (TR 38.901 Table 7.2-1), 8 dBi base-station antenna element and 5 dB
    noise figure (ITU-R M.2412 / TR 38.802 evaluation assumptions), and
    10 MHz per cell for the simulated vehicles (the carrier is shared with
    other users of a public network).
    """

    carrier_hz: float = 3.5e9
    bandwidth_hz: float = 10e6
    site_antenna_gain_dbi: float = 8.0
    noise_figure_db: float = 5.0
    site_height_m: float = 25.0
    inter_site_distance_m: float = 500.0
    coverage_radius_m: float = 2000.0
    min_rx_power_dbm: float = -109.0  # about -10 dB SNR in 10 MHz with a 5 dB noise figure
    # Explicit macro sites; empty = a hexagonal grid over the network with a
    # site at the network's centre.
    sites: tuple[EdgeSite, ...] = ()

    def __post_init__(self) -> None:
        for key in ("carrier_hz", "bandwidth_hz", "site_height_m", "inter_site_distance_m", "coverage_radius_m"):
            if not getattr(self, key) > 0:
                raise CrchflError(f"sfl_link.{key} must be > 0, got {getattr(self, key)}")
        check_range(self.site_height_m, "sfl_link.site_height_m", 0, MAX_HEIGHT_M, "metres", lo_open=True)
        if not 100.0 <= self.inter_site_distance_m <= 100e3:  # a grid finer than that has sites by the thousand
            raise CrchflError(
                f"sfl_link.inter_site_distance_m must be in 100 .. 100000 m (TR 38.901 UMa: 500), "
                f"got {self.inter_site_distance_m}"
            )
        try:  # the macro side's values within the channel's and the association's ranges, checked now
            self.channel_config(ChannelConfig())
            self.mobility_config(MobilityConfig())
        except CrchflError as exc:
            raise CrchflError(f"sfl_link: {exc}") from None

    def channel_config(self, base: ChannelConfig) -> ChannelConfig:
        """``base`` (the vehicle side) with the macro side of this config."""
        return dataclasses.replace(
            base,
            scenario="uma",
            carrier_hz=self.carrier_hz,
            bandwidth_hz=self.bandwidth_hz,
            site_antenna_gain_dbi=self.site_antenna_gain_dbi,
            noise_figure_db=self.noise_figure_db,
        )

    def mobility_config(self, base: MobilityConfig) -> MobilityConfig:
        """``base`` handover settings with macro coverage."""
        return dataclasses.replace(
            base, coverage_radius_m=self.coverage_radius_m, min_rx_power_dbm=self.min_rx_power_dbm
        )

    def resolve_sites(self, bounds_m: tuple[float, float, float, float]) -> tuple[EdgeSite, ...]:
        """The explicit sites, or a hexagonal grid covering ``bounds_m`` = (xmin, ymin, xmax, ymax)."""
        if self.sites:
            return self.sites
        return hex_grid_sites(bounds_m, self.inter_site_distance_m, self.site_height_m)


def hex_grid_sites(
    bounds_m: tuple[float, float, float, float], spacing_m: float, height_m: float, prefix: str = "macro"
) -> tuple[EdgeSite, ...]:
    """Sites on a hexagonal lattice (neighbours ``spacing_m`` apart) centred on the bounds
    (sites.hex_lattice), named ``{prefix}{i}`` in row-major order."""
    lattice = hex_lattice(bounds_m, spacing_m)
    return tuple(EdgeSite(f"{prefix}{i}", float(x), float(y), height_m) for i, (x, y) in enumerate(lattice))


def macro_link_model(
    macro: MacroLinkConfig,
    bounds_m: tuple[float, float, float, float],
    channel: ChannelConfig = ChannelConfig(),
    mobility: MobilityConfig = MobilityConfig(),
    seed: int | np.random.Generator = 0,
) -> LinkModel:
    """The LinkModel of SFL's direct vehicle <-> cloud link."""
    return LinkModel(
        macro.resolve_sites(bounds_m), macro.channel_config(channel), macro.mobility_config(mobility), seed
    )
