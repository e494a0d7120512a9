"""Two drivers on the same episodes compared pair by pair (driving.drive_bench_compare)."""

from __future__ import annotations

import pytest

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.intervals import wilson_interval
from crchfl_sumo.driving.drive_bench_compare import ALL, compare_episodes, compare_models, comparison_table


def _episode(task: str, index: int, success: bool, score: float, draw: int = 0) -> dict:
    return {"town": "town01", "task": task, "index": index, "edges": [f"e{index}"], "success": success,
            "driving_score": score, "draw": draw}


def test_pairs_by_episode_with_intervals_per_cell_and_over_all():
    a = [_episode("straight", i, ok, s) for i, (ok, s) in enumerate([(True, 1.0), (True, 0.7), (False, 0.2), (True, 1.0)])]
    b = [_episode("straight", i, ok, s) for i, (ok, s) in enumerate([(True, 1.0), (False, 0.3), (False, 0.2), (False, 0.4)])]
    a.append(_episode("one_turn", 0, True, 0.8))
    b.append(_episode("one_turn", 0, True, 0.8))
    # B's records in another order: pairing is by episode, not by position
    result = compare_episodes(a, list(reversed(b)))
    straight = result["town01/straight"]
    assert straight["a"]["success_rate"] == 0.75 and straight["b"]["success_rate"] == 0.25
    assert straight["a"]["success_ci95"] == list(wilson_interval(3, 4))
    assert straight["a"]["driving_score"] == pytest.approx(0.725)
    # success differences 0, -1, 0, -1: mean -0.5; scores 0, -0.4, 0, -0.6: mean -0.25
    assert straight["success_difference"]["mean"] == -0.5 and straight["success_difference"]["n"] == 4
    assert straight["driving_score_difference"]["mean"] == pytest.approx(-0.25)
    assert result[ALL]["a"]["episodes"] == 5 and result[ALL]["success_difference"]["mean"] == pytest.approx(-0.4)
    table = comparison_table(result, "before", "after")
    assert "| town01/straight | 4 | 75 [" in table and "not distinguishable" in table
    assert table.count("\n") == 2 + 3  # header, rule, two cells and all


def test_episodes_of_other_draws_or_routes_are_refused():
    a = [_episode("straight", 0, True, 1.0)]
    with pytest.raises(CrchflError, match="same --seed"):
        compare_episodes(a, [_episode("straight", 0, True, 1.0, draw=1)])
    with pytest.raises(CrchflError, match="different episodes"):
        compare_episodes(a, [{**a[0], "edges": ["other"]}])


def _run(outcomes, draw=0):
    """One model's episodes: (success, strict, score, red lights, metres) per straight episode."""
    return [{**_episode("straight", i, ok, score, draw), "strict_success": strict, "red_light_violations": red,
             "distance_m": metres} for i, (ok, strict, score, red, metres) in enumerate(outcomes)]


def test_recipes_compared_model_by_model_paired_by_seed():
    a = [_run([(True, False, 0.8, 1, 500.0), (True, True, 1.0, 0, 500.0)]),   # success 1, strict 0.5, 1 red/km
         _run([(False, False, 0.2, 0, 250.0), (True, True, 1.0, 0, 250.0)])]  # 0.5, 0.5, 0 red/km
    b = [_run([(True, True, 1.0, 0, 500.0), (True, True, 1.0, 0, 500.0)]),    # 1, 1, 0 red/km
         _run([(True, True, 0.9, 0, 250.0), (True, False, 0.6, 1, 250.0)])]   # 1, 0.5, 2 red/km
    result = compare_models(a, b)
    assert result["a"]["episodes"] == 4 and result["a"]["success_rate"] == 0.75
    assert result["a"]["success_ci95"] == list(wilson_interval(3, 4))
    assert [m["red_lights_per_km"] for m in result["a"]["models"]] == [1.0, 0.0]
    assert [m["driving_score"] for m in result["b"]["models"]] == pytest.approx([1.0, 0.75])
    d = result["differences"]
    assert d["success"]["mean"] == pytest.approx(0.25) and d["success"]["n"] == 2  # (0 + 0.5) / 2
    assert d["strict_success"]["mean"] == pytest.approx(0.25)  # (0.5 + 0) / 2
    assert d["red_lights_per_km"]["mean"] == pytest.approx(0.5)  # (-1 + 2) / 2
    # over seeds, episode by episode: 4 pairs, not 2 (both seeds drove episodes 0 and 1 of the same draw)
    pooled = result["by_episode"][ALL]
    assert pooled["success_difference"]["n"] == 4
    assert pooled["success_difference"]["mean"] == pytest.approx(0.25)  # (0 + 0 + 1 + 0) / 4
    assert pooled["driving_score_difference"]["mean"] == pytest.approx(0.125)  # (0.2 + 0 + 0.7 - 0.4) / 4
    with pytest.raises(CrchflError, match="the same seeds"):
        compare_models(a, b[:1])
    with pytest.raises(CrchflError, match="same --seed"):
        compare_models(a, [b[0], _run([(True, True, 1.0, 0, 1.0)] * 2, draw=1)])
