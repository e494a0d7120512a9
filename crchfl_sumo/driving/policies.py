"""Driving policies: Observation -> (throttle, steer, brake). A trained model, a scripted
route follower (pure pursuit on the lane centre, obeying signals), or a constant action.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_range
from crchfl_sumo.data.expert import ExpertConfig, pedals, steer_from_curvature
from crchfl_sumo.data.labels import FOLLOW
from crchfl_sumo.data.route_commands import PathCommands
from crchfl_sumo.learning.settings import (
    DEFAULT_BRAKE_GAIN,
    DEFAULT_STEER_DECODING,
    STEER_DECODINGS,
    check_brake_gain,
)
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.sumo.route import (
    RED_LETTERS,
    YELLOW_LETTERS,
    Crossing,
    RouteGeometry,
    internal_stop_ahead,
    next_crossing,
    point_at,
    project_points,
    signal_letter,
)

Action = tuple[float, float, float]  # (throttle, steer, brake), labels.py conventions


# --- policies ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Observation:
    """What a policy sees at one step."""

    frame: Frame
    ego_id: str
    ego_row: int
    progress_m: float  # the ego centre's arc position on the route
    images: np.ndarray | None  # uint8 [4, H, W, 3] when the loop renders, else None
    offset_m: float = 0.0  # the ego centre's signed distance from the route's centre line (LEFT +)
    lane_width_m: float = math.inf  # the planned lane's width there
    step_s: float = 0.0  # the loop's step: the action holds this long (0: not known)


Policy = Callable[[Observation], Action]


@dataclass(frozen=True)
class ConstantPolicy:
    """The same action every step (a test of the loop: a hard steer must leave the lane)."""

    throttle: float = 0.3
    steer: float = 0.0
    brake: float = 0.0

    def __call__(self, observation: Observation) -> Action:
        return (self.throttle, self.steer, self.brake)


@dataclass(frozen=True)
class RoutePolicyConfig:
    """A scripted driver that knows the route (no images): the reference the models are compared to.

    target_speed_mps        cruise speed
    lookahead_min_m, lookahead_time_s  pure-pursuit look-ahead max(min, time * speed) on the centre line,
                            and at least LOOKAHEAD_STEPS steps of travel
    speed_gain_per_s        desired acceleration per m/s of speed error
    headway_s, standstill_gap_m  distance kept to a vehicle ahead in the lane: gap >= standstill + headway * v
    comfort_decel_mps2      deceleration planned for stopping at a light
    stop_gap_m              the front bumper stops this far before the stop line
    yield_radius_m          on a minor green ('g') it waits while a vehicle within this distance of
                            the junction's middle moves towards it (or any vehicle is inside it);
                            inside a junction, not on a major green ('G'), short of a turn's internal
                            stop (SUMO's internal junction) and able to stop there, it waits there
                            while also a junction foe it must yield to is within this distance of
                            their conflict point
    hold_short_m            standing this close to a stop line it must stop at (red, or a minor
                            green it yields on), it holds the brake instead of creeping up to the
                            line; 0 (default) creeps. A labeller of a learner's states (DAgger) sets
                            it: a learner that stopped short has stopped, and a creep label there
                            teaches it to roll towards a red light
    """

    target_speed_mps: float = 8.0
    lookahead_min_m: float = 4.0
    lookahead_time_s: float = 0.5
    speed_gain_per_s: float = 1.5
    headway_s: float = 1.5
    standstill_gap_m: float = 3.0
    comfort_decel_mps2: float = 2.5
    stop_gap_m: float = 1.0
    yield_radius_m: float = 30.0
    hold_short_m: float = 0.0

    def __post_init__(self) -> None:
        # (name, upper bound, unit): far beyond any sensible driver, so a typo is caught, not driven
        for name, hi, what in (("target_speed_mps", 70.0, "m/s"), ("lookahead_min_m", 100.0, "metres"),
                               ("speed_gain_per_s", 100.0, "a gain per second"),
                               ("comfort_decel_mps2", 20.0, "m/s^2")):
            check_range(getattr(self, name), f"route_policy.{name}", 0, hi, what, lo_open=True)
        for name, hi, what in (("lookahead_time_s", 10.0, "seconds"), ("headway_s", 10.0, "seconds"),
                               ("standstill_gap_m", 100.0, "metres"), ("stop_gap_m", 100.0, "metres"),
                               ("yield_radius_m", 1000.0, "metres"), ("hold_short_m", 100.0, "metres")):
            check_range(getattr(self, name), f"route_policy.{name}", 0, hi, what)


def leader_gap_m(
    frame: Frame, rows: np.ndarray, route: RouteGeometry, s_m: float, half_length_m: float, ahead_m: float
) -> float:
    """Bumper gap to the nearest of the vehicles ``rows`` that is ahead on ``route`` within ``ahead_m`` of
    the ego's progress ``s_m`` and in its lane (its side within the lane, 0.3 m of overlap allowed);
    inf without one."""
    if len(rows) == 0:
        return math.inf
    s_o, off_o, width_o = project_points(route, frame.x_m[rows], frame.y_m[rows], s_m, s_m + ahead_m)
    ahead = (s_o > s_m) & (np.abs(off_o) < width_o / 2.0 + frame.width_m[rows] / 2.0 - 0.3)
    if not ahead.any():
        return math.inf
    return float((s_o - s_m - frame.length_m[rows] / 2.0 - half_length_m)[ahead].min())


# Pure pursuit aims at a point it reaches in about one step when the look-ahead is one step's travel, and then
# swings from side to side (A10KW's 0.5 s steps at 8 m/s: 4 m a step against a 4 m look-ahead): it looks at least
# this many steps ahead. The towns' 0.25 s steps give 0.5 s * speed, their look-ahead time already.
LOOKAHEAD_STEPS = 2.0


class RoutePolicy:
    """Pure pursuit on the route's centre line, stops at red lights and behind vehicles in its lane,
    yields on a minor green at the stop line and, inside a junction without a major green, at a turn's
    internal stop.

    Its pedals come from the expert's own mapping (expert.pedals) of the
    acceleration it wants, its steer from the expert's curvature mapping, so
    the loop's inverse mappings return exactly what it planned.
    ``wait_at_internal_stop`` False: inside a junction it always clears it (DAgger's labeller).
    """

    def __init__(
        self,
        route: RouteGeometry,
        config: RoutePolicyConfig = RoutePolicyConfig(),
        expert: ExpertConfig = ExpertConfig(),
        wait_at_internal_stop: bool = True,
    ) -> None:
        self.route = route
        self.config = config
        self.expert = expert
        self.wait_at_internal_stop = wait_at_internal_stop

    def steer(
        self, x_m: float, y_m: float, heading_rad: float, speed_mps: float, progress_m: float, step_s: float = 0.0
    ) -> float:
        cfg = self.config
        look = max(cfg.lookahead_min_m, max(cfg.lookahead_time_s, LOOKAHEAD_STEPS * step_s) * speed_mps)
        tx, ty, _ = point_at(self.route, progress_m + look)
        dx, dy = tx - x_m, ty - y_m
        chord = math.hypot(dx, dy)
        kappa = 2.0 * math.sin(math.atan2(dy, dx) - heading_rad) / chord if chord > 1e-6 else 0.0
        return float(steer_from_curvature(kappa, self.expert))

    def wanted_accel_mps2(self, observation: Observation) -> float:
        """Acceleration to cruise, to keep the gap to the vehicle ahead in the lane, and to stop at a light."""
        cfg = self.config
        frame, row = observation.frame, observation.ego_row
        v = float(frame.speed_mps[row])
        max_accel, max_decel = float(frame.max_accel_mps2[row]), float(frame.max_decel_mps2[row])
        half_length = float(frame.length_m[row]) / 2.0
        s = observation.progress_m
        wanted = cfg.target_speed_mps
        others = np.flatnonzero(
            (np.arange(len(frame)) != row) & (np.hypot(frame.x_m - frame.x_m[row], frame.y_m - frame.y_m[row]) < 60.0)
        )
        gap = leader_gap_m(frame, others, self.route, s, half_length, 50.0)
        if gap < math.inf:
            wanted = min(wanted, max(0.0, (gap - cfg.standstill_gap_m) / max(cfg.headway_s, 1e-3)))
        accel = cfg.speed_gain_per_s * (wanted - v)
        front = s + half_length
        index = next_crossing(self.route.crossings, front)
        if index >= 0:
            crossing = self.route.crossings[index]
            letter = signal_letter(crossing, frame.tls_states)
            room = crossing.s_start_m - front - cfg.stop_gap_m
            needed = v * v / (2.0 * room) if room > 0.3 else math.inf
            # Stop for red; for yellow only when that takes no more than a comfortable deceleration;
            # on a minor green ('g': yield) while other traffic is in or heading into the junction.
            yield_now = letter == "g" and self._junction_busy(observation, crossing)
            if letter in RED_LETTERS or yield_now or (letter in YELLOW_LETTERS and needed <= cfg.comfort_decel_mps2):
                accel = self._stopping(accel, room, v, max_decel)
        index = internal_stop_ahead(self.route.crossings, front) if self.wait_at_internal_stop else -1
        if index >= 0:
            # Inside the junction short of its internal stop, as SUMO's own left-turners wait: a turn without
            # priority ('G'; an unsignalised one too) waits there while traffic it must yield to comes, if it
            # can still stop there; past the stop, or too fast to stop short of it, it clears the junction.
            crossing = self.route.crossings[index]
            room = crossing.s_internal_stop_m - front - cfg.stop_gap_m
            can_stop = v < self.expert.stop_speed_mps or v * v <= 2.0 * max_decel * max(room, 0.0)
            yields = signal_letter(crossing, frame.tls_states) != "G"
            if can_stop and yields and self._foe_coming(observation, crossing):
                accel = self._stopping(accel, room, v, max_decel)
        return float(np.clip(accel, -max_decel, max_accel))

    def _stopping(self, accel: float, room: float, v: float, max_decel: float) -> float:
        """The acceleration that stops the front bumper ``room`` metres ahead (or holds it there), at most ``accel``."""
        cfg = self.config
        if room <= 0.3 or (v < self.expert.stop_speed_mps and room <= cfg.hold_short_m):
            return -max_decel
        needed = v * v / (2.0 * room)
        creep = cfg.speed_gain_per_s * (math.sqrt(cfg.comfort_decel_mps2 * room) - v)
        return min(accel, creep, -needed if needed >= 0.5 * cfg.comfort_decel_mps2 else math.inf)

    def _foe_coming(self, observation: Observation, crossing: Crossing) -> bool:
        """Is a junction foe the ego must yield to (SUMO's, Frame.foe_gap_m) within yield_radius_m of the
        conflict point and not through it, while the junction is busy (_junction_busy)? Both, so that a foe
        standing at its own red light does not alone hold the ego inside the junction."""
        frame, row = observation.frame, observation.ego_row
        gap = float(frame.foe_gap_m[row])
        return gap < self.config.yield_radius_m and self._junction_busy(observation, crossing)

    def _junction_busy(self, observation: Observation, crossing: Crossing) -> bool:
        """Is another vehicle inside the junction, or moving towards it, other than those in the ego's lane?"""
        frame, row = observation.frame, observation.ego_row
        cx, cy, _ = point_at(self.route, 0.5 * (crossing.s_start_m + crossing.s_end_m))
        dx, dy = cx - frame.x_m, cy - frame.y_m
        distance = np.hypot(dx, dy)
        closing = (np.cos(frame.heading_rad) * dx + np.sin(frame.heading_rad) * dy) > 0
        near = (np.arange(len(frame)) != row) & (
            (distance < 8.0) | ((distance < self.config.yield_radius_m) & closing & (frame.speed_mps > 0.5))
        )
        rows = np.flatnonzero(near)
        if len(rows) == 0:
            return False
        s = observation.progress_m
        s_o, off_o, width_o = project_points(self.route, frame.x_m[rows], frame.y_m[rows], s - 30.0, s + 30.0)
        in_my_lane = np.abs(off_o) < width_o / 2.0
        behind = in_my_lane & (s_o < s)
        return bool(np.any(~behind & ~(in_my_lane & (s_o > crossing.s_end_m))))

    def __call__(self, observation: Observation) -> Action:
        return self.decide(observation)[0]

    def decide(self, observation: Observation) -> tuple[Action, float]:
        """The action, and the acceleration it wanted (wanted_accel_mps2) before a standing car's hold."""
        frame, row = observation.frame, observation.ego_row
        v = float(frame.speed_mps[row])
        steer = self.steer(
            float(frame.x_m[row]), float(frame.y_m[row]), float(frame.heading_rad[row]), v, observation.progress_m,
            observation.step_s,
        )
        wanted = accel = self.wanted_accel_mps2(observation)
        if v < self.expert.stop_speed_mps and accel < 0:
            accel, steer = 0.0, 0.0  # standing: pedals() holds the brake; wheels straight like the expert's
        max_accel, max_decel = float(frame.max_accel_mps2[row]), float(frame.max_decel_mps2[row])
        # The expert's pedal mapping adds what holding speed costs.
        throttle, brake = pedals(
            np.array([v]), np.array([accel]), np.array([max_accel]), np.array([max_decel]), self.expert
        )
        return (float(throttle[0]), steer, float(brake[0])), wanted


def one_pedal(throttle: float, brake: float) -> tuple[float, float]:
    """Keep the stronger of the two predicted pedals and release the other.

    The expert never presses both (expert.pedals: one of them is always 0),
    so a prediction of both is the model hedging between the two; the
    stronger one is its choice. A tie brakes.
    """
    return (throttle, 0.0) if throttle > brake else (0.0, brake)


class ModelPolicy:
    """A DrivingModel: the ego's four camera images, its route command and its speed ->
    (throttle, steer via the DAC, brake).

    ``commands``: the commands along the ego's planned route, looked up at the
    observation's ``progress_m`` (the ego centre's arc position on that route,
    what data.route_commands expects): ``RouteCommands(route, choice_junctions(net))``,
    the same definition the training data was labelled with. A model of
    arch "paper" sees no command and may go without. The speed is the ego's
    ``frame.speed_mps``; a target-speed model's pedals are scaled by the ego's
    acceleration limits.
    ``one_pedal``: apply only the stronger pedal (``one_pedal``), as the
    expert does; False passes both through to the dynamics.
    ``steer_decoding``: how the steer head's scores become a steer
    (learning.settings.STEER_DECODINGS).
    ``brake_gain``: a target-speed model's lower targets are reached in its
    speed horizon / brake_gain (expert.pedals_towards; 1 = as labelled).
    ``source``: the model file, named when its output is not finite (a CrchflError
    then, before the dynamics see it).
    """

    def __init__(
        self,
        model,
        commands: PathCommands | None = None,
        one_pedal: bool = True,
        steer_decoding: str = DEFAULT_STEER_DECODING,
        brake_gain: float = DEFAULT_BRAKE_GAIN,
        source: str = "the model",
    ) -> None:
        if commands is None and model.config.arch != "paper":
            raise CrchflError(
                "the model policy needs the route's commands for a command-conditioned model (arch "
                f"{model.config.arch!r}); pass ModelPolicy(model, RouteCommands(route, choice_junctions(net)))"
            )
        self.model = model
        self.commands = commands
        self.one_pedal = one_pedal
        if steer_decoding not in STEER_DECODINGS:
            raise CrchflError(f"steer decoding must be one of {', '.join(STEER_DECODINGS)}, got {steer_decoding!r}")
        self.steer_decoding = steer_decoding
        self.brake_gain = check_brake_gain(brake_gain)
        self.source = source

    def command(self, observation: Observation) -> int:
        """The route command (labels.COMMAND_NAMES code) at the ego's position; FOLLOW without commands."""
        if self.commands is None:
            return FOLLOW  # only a paper-architecture model, which ignores it, gets here
        return int(self.commands.at(observation.progress_m)[0])

    def __call__(self, observation: Observation) -> Action:
        import torch

        from crchfl_sumo.learning.model import predict_actions

        if observation.images is None:
            raise CrchflError("the model policy needs camera images; give drive() a renderer")
        images = torch.from_numpy(np.ascontiguousarray(observation.images))
        frame, row = observation.frame, observation.ego_row
        actions = predict_actions(
            self.model, images, self.command(observation), float(frame.speed_mps[row]), self.steer_decoding,
            float(frame.max_accel_mps2[row]), float(frame.max_decel_mps2[row]), self.brake_gain,
        )
        if not np.isfinite(actions).all():
            raise CrchflError(
                f"{self.source}: the model's output at t = {frame.t_s:.2f} s is not finite (throttle, steer, brake = "
                f"{', '.join(f'{v:g}' for v in actions)}); its weights are damaged or diverged: retrain it"
            )
        throttle, steer, brake = (float(v) for v in actions)
        if self.one_pedal:
            throttle, brake = one_pedal(throttle, brake)
        return (throttle, steer, brake)


