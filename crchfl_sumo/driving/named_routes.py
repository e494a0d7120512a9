"""Named evaluation routes (scenarios/drive_routes.toml): a route name brings its scenario and edges."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from crchfl_sumo.core.config import from_mapping, read_toml
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.resources import drive_routes_path


@dataclass(frozen=True)
class DriveRoute:
    """A named evaluation route of drive_routes.toml."""

    scenario: str
    edges: tuple[str, ...]
    description: str = ""


def load_drive_routes(path: str | Path | None = None) -> dict[str, DriveRoute]:
    """Route name -> DriveRoute from a routes TOML (``[routes.NAME]`` tables); default: the built-in routes."""
    path = drive_routes_path() if path is None else path
    data = read_toml(path)
    unknown = sorted(set(data) - {"routes"})
    if unknown:
        raise CrchflError(f"{path}: unknown top-level key(s) {unknown}; put routes under [routes.NAME]")
    return {
        name: from_mapping(DriveRoute, table, where=f"{path}: routes.{name}")
        for name, table in data.get("routes", {}).items()
    }


def resolve_route(route: str, scenario: str | None) -> tuple[str, tuple[str, ...]]:
    """(scenario, edges) for a route name of drive_routes.toml, or for edge ids separated by commas/spaces.

    A named route brings its scenario; a list of edges needs ``scenario``.
    """
    named = load_drive_routes()
    if route in named:
        entry = named[route]
        if scenario is not None and scenario != entry.scenario:
            raise CrchflError(
                f"route '{route}' runs in scenario '{entry.scenario}', not '{scenario}'; drop --scenario or match it"
            )
        return entry.scenario, entry.edges
    edges = tuple(e for e in route.replace(",", " ").split() if e)
    if scenario is None or not edges:
        raise CrchflError(
            f"route '{route}' is not a named route ({', '.join(sorted(named))}); "
            "name one, or give --scenario and the edge ids separated by commas"
        )
    return scenario, edges
