"""Paths to the packaged data: built-in scenarios, drive routes, run presets.

The one place that knows where they are. They live in the repository's
``scenarios/`` folder and ship as the package ``crchfl_sumo.scenarios``;
importlib.resources finds them in a checkout, an editable install and a wheel
alike. SUMO reads files by path, so the package must be installed unzipped
(pip always does).
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def scenarios_dir() -> Path:
    """The folder of built-in scenarios: one subfolder per scenario, with its scenario.toml."""
    return Path(str(files("crchfl_sumo.scenarios")))


def builtin_names() -> list[str]:
    """The built-in scenarios' names: the packaged folders with a scenario.toml."""
    return sorted(p.parent.name for p in scenarios_dir().glob("*/scenario.toml"))


def drive_routes_path() -> Path:
    """The named routes that `drive` and `reproduce` drive."""
    return scenarios_dir() / "drive_routes.toml"


def experiments_dir() -> Path:
    """The run presets: crchfl, hfl, sfl (run configs), reproduce_quick, reproduce_full, mobility_quick, mobility_full."""
    return scenarios_dir() / "experiments"


def street_types_path() -> Path:
    """The street types every built-in network is made with (netconvert --type-files)."""
    return scenarios_dir() / "street.typ.xml"
