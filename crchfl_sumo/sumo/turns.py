"""Junctions where a route has a choice, and the turn a path takes through each: the geometry of route commands.

A path is a polyline of positions in driving order: a vehicle's recorded track
(data generation) or a planned route's centre line (the drive loop). It passes
a junction where it runs inside the junction's outline (from the network);
the turn it takes there is the change of its direction of travel between
entering and leaving, in radians, counter-clockwise (left) positive.
data/route_commands.py turns the next turn within a look-ahead into a command.

Only junctions where a driver must choose count: some incoming road leads to
two or more roads (turnarounds aside). A corner of a town's ring, where one
road continues into one other, is lane following, not a junction choice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

SAMPLE_STEP_M = 0.5  # the path is tested against the outlines every 0.5 m of arc length
HEADING_CHORD_M = 2.0  # direction in / out = chord over 2 m just before entering / after leaving


@dataclass(frozen=True)
class Junction:
    """A junction with a choice: its id and outline [K, 2] (network x, y in metres)."""

    id: str
    shape_m: np.ndarray


@dataclass(frozen=True)
class Passage:
    """One pass of a path through a junction, in the path's arc length.

    s_in_m: where the path enters the outline; s_out_m: where it leaves (inf if
    the path ends inside); turn_rad: direction out minus direction in, wrapped
    to (-pi, pi], left positive.
    """

    junction: str
    s_in_m: float
    s_out_m: float
    turn_rad: float


def choice_junctions(net) -> tuple[Junction, ...]:
    """The junctions of a sumolib network where some incoming road leads to two or more roads."""
    found = []
    for node in net.getNodes():
        shape = np.asarray(node.getShape(), dtype=np.float64)
        if len(shape) < 3:
            continue
        for edge in node.getIncoming():
            if edge.getFunction() == "internal":
                continue
            targets = {
                to_edge.getID()
                for to_edge, connections in edge.getOutgoing().items()
                if to_edge.getFunction() != "internal" and any(c.getDirection() != "t" for c in connections)
            }
            if len(targets) >= 2:
                found.append(Junction(node.getID(), shape))
                break
    return tuple(sorted(found, key=lambda j: j.id))


def arc_length_m(xy_m: np.ndarray) -> np.ndarray:
    """Arc length [m] at every vertex of a polyline [N, 2] (0 at the first)."""
    xy_m = np.asarray(xy_m, dtype=np.float64)
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy_m, axis=0).T))])


def _inside(shape: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Even-odd rule for many points [P, 2] against one polygon [K, 2]."""
    xa, ya = shape[:, 0], shape[:, 1]
    xb, yb = np.roll(xa, -1), np.roll(ya, -1)
    px, py = points[:, 0:1], points[:, 1:2]
    straddles = (ya > py) != (yb > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = xa + (py - ya) * (xb - xa) / (yb - ya)
    return (np.count_nonzero(straddles & (x_cross > px), axis=1) % 2).astype(bool)


def junction_passages(
    xy_m: np.ndarray, junctions: Sequence[Junction], step_m: float = SAMPLE_STEP_M
) -> tuple[Passage, ...]:
    """Every pass of the path ``xy_m`` [N, 2] through one of ``junctions``, in driving order."""
    xy_m = np.asarray(xy_m, dtype=np.float64)
    if len(xy_m) < 2:
        return ()
    s = arc_length_m(xy_m)
    moving = np.concatenate([[True], np.diff(s) > 0])  # a standing vehicle repeats its position
    s, xy_m = s[moving], xy_m[moving]
    if len(s) < 2:
        return ()
    grid = np.append(np.arange(0.0, s[-1], step_m), s[-1])

    def at(arc):
        arc = np.clip(arc, 0.0, s[-1])
        return np.stack([np.interp(arc, s, xy_m[:, 0]), np.interp(arc, s, xy_m[:, 1])], axis=-1)

    def direction(a, b):
        d = at(b) - at(a)
        return math.atan2(d[1], d[0])

    points = at(grid)
    passages = []
    for junction in junctions:
        lo, hi = junction.shape_m.min(axis=0), junction.shape_m.max(axis=0)
        near = np.flatnonzero(((points >= lo) & (points <= hi)).all(axis=1))
        if len(near) == 0:
            continue
        inside = np.zeros(len(grid), dtype=bool)
        inside[near] = _inside(junction.shape_m, points[near])
        edges = np.diff(np.concatenate([[False], inside, [False]]).astype(np.int8))
        for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
            s_in = float(grid[a])
            s_out = float(grid[b]) if b < len(grid) else math.inf
            heading_in = direction(max(s_in - HEADING_CHORD_M, 0.0), max(s_in, HEADING_CHORD_M))
            if math.isfinite(s_out):
                heading_out = direction(min(s_out, s[-1] - HEADING_CHORD_M), min(s_out + HEADING_CHORD_M, s[-1]))
            else:  # the path ends inside: the best known direction out is its last one
                heading_out = direction(s[-1] - HEADING_CHORD_M, s[-1])
            turn = math.remainder(heading_out - heading_in, 2 * math.pi)
            passages.append(Passage(junction.id, s_in, s_out, turn))
    return tuple(sorted(passages, key=lambda p: p.s_in_m))


def next_passage(passages: Sequence[Passage], s_m: np.ndarray, lookahead_m: float) -> np.ndarray:
    """Per arc position: index of the passage not yet left whose entry is within ``lookahead_m`` (-1: none)."""
    s_m = np.atleast_1d(np.asarray(s_m, dtype=np.float64))
    if not passages:
        return np.full(len(s_m), -1, dtype=np.int64)
    s_in = np.array([p.s_in_m for p in passages])
    s_out = np.array([p.s_out_m for p in passages])
    # Outlines do not overlap, so the passages' exits are in driving order too.
    k = np.searchsorted(s_out, s_m, side="right")
    valid = k < len(passages)
    kk = np.minimum(k, len(passages) - 1)
    return np.where(valid & (s_in[kk] <= s_m + lookahead_m), kk, -1).astype(np.int64)
