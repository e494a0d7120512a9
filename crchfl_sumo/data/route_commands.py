"""Route commands: what a vehicle's own path does at the next junction (follow, left, right, straight), and
where it changes lanes (change_left, change_right).

The command at arc position s of a path (sumo/turns.py finds the passes
through junctions with a choice):

    the first junction pass not yet left whose entry lies within
    lookahead_m ahead (or that the vehicle is inside):
        |turn| <= straight_within_deg  -> STRAIGHT
        turn > 0 (counter-clockwise)   -> LEFT
        turn < 0                       -> RIGHT
    none                               -> FOLLOW
    but from lane_change_lead_m before a lane change's sideways move
    until the move ends                -> CHANGE_LEFT or CHANGE_RIGHT

A lane change is planned on a route (RouteGeometry.lane_changes) or, on a
data vehicle's track, found where SUMO moved it to another lane of the same
edge (``track_lane_changes``). Positions are the vehicle's centre. The same lookup serves the data vehicles
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
from crchfl_sumo.data.expert import Track
from crchfl_sumo.data.labels import CHANGE_LEFT, CHANGE_RIGHT, FOLLOW, LEFT, RIGHT, STRAIGHT
from crchfl_sumo.sumo.route import LaneChange, RouteGeometry, lane_side
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
    lane_change_lead_m: a lane change's command starts this far before its
        sideways move (and holds until the move ends): about the 11 m by
        which the steer label leads the motion, so the command comes first.
    """

    lookahead_m: float = 25.0
    straight_within_deg: float = 45.0
    lane_change_lead_m: float = 10.0

    def __post_init__(self) -> None:
        # a junction farther ahead than a kilometre is no "next junction" (the paper's 25 m)
        check_range(self.lookahead_m, "command.lookahead_m", 0, MAX_LOOKAHEAD_M, "metres")
        check_range(self.lane_change_lead_m, "command.lane_change_lead_m", 0, MAX_LOOKAHEAD_M, "metres")
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
    """The commands along one path (polyline [N, 2] in driving order) with its lane changes (arc positions on
    it), looked up by arc position."""

    def __init__(
        self, xy_m: np.ndarray, junctions: Sequence[Junction], config: CommandConfig = CommandConfig(),
        lane_changes: Sequence[LaneChange] = (),
    ):
        self.config = config
        self.passages = junction_passages(xy_m, junctions)
        self.lane_changes = tuple(lane_changes)
        self._codes = command_from_turn([p.turn_rad for p in self.passages], config)

    def at(self, s_m: np.ndarray | float) -> np.ndarray:
        """Command code (labels.COMMAND_NAMES) at each arc position [m] of the path."""
        index = next_passage(self.passages, s_m, self.config.lookahead_m)
        if self.passages:
            codes = np.where(index >= 0, self._codes[np.maximum(index, 0)], FOLLOW).astype(np.int64)
        else:
            codes = np.full(len(index), FOLLOW, dtype=np.int64)
        s = np.atleast_1d(np.asarray(s_m, dtype=np.float64))
        for change in self.lane_changes:  # a lane change's command wins over the junction's ahead
            during = (s >= change.s_start_m - self.config.lane_change_lead_m) & (s < change.s_end_m)
            codes[during] = CHANGE_LEFT if change.side > 0 else CHANGE_RIGHT
        return codes


def track_lane_changes(track: Track, net, move_s: float) -> tuple[LaneChange, ...]:
    """The lane changes of a recorded track (``Track.lane_id`` per row), at arc positions along it: a row whose
    lane is another lane of the previous row's edge is where SUMO switched the vehicle over. SUMO moves it
    sideways over ``move_s`` seconds (its --lanechange.duration; 0: in one step) and switches its lane
    halfway, so the move spans move_s / 2 either side of the switch. ``net``: the sumolib network, for the side."""
    track_s_m = arc_length_m(np.stack([track.x_m, track.y_m], axis=1))
    t_s, lane_ids = track.t_s, track.lane_id if track.lane_id is not None else ()
    changes = []
    for row in range(1, len(lane_ids)):
        before, after = str(lane_ids[row - 1]), str(lane_ids[row])
        if not before or not after or before == after or before.startswith(":"):
            continue
        edge_before, edge_after = before.rsplit("_", 1)[0], after.rsplit("_", 1)[0]
        if edge_before != edge_after:
            continue
        switch_s = t_s[row - 1] if move_s <= 0 else (t_s[row - 1] + t_s[row]) / 2.0
        start = np.interp(switch_s - move_s / 2.0, t_s, track_s_m)
        end = np.interp(switch_s + move_s / 2.0, t_s, track_s_m)
        changes.append(LaneChange(float(start), float(max(end, track_s_m[row])), lane_side(net.getLane(before),
                                                                                              net.getLane(after))))
    return tuple(changes)


def track_commands(
    x_m: np.ndarray, y_m: np.ndarray, junctions: Sequence[Junction], config: CommandConfig = CommandConfig(),
    lane_changes: Sequence[LaneChange] = (),
) -> np.ndarray:
    """Command at every position of a recorded track (its own later positions are the path ahead); ``lane_changes``
    at arc positions of the track (``track_lane_changes``)."""
    xy = np.stack([np.asarray(x_m, np.float64), np.asarray(y_m, np.float64)], axis=1)
    return PathCommands(xy, junctions, config, lane_changes).at(arc_length_m(xy))


class RouteCommands(PathCommands):
    """The commands along a planned route's centre line: ``RouteCommands(route, junctions).at(s_m)``,
    s_m the arc position of the vehicle's centre on the route (route.project_points)."""

    def __init__(self, route: RouteGeometry, junctions: Sequence[Junction], config: CommandConfig = CommandConfig()):
        super().__init__(route.xy_m, junctions, config, route.lane_changes)
