"""The reference driver (RoutePolicy) on hand-made routes, by hand: its look-ahead at long steps, and its wait
at a turn's internal stop."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from crchfl_sumo.core.resources import scenarios_dir
from crchfl_sumo.driving.dynamics import VehicleState, bicycle_step
from crchfl_sumo.driving.policies import Observation, RoutePolicy
from crchfl_sumo.sumo.frame import make_frame
from crchfl_sumo.sumo.route import Crossing, RouteGeometry, internal_stop_ahead, read_net, route_geometry


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


# --- waiting at a turn's internal stop ---------------------------------------------------------------


def test_a_left_turn_at_a_town01_t_junction_has_its_internal_stop_where_its_first_internal_lane_ends():
    net = read_net(scenarios_dir() / "town01" / "town01.net.xml")
    left = route_geometry(net, ["W3_W2", "W2_E2"]).crossings[0]
    first_internal = net.getLane(":W2_1_0").getLength()  # SUMO's internal junction follows it
    assert left.direction == "l" and first_internal == pytest.approx(5.23)
    assert left.s_internal_stop_m == pytest.approx(left.s_start_m + first_internal, abs=0.01)  # SUMO rounds lengths
    assert left.s_end_m == pytest.approx(left.s_internal_stop_m + net.getLane(":W2_6_0").getLength(), abs=0.01)
    straight = route_geometry(net, ["W3_W2", "W2_W1"]).crossings[0]  # one internal lane: no internal stop
    assert straight.direction == "s" and math.isnan(straight.s_internal_stop_m)
    crossings = [left, straight]
    assert internal_stop_ahead(crossings, left.s_start_m) == -1  # on the stop line: not yet in
    assert internal_stop_ahead(crossings, left.s_start_m + 0.1) == 0
    assert internal_stop_ahead(crossings, left.s_internal_stop_m) == -1  # reached it: past
    assert internal_stop_ahead([straight], straight.s_start_m + 1.0) == -1


def _inside_the_turn(
    front_m: float, foe_gap_m: float, letter: str = "g", foe_speed_mps: float = 10.0, speed_mps: float = 3.0
):
    """The ego at ``speed_mps`` on a straight 60 m route whose junction spans 20 to 36 m with its internal stop at
    25 m; a crossing vehicle 20 m beside the junction's middle (28 m) drives towards it at ``foe_speed_mps``;
    SUMO reports the ego's nearest foe ``foe_gap_m`` from their conflict point."""
    route = _route([(0.0, 0.0), (60.0, 0.0)])
    route = dataclasses.replace(route, crossings=(Crossing(20.0, 36.0, "J", 0, "l", s_internal_stop_m=25.0),))
    frame = make_frame(
        ids=["ego", "foe"], x_m=[front_m - 2.25, 28.0], y_m=[0.0, 20.0], heading_rad=[0.0, -math.pi / 2],
        speed_mps=[speed_mps, foe_speed_mps], foe_gap_m=[foe_gap_m, math.inf],
        tls_states={"J": letter} if letter else {},
    )
    return RoutePolicy(route), Observation(frame, "ego", 0, front_m - 2.25, None)  # make_frame's 4.5 m car


def test_inside_a_turn_the_reference_waits_at_the_internal_stop_while_a_foe_comes_by_hand():
    # front at 22 m: 25 - 22 - 1 m (stop gap) = 2 m of room; stopping from 3 m/s there needs 9 / 4 = 2.25 m/s^2
    # (more than half the comfortable 2.5), creeping wants 1.5 x (sqrt(2.5 x 2) - 3) = -1.15: it brakes 2.25.
    policy, waiting = _inside_the_turn(22.0, foe_gap_m=12.0)
    assert policy.wanted_accel_mps2(waiting) == pytest.approx(-2.25)
    policy, unsignalised = _inside_the_turn(22.0, foe_gap_m=12.0, letter="")  # no signal: SUMO's foe decides
    assert policy.wanted_accel_mps2(unsignalised) == pytest.approx(-2.25)
    policy, standing = _inside_the_turn(23.9, foe_gap_m=12.0, speed_mps=0.0)  # 0.1 m of room left: it holds
    assert policy.wanted_accel_mps2(standing) == -4.5  # make_frame's max_decel
    free_accel = 2.6  # make_frame's maximum: cruising to 8 m/s from 3 (or 5) wants 1.5 x 5 (or 3)
    for front, gap, letter, foe_speed, speed in (
        (22.0, math.inf, "g", 10.0, 3.0),  # SUMO reports no foe to yield to
        (22.0, 40.0, "g", 10.0, 3.0),  # beyond yield_radius_m (30 m) of the conflict point
        (22.0, 12.0, "G", 10.0, 3.0),  # a priority green: the foes yield
        (22.0, 12.0, "g", 0.0, 3.0),  # the foe stands (at its own red, say) and nothing moves towards the junction
        (25.5, 12.0, "g", 10.0, 3.0),  # past the internal stop: it clears the junction
        (22.0, 12.0, "g", 10.0, 5.0),  # too fast to stop in 2 m (25 / 4 = 6.25 m/s^2 > 4.5): it clears
    ):
        policy, observation = _inside_the_turn(front, gap, letter, foe_speed, speed)
        assert policy.wanted_accel_mps2(observation) == pytest.approx(free_accel), (front, letter, foe_speed, speed)


def test_dagger_labels_with_an_expert_that_clears_the_junction_instead():
    from crchfl_sumo.data.expert import ExpertConfig
    from crchfl_sumo.driving.dagger import labeller
    from crchfl_sumo.driving.dagger_settings import DaggerConfig

    reference, waiting = _inside_the_turn(22.0, foe_gap_m=12.0)
    assert reference.wanted_accel_mps2(waiting) == pytest.approx(-2.25)
    expert = labeller(reference.route, DaggerConfig(), ExpertConfig())
    assert expert.wanted_accel_mps2(waiting) == pytest.approx(2.6)  # it drives on, as with no foe at all
