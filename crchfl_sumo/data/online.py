"""Online data mode: vehicles keep collecting training samples as they drive.

A vehicle's generated shard holds what it recorded up to the shard's last
sample time; in the ``online`` mode it keeps recording after that, on the
federation's own SUMO run: every ``sample_period_s`` the collector renders
the vehicle's four camera images (raster.py, with the data set's own camera
and world settings) and keeps its kinematics. A sample is labelled by the
expert (expert.py) and given its route command (commands.py) once the
vehicle has driven ``recording.FUTURE_S`` past it (the look-ahead the expert
needs) and ``CommandConfig.path_ahead_m`` metres beyond it (what the command
needs to see the next junction's pass), so a sample's label never changes
after it first appears. Collected samples are all rendered on the track (no
recovery perturbation). Each vehicle keeps at most ``max_samples`` collected samples
(on-board storage): the newest.

What a vehicle trains on at time t is its shard plus the samples it had
collected and could label by t; FedAvg weights and training time follow
those counts. Collected samples never leave the vehicle (nothing is charged).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.data.expert import ExpertConfig, Track, expert_labels, target_speeds
from crchfl_sumo.data.recording import FUTURE_S
from crchfl_sumo.data.route_commands import CommandConfig, track_commands
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.data.settings import OnlineConfig
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.sumo.route import read_net
from crchfl_sumo.sumo.turns import arc_length_m, choice_junctions
from crchfl_sumo.vision.raster import RasterConfig, Renderer, neighbourhood_m
from crchfl_sumo.vision.world import WorldConfig, build_world

_COLUMNS = ("x_m", "y_m", "heading_rad", "speed_mps", "accel_mps2", "max_accel_mps2", "max_decel_mps2")


class OnlineCollector:
    """Renders and keeps each federated vehicle's samples from the frames it is shown, in time order.

    ``start_after_s[v]``: vehicle v collects only at sample times after this
    (its shard's last sample). Frames must come at the scenario's step.
    """

    def __init__(
        self,
        net_path,
        vehicles: Sequence[str],
        start_after_s: Mapping[str, float],
        sample_period_s: float,
        step_s: float,
        raster: RasterConfig = RasterConfig(),
        world: WorldConfig = WorldConfig(),
        expert: ExpertConfig = ExpertConfig(),
        config: OnlineConfig = OnlineConfig(),
        command: CommandConfig = CommandConfig(),
    ) -> None:
        every = int(round(sample_period_s / step_s))
        if every < 1 or not math.isclose(every * step_s, sample_period_s, rel_tol=1e-6):
            raise CrchflError(
                f"online mode: the data set's sample period {sample_period_s} s is not a multiple of the "
                f"scenario's step length {step_s} s; use the scenario the data set was generated with"
            )
        self.vehicles = tuple(vehicles)
        self._every, self._step_s = every, step_s
        self._start_after_s = {v: float(start_after_s.get(v, -math.inf)) for v in self.vehicles}
        self._renderer = Renderer(build_world(net_path, world), raster)
        self.neighbourhood_m = neighbourhood_m(raster)  # what a frame must hold around each vehicle
        self._expert = expert
        self._command = command
        self._junctions = choice_junctions(read_net(Path(net_path)))
        self._max = config.max_samples
        self._rows: dict[str, dict[str, list[float]]] = {v: {c: [] for c in ("t_s", *_COLUMNS)} for v in self.vehicles}
        self._sample_t: dict[str, list[float]] = {v: [] for v in self.vehicles}
        self._images: dict[str, list[np.ndarray]] = {v: [] for v in self.vehicles}
        self._labels: dict[str, tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self.t_s = -math.inf

    def observe(self, frame: Frame) -> None:
        """Record one step: every vehicle's kinematics, and its images at sample times."""
        self.t_s = float(frame.t_s)
        rows = {str(v): i for i, v in enumerate(frame.ids.tolist())}
        sample_step = round(frame.t_s / self._step_s) % self._every == 0
        takers = []
        for v in self.vehicles:
            i = rows.get(v)
            if i is None:
                continue
            store = self._rows[v]
            store["t_s"].append(self.t_s)
            for c in _COLUMNS:
                store[c].append(float(getattr(frame, c)[i]))
            if sample_step and self.t_s > self._start_after_s[v] + 1e-9:
                takers.append(v)
        if not takers:
            return
        images = self._renderer.render(frame, takers)
        for v, image in zip(takers, images):
            self._sample_t[v].append(self.t_s)
            self._images[v].append(image)

    def collected(self, vehicle: str, now_s: float) -> Samples | None:
        """The labelled samples ``vehicle`` holds at ``now_s`` (None if none): the newest ``max_samples``.

        Needs frames up to ``now_s``. A vehicle's calls must come at
        non-decreasing times: samples older than the oldest one returned are
        forgotten (the clock runs ahead of the loop, so storage is trimmed
        here, at the vehicle's own time, not when a frame is observed).
        """
        if now_s > self.t_s + 1e-9:
            raise ValueError(f"OnlineCollector.collected: asked for {now_s} s but frames end at {self.t_s} s")
        times = np.asarray(self._sample_t[vehicle], dtype=np.float64)
        track_t = np.asarray(self._rows[vehicle]["t_s"])
        # Final labels only: FUTURE_S of time and path_ahead_m of path driven since the sample, by now_s.
        arc = arc_length_m(np.stack([self._rows[vehicle]["x_m"], self._rows[vehicle]["y_m"]], axis=1))
        now_row = np.searchsorted(track_t, now_s + 1e-9, side="right") - 1
        final_arc = arc[now_row] - self._command.path_ahead_m if now_row >= 0 else -math.inf
        sample_arc = arc[np.searchsorted(track_t, times - 1e-9)] if len(times) else times
        keep = np.flatnonzero((times <= now_s - FUTURE_S + 1e-9) & (sample_arc <= final_arc + 1e-9))[-self._max :]
        if len(keep) == 0:
            return None
        if keep[0] > 0:  # on-board storage: the older samples are gone for good
            del self._sample_t[vehicle][: keep[0]], self._images[vehicle][: keep[0]]
            times, keep = times[keep[0] :], keep - keep[0]
        actions, steer_class, commands, targets = self._labels_for(vehicle)
        rows = np.searchsorted(track_t, times[keep] - 1e-9)
        images = np.stack([self._images[vehicle][k] for k in keep])
        speed_mps = np.asarray(self._rows[vehicle]["speed_mps"], dtype=np.float32)[rows]
        return Samples.from_numpy(images, actions[rows], steer_class[rows], commands[rows], speed_mps, targets[rows])

    def _labels_for(self, vehicle: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Expert labels, commands and target speeds over the vehicle's whole track so far (cached until it grows)."""
        store = self._rows[vehicle]
        n = len(store["t_s"])
        cached = self._labels.get(vehicle)
        if cached is None or cached[0] != n:
            track = Track(vehicle, *(np.asarray(store[c], dtype=np.float64) for c in ("t_s", *_COLUMNS)))
            actions, steer_class = expert_labels(track, self._expert)
            commands = track_commands(track.x_m, track.y_m, self._junctions, self._command)
            cached = (n, actions, steer_class, commands, target_speeds(track, self._expert))
            self._labels[vehicle] = cached
        return cached[1:]
