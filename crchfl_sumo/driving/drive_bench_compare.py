"""Two drivers on the same benchmark episodes, compared pair by pair: success and driving score per
cell with Wilson and t intervals, and the paired difference (B - A) with its interval and p-value.
Two recipes, each trained with several seeds, compared model by model (``compare_models``): each
model's success, strict success, driving score and red lights per km, paired by seed.

Pure: it reads the episode records drive-bench writes (episodes.json) and returns numbers and a
table. tools/bench_closed_loop.py drives both checkpoints and prints the comparison; the closed-loop
guard (tests/driving/test_closed_loop_guard.py) holds a driver to its success on a fixed suite.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.intervals import distinguishable, paired_difference, t_interval, wilson_interval

ALL = "all"  # the row that pools every cell


# A record's tag naming the seed its model was trained with (compare_models): the k-th model of each
# recipe drives the same episodes, so pooled over seeds an episode is one seed's, not one index's.
SEED_SLOT = "seed_slot"


def episode_key(record: Mapping[str, Any]) -> tuple:
    """What makes two records the same episode: its model's seed slot, its draw, town, task, index and route."""
    return (record.get(SEED_SLOT, 0), record.get("draw", 0), record["town"], record["task"], record["index"],
            tuple(record["edges"]))


def success_stats(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Episodes, success rate with its Wilson 95 % interval, mean driving score with its t interval."""
    successes = sum(bool(r["success"]) for r in records)
    scores = [float(r["driving_score"]) for r in records]
    return {
        "episodes": len(records),
        "success_rate": successes / len(records) if records else None,
        "success_ci95": list(wilson_interval(successes, len(records))),
        "driving_score": float(np.mean(scores)) if scores else None,
        "driving_score_ci95": (lambda ci: list(ci) if ci else None)(t_interval(scores)),
    }


def paired_episodes(a: Sequence[Mapping[str, Any]], b: Sequence[Mapping[str, Any]]) -> list[tuple]:
    """Each record of ``a`` with the record of ``b`` of the same episode; a CrchflError if they drove others."""
    by_key_b = {episode_key(r): r for r in b}
    if len(by_key_b) != len(b) or {episode_key(r) for r in a} != set(by_key_b):
        raise CrchflError(
            "the two benchmarks drove different episodes; run both with the same --seed, --episodes, --towns and --tasks"
        )
    return [(r, by_key_b[episode_key(r)]) for r in a]


def compare_episodes(a: Sequence[Mapping[str, Any]], b: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per (town, task) cell and over all (key ALL): A's and B's success_stats and B - A paired by episode.

    ``a`` and ``b`` are episode records (drive-bench's episodes.json, optionally with a ``draw``
    naming the benchmark seed) of the same episodes; a record of one without its pair in the other
    is a CrchflError (compare the same --seed, --episodes, towns and tasks).
    """
    pairs = paired_episodes(a, b)
    cells: dict[str, list] = {}
    for ra, rb in pairs:
        cells.setdefault(f"{ra['town']}/{ra['task']}", []).append((ra, rb))
    cells[ALL] = pairs
    out = {}
    for name, cell in cells.items():
        side_a, side_b = [p[0] for p in cell], [p[1] for p in cell]
        out[name] = {
            "a": success_stats(side_a),
            "b": success_stats(side_b),
            "success_difference": paired_difference([float(r["success"]) for r in side_a],
                                                    [float(r["success"]) for r in side_b]),
            "driving_score_difference": paired_difference([float(r["driving_score"]) for r in side_a],
                                                          [float(r["driving_score"]) for r in side_b]),
        }
    return out


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f}"


def _interval(ci: Sequence[float] | None, scale: float = 100.0, digits: int = 0) -> str:
    return "" if ci is None else f" [{scale * ci[0]:.{digits}f}, {scale * ci[1]:.{digits}f}]"


def _difference(d: Mapping[str, Any], scale: float, digits: int) -> str:
    if d["mean"] is None:
        return "-"
    words = "" if distinguishable(d["ci95"]) else " (not distinguishable)"
    return f"{scale * d['mean']:+.{digits}f}{_interval(d['ci95'], scale, digits)}{words}"


def comparison_table(comparison: Mapping[str, Mapping[str, Any]], label_a: str = "A", label_b: str = "B") -> str:
    """The comparison as a markdown table: success in % and driving score (0-100), each with its 95 % interval."""
    lines = [
        f"| cell | episodes | success {label_a} | success {label_b} | success {label_b} - {label_a} (points) "
        f"| score {label_a} | score {label_b} | score {label_b} - {label_a} |",
        "| --- | ---: | --- | --- | --- | --- | --- | --- |",
    ]
    for name, c in comparison.items():
        a, b = c["a"], c["b"]
        lines.append(
            f"| {name} | {a['episodes']} | {_pct(a['success_rate'])}{_interval(a['success_ci95'])} "
            f"| {_pct(b['success_rate'])}{_interval(b['success_ci95'])} | {_difference(c['success_difference'], 100, 0)} "
            f"| {_pct(a['driving_score'])}{_interval(a['driving_score_ci95'])} "
            f"| {_pct(b['driving_score'])}{_interval(b['driving_score_ci95'])} "
            f"| {_difference(c['driving_score_difference'], 100, 1)} |"
        )
    return "\n".join(lines) + "\n"


# What a model's benchmark is summed up by when recipes are compared seed by seed (compare_models).
MODEL_FIGURES = ("success", "strict_success", "driving_score", "red_lights_per_km")


def model_figures(records: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """One model's episodes -> its success and strict success rates, mean driving score (0-1) and red
    lights per km driven."""
    if not records:
        raise CrchflError("a model with no benchmark episode cannot be compared")
    km = sum(float(r["distance_m"]) for r in records) / 1000.0
    return {
        "success": float(np.mean([bool(r["success"]) for r in records])),
        "strict_success": float(np.mean([bool(r["strict_success"]) for r in records])),
        "driving_score": float(np.mean([float(r["driving_score"]) for r in records])),
        "red_lights_per_km": sum(int(r["red_light_violations"]) for r in records) / km if km > 0 else 0.0,
    }


def compare_models(a: Sequence[Sequence[Mapping[str, Any]]], b: Sequence[Sequence[Mapping[str, Any]]]) -> dict:
    """Recipe A's and B's models (one episode list per model; the k-th of each trained with the same seed)
    on the same episodes: per recipe the pooled success with its Wilson interval and each model's
    MODEL_FIGURES, per figure B - A paired by seed (core.intervals.paired_difference), and under
    ``by_episode`` the episodes of all seeds paired one by one (compare_episodes, each record tagged
    with its SEED_SLOT so that seed 0's and seed 1's episode 3 stay two pairs)."""
    if len(a) != len(b) or not a:
        raise CrchflError(f"compare the same seeds: {len(a)} models of A against {len(b)} of B")
    # paired episode by episode first: compare_episodes refuses a model that drove other episodes
    tagged_a, tagged_b = ([{**r, SEED_SLOT: k} for k, m in enumerate(models) for r in m] for models in (a, b))
    by_episode = compare_episodes(tagged_a, tagged_b)
    sides = {}
    for name, models in (("a", a), ("b", b)):
        pooled = [r for m in models for r in m]
        successes = sum(bool(r["success"]) for r in pooled)
        sides[name] = {
            "episodes": len(pooled),
            "success_rate": successes / len(pooled),
            "success_ci95": list(wilson_interval(successes, len(pooled))),
            "models": [model_figures(m) for m in models],
        }
    differences = {
        figure: paired_difference([m[figure] for m in sides["a"]["models"]], [m[figure] for m in sides["b"]["models"]])
        for figure in MODEL_FIGURES
    }
    return {**sides, "differences": differences, "by_episode": by_episode}
