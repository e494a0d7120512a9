"""Remaining time in a cell on a straight track, against hand-computed cases."""

from __future__ import annotations

import math

import pytest

from crchfl_sumo.links.residence import Coverage, Pose, residence_time_s, sites_coverage
from crchfl_sumo.sumo.sites import EdgeSite

ONE = Coverage(((0.0, 0.0),), 300.0)
TWO = Coverage(((0.0, 0.0), (400.0, 0.0)), 300.0, time_to_trigger_s=2.0)
EAST, NORTH, WEST = 0.0, math.pi / 2, math.pi


def test_driving_away_from_the_site_leaves_at_the_range():
    # 100 m -> 300 m at 10 m/s
    assert residence_time_s(Pose(100.0, 0.0, 10.0, EAST), 0, ONE) == pytest.approx(20.0)


def test_driving_towards_the_site_passes_it_and_leaves_on_the_far_side():
    # 100 m to the site, then 300 m beyond it, at 10 m/s
    assert residence_time_s(Pose(100.0, 0.0, 10.0, WEST), 0, ONE) == pytest.approx(40.0)


def test_a_chord_that_misses_the_site():
    # 100 m south of the site, heading east: leaves where x^2 + 100^2 = 300^2
    assert residence_time_s(Pose(0.0, -100.0, 10.0, EAST), 0, ONE) == pytest.approx(math.sqrt(80_000.0) / 10.0)
    assert residence_time_s(Pose(0.0, -100.0, 5.0, NORTH), 0, ONE) == pytest.approx(400.0 / 5.0)


def test_a_standing_vehicle_stays_for_ever():
    assert residence_time_s(Pose(250.0, 10.0, 0.0, EAST), 0, TWO) == math.inf


def test_no_site_or_out_of_range_is_no_time_left():
    assert residence_time_s(Pose(0.0, 0.0, 10.0, EAST), -1, ONE) == 0.0
    assert residence_time_s(Pose(301.0, 0.0, 10.0, WEST), 0, ONE) == 0.0


def test_the_nearer_site_takes_over_after_the_time_to_trigger():
    # the bisector of sites 0 and 1 is x = 200: 100 m at 10 m/s, then 2 s time-to-trigger (before the range's 20 s)
    assert residence_time_s(Pose(100.0, 0.0, 10.0, EAST), 0, TWO) == pytest.approx(12.0)
    # served by site 1, driving west: the same border from the other side, 200 m away
    assert residence_time_s(Pose(400.0, 0.0, 10.0, WEST), 1, TWO) == pytest.approx(22.0)
    # driving away from site 1: only the range counts
    assert residence_time_s(Pose(100.0, 0.0, 10.0, WEST), 0, TWO) == pytest.approx(40.0)


def test_past_the_border_a_handover_is_pending():
    assert residence_time_s(Pose(250.0, 0.0, 10.0, WEST), 0, TWO) == pytest.approx(2.0)


def test_sites_coverage_reads_edge_sites():
    coverage = sites_coverage([EdgeSite("a", 1.0, 2.0), EdgeSite("b", 3.0, 4.0)], 250.0, 2.56)
    assert coverage == Coverage(((1.0, 2.0), (3.0, 4.0)), 250.0, 2.56)
