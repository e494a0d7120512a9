"""The benchmark's arithmetic: an episode's success, route completion and driving score, and a task's summary.

Success is CoRL2017's (Dosovitskiy et al. 2017): the goal reached within the
time limit, here also with no collision and no off-road driving. The driving
score is the CARLA Leaderboard's (leaderboard.carla.org, "Driving score"):
route completion x infraction penalty, the penalty a product of one
coefficient per infraction; driving off the road counts against route
completion instead (the progress made off the road is not counted).
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from crchfl_sumo.core.intervals import wilson_interval
from crchfl_sumo.driving.drive_bench_behaviour import ABILITIES

# CARLA Leaderboard 1.0 infraction coefficients for the infractions the loop measures.
# The towns have no pedestrians (0.50), static obstacles (0.65) or stop signs (0.80),
# so those never occur; every collision the loop sees is with a vehicle.
PENALTY_COEFFICIENTS = {
    "collisions": 0.60,  # collision with a vehicle
    "red_light_violations": 0.70,  # running a red light
}
# What infractions_per_km counts (CoRL2017 counts its "infractions" per km the same way:
# collisions, driving onto the other lane, onto the sidewalk).
INFRACTIONS = ("collisions", "red_light_violations", "off_road_events", "lane_departures")


def route_completion(progress_m, on_road, start_m: float, goal_m: float) -> float:
    """Share of the route from start to goal covered, counting only new progress made on the road.

    ``progress_m[i]`` and ``on_road[i]`` are the ego's state at step i; the
    progress a step adds to the best so far counts when the ego ends that
    step on the road (the Leaderboard leaves the off-road share out).
    """
    progress = np.maximum.accumulate(np.maximum(np.asarray(progress_m, dtype=np.float64), start_m))
    gained = np.diff(progress) * np.asarray(on_road, dtype=bool)[1:]
    return float(np.clip(gained.sum() / max(goal_m - start_m, 1e-9), 0.0, 1.0))


def penalty(counts: Mapping[str, int]) -> float:
    """The infraction penalty: the product of each infraction's coefficient, once per occurrence."""
    return float(math.prod(c ** int(counts.get(k, 0)) for k, c in PENALTY_COEFFICIENTS.items()))


def succeeded(end_reason: str, collisions: int, off_road_events: int) -> bool:
    """Reached the goal (the drive ended 'completed', so within the time limit) with no collision and no off-road."""
    return end_reason == "completed" and collisions == 0 and off_road_events == 0


def score_episode(metrics: Mapping[str, Any], completion: float, min_speed_penalty: float = 1.0) -> dict[str, Any]:
    """success, strict_success, route_completion, penalty and driving_score of one episode from its drive
    metrics; driving_score_lb2 adds Leaderboard 2.0's minimum-speed factor (drive_bench_behaviour.min_speed_penalty).

    Strict success is success with no red light run either (the Leaderboard's "Perfect" without its
    minimum-speed events, which Bench2Drive leaves out of its success as well).
    """
    p = penalty(metrics)
    success = succeeded(metrics["end_reason"], metrics["collisions"], metrics["off_road_events"])
    return {
        "success": success,
        "strict_success": success and metrics["red_light_violations"] == 0,
        "route_completion": completion,
        "penalty": p,
        "driving_score": completion * p,
        "driving_score_lb2": completion * p * min_speed_penalty,
        # the Leaderboard ends a route on these without a penalty factor
        "agent_blocked": metrics["end_reason"] == "stuck",
        "route_timeout": metrics["end_reason"] == "time limit",
    }


def summarize_task(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One task's results over its episodes (at least one; records carry score_episode's keys and the INFRACTIONS counts).

    success_rate, route_completion and driving_score are means over the
    episodes; infractions_per_km pools them: all infractions / all km driven
    (None when nothing was driven).
    """
    km = sum(r["distance_m"] for r in records) / 1000.0
    counts = {k: int(sum(r[k] for r in records)) for k in INFRACTIONS}
    successes = sum(bool(r["success"]) for r in records)
    strict = sum(bool(r["strict_success"]) for r in records)
    # an episode recorded before an ability existed did not attempt it
    tally = {name: [sum(r["abilities"].get(name, (0, 0))[i] for r in records) for i in (0, 1)] for name in ABILITIES}
    return {
        "episodes": len(records),
        "success_rate": successes / len(records),
        "route_completion": float(np.mean([r["route_completion"] for r in records])),
        "driving_score": float(np.mean([r["driving_score"] for r in records])),
        "infractions_per_km": sum(counts.values()) / km if km > 0 else None,
        "infractions": counts,
        "distance_km": km,
        **_behaviour_keys(len(records), successes, strict, km, counts["red_light_violations"],
                          _mean_of_some(records, "efficiency"), _mean_of_some(records, "smoothness"),
                          float(np.mean([r["driving_score_lb2"] for r in records])),
                          sum(bool(r["agent_blocked"]) for r in records),
                          sum(bool(r["route_timeout"]) for r in records), tally),
    }


def _mean_of_some(records: Sequence[Mapping[str, Any]], key: str) -> tuple[float | None, int]:
    """(mean of the records' values that are not None, how many there were)."""
    values = [r[key] for r in records if r.get(key) is not None]
    return (float(np.mean(values)) if values else None, len(values))


def _behaviour_keys(episodes: int, successes: int, strict: int, km: float, red_lights: int,
                    efficiency: tuple[float | None, int], smoothness: tuple[float | None, int],
                    driving_score_lb2: float, blocked: int, timeouts: int, tally: Mapping[str, list[int]]) -> dict:
    """A cell's Leaderboard 2.0 and Bench2Drive keys, with Wilson 95 % intervals on its rates."""
    return {
        "success_ci95": list(wilson_interval(successes, episodes)),
        "strict_success_rate": strict / episodes,
        "strict_success_ci95": list(wilson_interval(strict, episodes)),
        "red_lights_per_km": red_lights / km if km > 0 else None,
        "efficiency": efficiency[0],
        "efficiency_episodes": efficiency[1],
        "smoothness": smoothness[0],
        "smoothness_episodes": smoothness[1],
        "driving_score_lb2": driving_score_lb2,
        "agent_blocked": blocked,
        "route_timeouts": timeouts,
        "abilities": {
            name: {"attempts": attempts, "successes": ok, "success_rate": ok / attempts if attempts else None,
                   "success_ci95": list(wilson_interval(ok, attempts))}
            for name, (attempts, ok) in tally.items()
        },
    }


def pool_task_summaries(summaries: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One task's results over the episodes of several runs (several models of one scheme, say), as
    summarize_task would give them over all those episodes together."""
    episodes = [int(s["episodes"]) for s in summaries]
    total = sum(episodes)

    def mean(key: str) -> float:
        return float(sum(n * s[key] for n, s in zip(episodes, summaries)) / total)

    km = float(sum(s["distance_km"] for s in summaries))
    counts = {k: int(sum(s["infractions"][k] for s in summaries)) for k in INFRACTIONS}
    pooled = {
        "episodes": total,
        "success_rate": mean("success_rate"),
        "route_completion": mean("route_completion"),
        "driving_score": mean("driving_score"),
        "infractions_per_km": sum(counts.values()) / km if km > 0 else None,
        "infractions": counts,
        "distance_km": km,
    }
    if not all("strict_success_rate" in s for s in summaries):  # summaries written before these keys
        return pooled

    def some(key: str) -> tuple[float | None, int]:
        n = sum(s[f"{key}_episodes"] for s in summaries)
        kept = [(s[key], s[f"{key}_episodes"]) for s in summaries if s[key] is not None]
        return (sum(v * k for v, k in kept) / n if n else None, n)

    tally = {name: [sum(s["abilities"].get(name, {}).get(k, 0) for s in summaries) for k in ("attempts", "successes")]
             for name in ABILITIES}
    return pooled | _behaviour_keys(
        total, round(pooled["success_rate"] * total), round(mean("strict_success_rate") * total), km,
        counts["red_light_violations"], some("efficiency"), some("smoothness"), mean("driving_score_lb2"),
        sum(s["agent_blocked"] for s in summaries), sum(s["route_timeouts"] for s in summaries), tally,
    )
