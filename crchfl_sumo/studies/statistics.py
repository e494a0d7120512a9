"""Pure statistics over a reproduction's results: mean and spread over seeds, learning curves against rounds and bytes, gains between schemes, running times, the summary.json dictionary.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from crchfl_sumo.accounting.ledger import GIB, gb_label
from crchfl_sumo.accounting.schedules import STAGES
from crchfl_sumo.core.intervals import paired_difference, t_interval
from crchfl_sumo.driving.drive_bench_compare import episode_key
from crchfl_sumo.driving.drive_bench_score import pool_task_summaries

# Section IV-B of the paper: CRCHFL's Accuracy over HFL's and SFL's under 20 GB.
PAPER_GAINS_PERCENT = {"hfl": 10.33, "sfl": 12.41}


# What a run's summary says of how its best model learned, beside accuracy and loss.
LEARNING_KEYS = ("balanced_accuracy", "final_balanced_accuracy", "best_steer_error", "best_throttle_error",
                 "best_brake_error")


def mean_std(values: Iterable[float | None]) -> dict[str, Any]:
    """Mean, sample standard deviation (ddof = 1) and the mean's 95 % t interval of the values that are not None.

    ``std`` and ``ci95`` are None with fewer than two values, ``mean`` None with none.
    """
    kept = [float(v) for v in values if v is not None]
    n = len(kept)
    mean = float(np.mean(kept)) if n else None
    std = float(np.std(kept, ddof=1)) if n >= 2 else None
    ci = t_interval(kept)
    return {"mean": mean, "std": std, "n": n, "ci95": list(ci) if ci else None}


def paired_by_seed(theirs: Mapping[Any, Any], mine: Mapping[Any, Any]) -> dict[str, Any]:
    """mine - theirs over the seeds both have a number for (the same seed: the same data, start and traffic):
    core.intervals.paired_difference's {mean, ci95, p, n}."""
    seeds = [s for s in mine if s in theirs and _number(mine[s]) and _number(theirs[s])]
    return paired_difference([theirs[s] for s in seeds], [mine[s] for s in seeds])


def seed_mean(values: Iterable[Any]) -> Any:
    """A figure over seeds: the mean of the numbers (one seed's as it is, so a count stays whole); a column of
    text (a stop reason) gives the first seed's."""
    values = list(values)
    numbers = [v for v in values if _number(v)]
    if len(numbers) == 1:
        return numbers[0]
    if numbers:
        return sum(numbers) / len(numbers)
    return values[0] if values else None


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# The schemes CRCHFL is compared with, seed by seed, and the figures compared (summary.json "differences").
DIFFERENCE_KEYS = ("balanced_accuracy", "best_accuracy")


def differences(schemes: Mapping[str, Mapping[str, Any]], ours: str = "crchfl") -> dict[str, Any]:
    """``differences["crchfl-hfl"][KEY]`` = {mean, ci95, p, n}: ours - theirs, paired by seed
    (the same seed: the same data, start and traffic), with the paired-t 95 % interval and p-value."""
    out: dict[str, Any] = {}
    if ours not in schemes:
        return out
    for other, stats in schemes.items():
        if other == ours:
            continue
        pair: dict[str, Any] = {}
        for key in DIFFERENCE_KEYS:
            mine = dict(zip(schemes[ours]["seeds"], schemes[ours][key]["values"]))
            pair[key] = paired_by_seed(dict(zip(stats["seeds"], stats[key]["values"])), mine)
        out[f"{ours}-{other}"] = pair
    return out


# The closed-loop figures compared model by model: each over all the benchmark episodes of a seed's model, or per
# episode (summary.json "differences" and its "by_episode").
BENCH_DIFFERENCE_KEYS = ("success_rate", "driving_score")
EPISODE_FIELDS = {"success_rate": "success", "driving_score": "driving_score"}  # key -> an episode record's field


def bench_differences(bench: Mapping[str, Mapping[str, Any]], ours: str = "crchfl") -> dict[str, Any]:
    """``PAIR[KEY]`` = ours - other over each seed's benchmark (success rate and driving score over all its
    episodes), paired by seed; ``PAIR["by_episode"][KEY]`` = the same paired by episode (the same seed, town,
    task, index and route; every seed's model drove the same episodes). For every other label whose every
    seed's model drove (``bench_all_seeds``), PAIR ``ours-other``; none without ours."""
    mine = bench.get(ours) or {}
    if "seeds" not in mine:
        return {}
    my_seeds = {key: {s: bench_overall(r, key) for s, r in mine["seeds"].items()} for key in BENCH_DIFFERENCE_KEYS}
    my_episodes = _episodes_by_key(mine.get("episodes") or {})
    out: dict[str, Any] = {}
    for other, found in bench.items():
        if other == ours or "seeds" not in found:
            continue
        pair = {key: paired_by_seed({s: bench_overall(r, key) for s, r in found["seeds"].items()}, my_seeds[key])
                for key in BENCH_DIFFERENCE_KEYS}
        their_episodes = _episodes_by_key(found.get("episodes") or {})
        shared = [episode for episode in my_episodes if episode in their_episodes]
        if shared:
            pair["by_episode"] = {
                key: paired_difference([float(their_episodes[e][field]) for e in shared],
                                       [float(my_episodes[e][field]) for e in shared])
                for key, field in EPISODE_FIELDS.items()
            }
        out[f"{ours}-{other}"] = pair
    return out


def _episodes_by_key(episodes: Mapping[Any, Sequence[Mapping[str, Any]]]) -> dict[tuple, Mapping[str, Any]]:
    """drive_bench_compare.episode_key (the seed as the draw) -> the episode's record."""
    return {episode_key({**r, "draw": seed}): r for seed, records in episodes.items() for r in records}


def relative_gain_percent(ours: float | None, theirs: float | None) -> float | None:
    """How much higher ``ours`` is than ``theirs``, in percent of ``theirs``: 100 (a - b) / b."""
    if ours is None or theirs is None or theirs == 0:
        return None
    return 100.0 * (ours - theirs) / theirs


def cloud_lines(metrics: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The evaluated global models: the pretrained one (stage I, round 0) and each cloud aggregation (III)."""
    return [m for m in metrics if m.get("stage") in ("I", "III") and m.get("accuracy") is not None]


def curve_by_round(runs: Sequence[Sequence[Mapping[str, Any]]], key: str) -> dict[str, np.ndarray]:
    """Mean and spread over runs of ``key`` at each cloud round (rounds some runs lack use the others)."""
    by_round: dict[int, list[float]] = {}
    for lines in runs:
        for m in cloud_lines(lines):
            if m.get(key) is not None:
                by_round.setdefault(int(m["cloud_round"]), []).append(float(m[key]))
    rounds = sorted(by_round)
    stats = [mean_std(by_round[r]) for r in rounds]
    return _curve(np.array(rounds, float), stats)


def curve_by_bytes(runs: Sequence[Sequence[Mapping[str, Any]]], key: str) -> dict[str, np.ndarray]:
    """``key`` against consumed bytes: at each cloud round, the mean over runs of both the bytes
    consumed by then and ``key`` (with the paper's accounting every seed consumes the same bytes)."""
    by_round: dict[int, list[tuple[float, float]]] = {}
    for lines in runs:
        for m in cloud_lines(lines):
            if m.get(key) is not None:
                by_round.setdefault(int(m["cloud_round"]), []).append((float(m["consumed_bytes"]), float(m[key])))
    rounds = sorted(by_round)
    x = np.array([np.mean([b for b, _ in by_round[r]]) for r in rounds], float)
    return _curve(x, [mean_std(v for _, v in by_round[r]) for r in rounds])


def _curve(x: np.ndarray, stats: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    mean = np.array([s["mean"] for s in stats], float)
    std = np.array([np.nan if s["std"] is None else s["std"] for s in stats], float)
    return {"x": x, "mean": mean, "std": std, "n": np.array([s["n"] for s in stats], int)}


def scheme_stats(runs: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """Per-seed values and their mean/std of one scheme's (or ablation setting's) runs."""
    summaries = [r["summary"] for r in runs.values()]
    stats: dict[str, Any] = {"seeds": list(runs)}
    for key in ("cloud_rounds", "edge_aggregations", "best_accuracy", "final_accuracy", "best_loss", "final_loss",
                "consumed_bytes", "sim_time_s", *LEARNING_KEYS):
        values = [s.get(key) for s in summaries]
        stats[key] = {**mean_std(values), "values": values}
    stats.update(class_stats(summaries))
    stats["budget_bytes"] = summaries[0].get("budget_bytes")
    stats["stop_reason"] = [s.get("stop_reason") for s in summaries]
    stats["hyper"] = summaries[0].get("hyper")
    by_stage = [s.get("bytes_by_stage") or {} for s in summaries]
    stats["bytes_by_stage"] = {stage: mean_std(b.get(stage) for b in by_stage)["mean"] for stage in STAGES}
    return stats


def centralized_stats(runs: Mapping[int, Mapping[str, Any]]) -> dict[str, Any] | None:
    if not runs:
        return None
    summaries = [r["summary"] for r in runs.values()]
    stats: dict[str, Any] = {"seeds": list(runs), "epochs": summaries[0].get("epochs")}
    for key in ("best_accuracy", "final_accuracy", "best_loss", "final_loss", *LEARNING_KEYS):
        values = [s.get(key) for s in summaries]
        stats[key] = {**mean_std(values), "values": values}
    stats.update(class_stats(summaries))
    return stats


def class_stats(summaries: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per steer class: the best models' recall (mean over the seeds that have the class) and their
    confusion matrices summed over seeds; None where the runs carry none."""
    recalls = [s["best_recall"] for s in summaries if s.get("best_recall")]
    confusions = [s["best_confusion"] for s in summaries if s.get("best_confusion")]
    recall = None
    if recalls:
        recall = [mean_std(r[c] for r in recalls)["mean"] for c in range(len(recalls[0]))]
    confusion = np.sum(np.asarray(confusions, dtype=np.int64), axis=0).tolist() if confusions else None
    return {"recall": recall, "confusion": confusion}


def baselines(results: Mapping[str, Any]) -> dict[str, Any]:
    """The always-straight prediction on the test set, as the runs measured it (the same data for every run)."""
    for runs in (*results["schemes"].values(), *results["ablation"].values(), results["centralized"]):
        for run in runs.values():
            found = (run["summary"].get("baselines") or {}).get("always_straight")
            if found:
                return {"always_straight": found}
    return {}


def gains(schemes: Mapping[str, Mapping[str, Any]], ours: str = "crchfl") -> dict[str, Any]:
    """CRCHFL's accuracy over each other scheme: relative (% of theirs) and in points, for the
    best and final accuracy and the balanced accuracy (means over seeds), next to the paper's figures.

    No relative gain over a scheme one of whose seeds scored 0: a percentage of a mean pulled down by a
    broken run says nothing (the points still show the difference)."""
    out: dict[str, Any] = {"paper_percent": dict(PAPER_GAINS_PERCENT)}
    if ours not in schemes:
        return out
    for key in ("best_accuracy", "final_accuracy", "balanced_accuracy"):
        mine = schemes[ours][key]["mean"]
        out[key] = {}
        for other, stats in schemes.items():
            if other == ours:
                continue
            theirs = stats[key]["mean"]
            broken = any(v == 0 for v in stats[key]["values"])
            out[key][other] = {
                "relative_percent": None if broken else relative_gain_percent(mine, theirs),
                "points": None if mine is None or theirs is None else 100.0 * (mine - theirs),
            }
    return out


def timing_groups(timings: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """Wall and CPU seconds per kind of part (data, centralized, runs, ablation, drives) and in total.

    The total also has ``elapsed_s``: the time during which at least one part ran (parts run side
    by side with ``--jobs``; a part recorded without its start time counts its whole wall time).
    """
    groups: dict[str, dict[str, float]] = {}
    for key, spent in list(timings.items()):
        for group in (key.split("/", 1)[0], "total"):
            sums = groups.setdefault(group, {"wall_s": 0.0, "cpu_s": 0.0})
            for unit in ("wall_s", "cpu_s"):
                sums[unit] += float(spent.get(unit, 0.0))
    total = groups.pop("total", {"wall_s": 0.0, "cpu_s": 0.0})
    total["elapsed_s"] = elapsed_s(timings.values())
    return {**groups, "total": total}


def elapsed_s(spans: Iterable[Mapping[str, float]]) -> float:
    """Length of the union of the intervals [start_unix, start_unix + wall_s]; a span without a start adds its wall."""
    spans = list(spans)
    intervals = sorted((s["start_unix"], s["start_unix"] + s["wall_s"]) for s in spans if "start_unix" in s)
    covered = sum(float(s.get("wall_s", 0.0)) for s in spans if "start_unix" not in s)
    end = -math.inf
    for start, stop in intervals:
        covered += max(0.0, stop - max(start, end))
        end = max(end, stop)
    return covered


# The benchmark's per-episode means whose spread over seeds the summary gives.
BENCH_SPREAD_KEYS = ("success_rate", "route_completion", "driving_score")


def bench_stats(bench: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """summary.json's ``drive_bench`` (label -> results[TOWN][TASK]) and ``drive_bench_spread``.

    A label benchmarked with one model gives its results as they are. A label benchmarked with every
    seed's model ({"seeds": {seed: summary}}) gives the results over all its episodes together in
    ``drive_bench``, and in ``drive_bench_spread[label][TOWN][TASK][KEY]`` the mean, sample std and
    per-seed values of each seed's success rate, route completion and driving score.
    """
    pooled: dict[str, Any] = {}
    spread: dict[str, Any] = {}
    for label, found in bench.items():
        if "seeds" not in found:
            pooled[label] = found["results"]
            continue
        per_seed = [summary["results"] for summary in found["seeds"].values()]
        pooled[label], spread[label] = {}, {"seeds": list(found["seeds"])}
        for town, tasks in per_seed[0].items():
            pooled[label][town], spread[label][town] = {}, {}
            for task in tasks:
                runs = [results[town][task] for results in per_seed]
                pooled[label][town][task] = pool_task_summaries(runs)
                spread[label][town][task] = {
                    key: {**mean_std(r[key] for r in runs), "values": [r[key] for r in runs]} for key in BENCH_SPREAD_KEYS
                }
    return {"drive_bench": pooled, "drive_bench_spread": spread}


def bench_overall(summary: Mapping[str, Any], key: str) -> float | None:
    """A drive-bench summary's ``key`` (driving_score, success_rate) over all its episodes (its cells weighted by
    their episodes); None without episodes."""
    cells = [cell for tasks in summary["results"].values() for cell in tasks.values() if cell.get("episodes")]
    episodes = sum(cell["episodes"] for cell in cells)
    return sum(cell[key] * cell["episodes"] for cell in cells) / episodes if episodes else None


def first_bytes_gb(metrics: Sequence[Mapping[str, Any]], target: float) -> float | None:
    """The consumed GB of the first evaluation that reached balanced accuracy ``target`` (None: none did)."""
    for line in metrics:
        value = line.get("balanced_accuracy")
        if value is not None and value >= target:
            return line["consumed_bytes"] / GIB
    return None


def budget_curve(results: Mapping[str, Any]) -> dict[str, Any]:
    """summary.json's experiment E: ``budget_curve[SCHEME]["B"]`` = {balanced_accuracy, driving_score}, each
    {mean, std, ci95, n, values, seeds} over seeds; ``budget_differences["crchfl-OTHER"]["B"]`` = CRCHFL minus
    OTHER, paired by seed, for both; ``bytes_to_accuracy[SCHEME]["T"]`` = the mean GB over seeds that the
    runs of experiment B consumed until their first evaluation at balanced accuracy T (None unless every seed
    reached it), with ``bytes_to_accuracy_seeds`` per seed. Budgets below a scheme's run budget come from
    the curve's own runs where it has them (CRCHFL) or from the run's budget marks (HFL, SFL)."""
    config = (results["reproduce"] or {}).get("config") or {}
    budgets = [float(b) for b in config.get("budgets_gb") or []]
    curve_runs, curve_bench = results["budget_curve"]["runs"], results["budget_curve"]["bench"]
    bench = results["drive_bench"]
    per_seed: dict[str, dict[str, dict[str, dict[int, float | None]]]] = {}
    for scheme, runs in results["schemes"].items() if budgets else ():
        budget = max(run["summary"]["budget_bytes"] for run in runs.values()) / GIB
        per_seed[scheme] = {}
        for gb in budgets:
            label = gb_label(gb)
            if gb >= budget:  # experiment B's runs and benchmarks themselves
                accuracy = {seed: run["summary"].get("balanced_accuracy") for seed, run in runs.items()}
                driven = (bench.get(scheme) or {}).get("seeds") or {}
            else:
                if scheme in curve_runs:
                    found = curve_runs[scheme].get(label) or {}
                    accuracy = {seed: summary.get("balanced_accuracy") for seed, summary in found.items()}
                else:  # a mark with no evaluation within it (None) has no model: no figure
                    marks = {seed: run["summary"].get("budget_marks") or {} for seed, run in runs.items()}
                    accuracy = {seed: (mark[label] or {}).get("balanced_accuracy")
                                for seed, mark in marks.items() if label in mark}
                driven = (curve_bench.get(scheme) or {}).get(label) or {}
            score = {seed: bench_overall(summary, "driving_score") for seed, summary in driven.items()}
            per_seed[scheme][label] = {"balanced_accuracy": accuracy, "driving_score": score}
    curve = {
        scheme: {
            label: {key: {**mean_std(values.values()), "values": list(values.values()), "seeds": list(values)}
                    for key, values in point.items()}
            for label, point in points.items()
        }
        for scheme, points in per_seed.items()
    }
    differences_by_budget: dict[str, Any] = {}
    if "crchfl" in per_seed:
        for other in per_seed:
            if other == "crchfl":
                continue
            pair = differences_by_budget.setdefault(f"crchfl-{other}", {})
            for label, point in per_seed["crchfl"].items():
                pair[label] = {}
                for key, mine in point.items():
                    pair[label][key] = paired_by_seed(per_seed[other].get(label, {}).get(key, {}), mine)
    targets = [float(t) for t in config.get("accuracy_targets") or []]
    to_accuracy, to_accuracy_seeds = {}, {}
    for scheme, runs in results["schemes"].items():
        seeds = {str(t): {seed: first_bytes_gb(run["metrics"], t) for seed, run in runs.items()} for t in targets}
        to_accuracy_seeds[scheme] = seeds
        to_accuracy[scheme] = {
            t: (None if not values or any(v is None for v in values.values()) else float(np.mean(list(values.values()))))
            for t, values in seeds.items()
        }
    return {"budget_curve": curve, "budget_differences": differences_by_budget,
            "bytes_to_accuracy": to_accuracy, "bytes_to_accuracy_seeds": to_accuracy_seeds}


def _merged(first: Mapping[str, Mapping[str, Any]], second: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """PAIR -> the keys of both (a pair in one only keeps its own)."""
    return {pair: {**first.get(pair, {}), **second.get(pair, {})} for pair in {**first, **second}}


def build_summary(results: Mapping[str, Any]) -> dict[str, Any]:
    """summary.json: per scheme cloud_rounds, accuracies and losses (mean, std), bytes, closed loop."""
    schemes = {name: scheme_stats(runs) for name, runs in results["schemes"].items()}
    for name, stats in schemes.items():
        stats["closed_loop"] = {
            route: labels[name] for route, labels in results["drives"].items() if name in labels
        }
    ablation = {}
    for setting, runs in results["ablation"].items():
        stats = scheme_stats(runs)
        budget = stats["budget_bytes"] or 0
        spent = {s: stats["bytes_by_stage"][s] or 0.0 for s in STAGES}
        stats["budget_percent"] = {
            **{s: 100.0 * spent[s] / budget if budget else None for s in STAGES},
            "unused": 100.0 * (budget - sum(spent.values())) / budget if budget else None,
        }
        ablation[setting] = stats
    reproduce = results["reproduce"]
    return {
        "mode": (reproduce.get("config") or {}).get("name"),
        "seeds": reproduce.get("seeds"),
        "schemes": schemes,
        "gains": gains(schemes),
        "differences": _merged(differences(schemes), bench_differences(results["drive_bench"])),
        "baselines": baselines(results),
        "model": next((run["summary"].get("model") for runs in results["schemes"].values() for run in runs.values()),
                      None),
        "centralized": centralized_stats(results["centralized"]),
        "ablation": ablation,
        "closed_loop": results["drives"],
        **bench_stats(results["drive_bench"]),
        **budget_curve(results),
        "running_time_s": timing_groups(results["timings"]),
    }
