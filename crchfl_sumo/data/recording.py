"""The data set's simulation run: every step's Frame, and which of them are each vehicle's samples.

Stage 1 of generation (data/generation.py): the scenario runs once. Each
planned vehicle is sampled every ``sample_period_s`` from its departure until
it has its sample count; the run goes on ``FUTURE_S`` more seconds so the last
samples have a path ahead to label. It also goes on until each of them has
driven ``CommandConfig.path_ahead_m`` past its last sample, so that the last
samples' route commands are known. The online data mode (online.py) waits the
same ``FUTURE_S`` before it labels a collected sample.
"""

from __future__ import annotations

import logging
import math

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.sumo.scenario import Scenario
from crchfl_sumo.sumo.simulation import Simulation

log = logging.getLogger(__name__)

FUTURE_S = 10.0  # simulated time kept after the last sample: >= the look-ahead at any town speed


def steps_per_sample(scenario: Scenario, sample_period_s: float) -> int:
    """Simulation steps between two samples of a vehicle; the period must be a whole number of steps."""
    step_s = scenario.step_length_s
    every = int(round(sample_period_s / step_s))
    if every < 1 or not math.isclose(every * step_s, sample_period_s, rel_tol=1e-6):
        raise CrchflError(
            f"dataset.sample_period_s = {sample_period_s} is not a multiple of the scenario's step "
            f"length {step_s} s; choose a multiple"
        )
    return every


def record_run(
    scenario: Scenario,
    seed: int,
    needed: dict[str, int],
    sample_period_s: float,
    progress: Progress | None = None,
    around_m: float | None = None,
    ahead_m: float = 0.0,
    sumo_options: tuple[str, ...] = (),
    standing_every: int = 1,
    stop_speed_mps: float = ExpertConfig.stop_speed_mps,
) -> tuple[list[Frame], dict[str, list[int]]]:
    """Simulate until each vehicle in ``needed`` has its samples, then FUTURE_S more and until each
    has driven ``ahead_m`` past its last sample (or left the network).

    Returns every step's Frame (every vehicle, or with ``around_m`` only the
    needed vehicles and those within it of one) and, per vehicle, the indices
    of its sampled frames. ``sumo_options``: more of SUMO's options (its own output files).
    ``standing_every`` (DatasetConfig.standing_sample_every): a vehicle slower than ``stop_speed_mps``
    (the expert's standing speed; its labels also ask for no acceleration) is sampled only at every so
    many sampling steps; 1: like a moving one.
    """
    step_s = scenario.step_length_s
    every = steps_per_sample(scenario, sample_period_s)
    longest_s = max(needed.values(), default=0) * sample_period_s
    max_steps = int((4 * longest_s + 600.0) / step_s)
    frames: list[Frame] = []
    sampled: dict[str, list[int]] = {v: [] for v in needed}
    seen: set[str] = set()
    done_at: int | None = None
    driven_m = {v: 0.0 for v in needed}  # path driven since the vehicle's last sample
    last_xy: dict[str, tuple[float, float]] = {}
    focus = None if around_m is None else set(needed)  # without a radius, no vehicle may go missing
    with Simulation(scenario, seed=seed, watch=set(needed), focus=focus, around_m=around_m or 0.0,
                    extra_options=sumo_options) as sim:
        if sim.injection_error is not None and set(needed) & set(scenario.injected):
            raise CrchflError(f"scenario '{scenario.name}': {sim.injection_error}")
        for step in range(max_steps):
            frame = sim.step()
            frames.append(frame)
            present = set(frame.ids.tolist())
            step_no = round(frame.t_s / step_s)
            if step_no % every == 0:
                for vehicle, rows in sampled.items():
                    if vehicle in present and len(rows) < needed[vehicle] and (
                        step_no % (every * standing_every) == 0
                        or frame.speed_mps[frame.index_of(vehicle)] >= stop_speed_mps
                    ):
                        rows.append(len(frames) - 1)
            for vehicle in needed:
                if vehicle in present:
                    seen.add(vehicle)
                elif vehicle in seen and len(sampled[vehicle]) < needed[vehicle]:
                    raise CrchflError(
                        f"vehicle '{vehicle}' left the network after {len(sampled[vehicle])} of its "
                        f"{needed[vehicle]} samples; ask for fewer samples or give it a longer route"
                    )
            if done_at is None and all(len(sampled[v]) >= n for v, n in needed.items()):
                done_at = step
            for vehicle in needed:
                if len(sampled[vehicle]) >= needed[vehicle] and vehicle in present:
                    row = frame.index_of(vehicle)
                    xy = (float(frame.x_m[row]), float(frame.y_m[row]))
                    if vehicle in last_xy:
                        driven_m[vehicle] += math.hypot(xy[0] - last_xy[vehicle][0], xy[1] - last_xy[vehicle][1])
                    last_xy[vehicle] = xy
            if step % 40 == 0:
                report(progress, "simulate", sum(len(r) for r in sampled.values()), sum(needed.values()))
            if (
                done_at is not None
                and (step - done_at) * step_s >= FUTURE_S
                and all(driven_m[v] >= ahead_m or v not in present for v in needed)
            ):
                break
        else:
            short = {v: len(r) for v, r in sampled.items() if len(r) < needed[v]}
            if short:
                raise CrchflError(
                    f"after {max_steps * step_s:.0f} simulated seconds these vehicles still lack samples "
                    f"(have: {short}); check that they depart in scenario '{scenario.name}'"
                )
            # All sampled, but one stood to the end: where its path is unknown its command stays FOLLOW.
            log.warning("stopped at %.0f s before every vehicle had driven %.0f m past its last sample",
                        max_steps * step_s, ahead_m)
        stats = sim.stats()
    if stats.teleports or stats.collisions:
        log.warning("run had %d teleports and %d collisions", stats.teleports, stats.collisions)
    return frames, sampled
