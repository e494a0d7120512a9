"""The reference driver (RoutePolicy) on hand-made routes, by hand: its look-ahead at long steps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crchfl_sumo.driving.dynamics import VehicleState, bicycle_step
from crchfl_sumo.driving.policies import RoutePolicy
from crchfl_sumo.sumo.route import RouteGeometry


def _route(points) -> RouteGeometry:
    xy = np.asarray(points, dtype=np.float64)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    n = len(xy) - 1
    return RouteGeometry(("e",), xy, s, np.full(n, 3.2), np.zeros(n, bool), ())


@pytest.mark.parametrize("step_s, look_m", [(0.0, 4.0), (0.25, 4.0), (0.5, 8.0)])
def test_pure_pursuit_looks_two_steps_ahead(step_s, look_m):
    """On a straight road at 8 m/s, 0.2 rad off its heading: pure pursuit drives the circle through the point
    ``look_m`` ahead, of radius look / (2 sin 0.2), and one 0.5 s step (4 m of it) turns the car by 4 m / radius.
    A 4 m look-ahead (the towns' at 8 m/s) is reached in that one step and the heading swings to about -0.2: it
    sways from side to side for ever; two steps' travel (8 m) brings it level."""
    policy = RoutePolicy(_route([(0.0, 0.0), (500.0, 0.0)]))
    state = VehicleState(0.0, 0.0, 0.2, 8.0)
    steer = policy.steer(state.x_m, state.y_m, state.heading_rad, state.speed_mps, 0.0, step_s)
    after = bicycle_step(state, 0.0, steer, 0.5)
    radius = look_m / (2.0 * math.sin(0.2))
    assert after.heading_rad == pytest.approx(0.2 - 4.0 / radius, abs=1e-9)
    if step_s == 0.5:
        assert abs(after.heading_rad) < 0.002  # level: 0.2 - 4 / 20.13
    else:
        assert after.heading_rad == pytest.approx(-0.197, abs=1e-3)  # swung to the other side
