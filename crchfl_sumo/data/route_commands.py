"""Route commands: what a vehicle's own path does at the next junction (follow, left, right, straight).

The command at arc position s of a path (sumo/turns.py finds the passes
through junctions with a choice):

    the first junction pass not yet left whose entry lies within
    lookahead_m ahead (or that the vehicle is inside):
        |turn| <= straight_within_deg  -> STRAIGHT
        turn > 0 (counter-clockwise)   -> LEFT
        turn < 0                       -> RIGHT
    none                               -> FOLLOW

Positions are the vehicle's centre. The same lookup serves the data vehicles
(their recorded track: ``track_commands``) and the drive loop (the ego's
planned RouteGeometry: ``RouteCommands``), so both see the same definition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.data.labels import FOLLOW, LEFT, RIGHT, STRAIGHT
from crchfl_sumo.sumo.route import RouteGeometry
from crchfl_sumo.sumo.turns import Junction, arc_length_m, junction_passages, next_passage

# A pass through a junction ends at most this far beyond its entry (T-junctions: 12-22 m of path).
MAX_PASSAGE_M = 40.0
MAX_LOOKAHEAD_M = 1000.0


@dataclass(frozen=True)
class CommandConfig:
    """How commands are read off a path (TOML ``[command]``).

    lookahead_m: a junction's command starts this far (vehicle centre to the
        junction's outline) before it. 25 m is 1.8 s at the towns' 13.9 m/s
        limit, more than the 11 m the steer label leads a turn by, and shorter
        than the shortest road between two junctions (Town02: 33 m), so that
        FOLLOW separates the commands of consecutive junctions.
    straight_within_deg: a pass that turns by at most this much is STRAIGHT.
    """

    lookahead_m: float = 25.0
    straight_within_deg: float = 45.0

    def __post_init__(self) -> None:
        # a junction farther ahead than a kilometre is no "next junction" (the paper's 25 m)
        check_range(self.lookahead_m, "command.lookahead_m", 0, MAX_LOOKAHEAD_M, "metres")
        if not 0 < self.straight_within_deg < 90:
            raise CrchflError(f"command.straight_within_deg must lie in (0, 90), got {self.straight_within_deg}")

    @property
    def path_ahead_m(self) -> float:
        """Path a position needs ahead of it before its command is final."""
        return self.lookahead_m + MAX_PASSAGE_M


def command_from_turn(turn_rad: np.ndarray, config: CommandConfig = CommandConfig()) -> np.ndarray:
    """Turn through a junction (CCW positive) -> LEFT, RIGHT or STRAIGHT code."""
    turn_rad = np.asarray(turn_rad, dtype=np.float64)
    straight = np.abs(turn_rad) <= math.radians(config.straight_within_deg)
    return np.where(straight, STRAIGHT, np.where(turn_rad > 0, LEFT, RIGHT)).astype(np.int64)


class PathCommands:
    """The commands along one path (polyline [N, 2] in driving order), looked up by arc position."""

    def __init__(self, xy_m: np.ndarray, junctions: Sequence[Junction], config: CommandConfig = CommandConfig()):
        self.config = config
        self.passages = junction_passages(xy_m, junctions)
        self._codes = command_from_turn([p.turn_rad for p in self.passages], config)

    def at(self, s_m: np.ndarray | float) -> np.ndarray:
        """Command code (labels.COMMAND_NAMES) at each arc position [m] of the path."""
        index = next_passage(self.passages, s_m, self.config.lookahead_m)
        if not self.passages:
            return np.full(len(index), FOLLOW, dtype=np.int64)
        return np.where(index >= 0, self._codes[np.maximum(index, 0)], FOLLOW).astype(np.int64)


def track_commands(
    x_m: np.ndarray, y_m: np.ndarray, junctions: Sequence[Junction], config: CommandConfig = CommandConfig()
) -> np.ndarray:
    """Command at every position of a recorded track (its own later positions are the path ahead)."""
    xy = np.stack([np.asarray(x_m, np.float64), np.asarray(y_m, np.float64)], axis=1)
    return PathCommands(xy, junctions, config).at(arc_length_m(xy))


class RouteCommands(PathCommands):
    """The commands along a planned route's centre line: ``RouteCommands(route, junctions).at(s_m)``,
    s_m the arc position of the vehicle's centre on the route (route.project_points)."""

    def __init__(self, route: RouteGeometry, junctions: Sequence[Junction], config: CommandConfig = CommandConfig()):
        super().__init__(route.xy_m, junctions, config)
