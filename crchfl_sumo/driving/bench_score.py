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


def score_episode(metrics: Mapping[str, Any], completion: float) -> dict[str, Any]:
    """success, route_completion, penalty and driving_score of one episode from its drive metrics."""
    p = penalty(metrics)
    return {
        "success": succeeded(metrics["end_reason"], metrics["collisions"], metrics["off_road_events"]),
        "route_completion": completion,
        "penalty": p,
        "driving_score": completion * p,
    }


def summarize_task(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One task's results over its episodes (at least one; records carry score_episode's keys and the INFRACTIONS counts).

    success_rate, route_completion and driving_score are means over the
    episodes; infractions_per_km pools them: all infractions / all km driven
    (None when nothing was driven).
    """
    km = sum(r["distance_m"] for r in records) / 1000.0
    counts = {k: int(sum(r[k] for r in records)) for k in INFRACTIONS}
    return {
        "episodes": len(records),
        "success_rate": float(np.mean([bool(r["success"]) for r in records])),
        "route_completion": float(np.mean([r["route_completion"] for r in records])),
        "driving_score": float(np.mean([r["driving_score"] for r in records])),
        "infractions_per_km": sum(counts.values()) / km if km > 0 else None,
        "infractions": counts,
        "distance_km": km,
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
    return {
        "episodes": total,
        "success_rate": mean("success_rate"),
        "route_completion": mean("route_completion"),
        "driving_score": mean("driving_score"),
        "infractions_per_km": sum(counts.values()) / km if km > 0 else None,
        "infractions": counts,
        "distance_km": km,
    }
