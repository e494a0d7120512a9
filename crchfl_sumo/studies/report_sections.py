"""report.md, one function a section: what ran, the tables, every figure, the settings, the versions
and the times, from a summary (studies/statistics.py) and the results folder it was built from."""

from __future__ import annotations

import json
import math
from typing import Any, Iterable, Mapping, Sequence

from crchfl_sumo.accounting.ledger import GIB
from crchfl_sumo.accounting.schedules import STAGES
from crchfl_sumo.core.intervals import distinguishable
from crchfl_sumo.data.labels import STEER_CLASS_VALUES
from crchfl_sumo.federation.settings import PLANNED_BY_THE_OPTIMIZER
from crchfl_sumo.studies.report_figures import NAMES
from crchfl_sumo.studies.statistics import PAPER_GAINS_PERCENT

HYPER = PLANNED_BY_THE_OPTIMIZER  # the four hyper-parameters, in the report's column order
DRIVE_COLUMNS = (
    "completion", "end_reason", "duration_s", "mean_speed_mps", "collisions", "lane_departures",
    "off_road_s", "red_light_violations", "max_abs_offset_m",
)


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.{digits}f}"
    return str(value)


def _seeds(stats: Mapping[str, Any]) -> str:
    """The seed count; runs still going (no stop_reason yet: a reproduction in progress) are named."""
    unfinished = sum(reason is None for reason in stats["stop_reason"])
    return f"{len(stats['seeds'])}" + (f" ({unfinished} unfinished)" if unfinished else "")


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{value:+.2f} %"


def _pm(stats: Mapping[str, Any], digits: int = 4, scale: float = 1.0) -> str:
    """The mean with its 95 % interval over seeds (summaries written before intervals: ± the std)."""
    if stats["mean"] is None:
        return "-"
    text = f"{stats['mean'] * scale:.{digits}f}"
    if stats.get("ci95"):
        lo, hi = stats["ci95"]
        return text + f" [{lo * scale:.{digits}f}, {hi * scale:.{digits}f}]"
    return text + (f" ± {stats['std'] * scale:.{digits}f}" if stats["std"] is not None else "")


def _table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def report_markdown(summary: Mapping[str, Any], results: Mapping[str, Any], figures: Mapping[str, str]) -> str:
    """report.md: what ran, the tables, every figure, the settings, the versions and the times."""
    lines = _header(summary, results)
    lines += _experiment_b(summary, figures)
    lines += _experiment_e(summary, figures)
    lines += _experiment_d(summary, figures)
    lines += _closed_loop(summary, figures)
    lines += _drive_bench(summary)
    lines += _settings(summary, results)
    lines += _environment(summary, results, figures)
    return "\n".join(lines)


def _figure(caption: str, file: str) -> list[str]:
    """A figure embedded with its caption and its path."""
    return ["", f"![{caption}](figures/{file})", "", f"*{caption}* (`figures/{file}`)"]


def _header(summary: Mapping[str, Any], results: Mapping[str, Any]) -> list[str]:
    reproduce = results["reproduce"]
    total = summary["running_time_s"]["total"]
    return [
        f"# CRCHFL reproduction: {summary['mode'] or 'results'}",
        "",
        f"Results folder `{results['out_dir'].name}`, started {reproduce.get('started_utc', '-')}; "
        f"seeds {summary['seeds']}, ablation seeds {reproduce.get('ablation_seeds')}. "
        f"Running time: {total['elapsed_s'] / 60:.1f} min elapsed (the parts' wall times sum to "
        f"{total['wall_s'] / 60:.1f} min, CPU {total['cpu_s'] / 60:.1f} min). "
        "Every [lo, hi] is the 95 % confidence interval of a mean over seeds (Student t; none with one seed), "
        "or of a success rate over episodes (Wilson).",
    ]


def _experiment_b(summary: Mapping[str, Any], figures: Mapping[str, str]) -> list[str]:
    """The schemes' table, the centralized bound beside them, CRCHFL's gains, Fig. 3 and 4."""
    lines = ["", "## Experiment B: CRCHFL, HFL and SFL under one budget", ""]
    rows = []
    for name, s in summary["schemes"].items():
        rows.append([
            NAMES.get(name, name), _pm(s["cloud_rounds"], 1), _pm(s["best_accuracy"]), _pm(s["balanced_accuracy"]),
            _pm(s["final_accuracy"]),
            _pm(s["best_loss"]), _pm(s["final_loss"]), _pm(s["consumed_bytes"], 2, 1 / GIB),
            _fmt(s["budget_bytes"] / GIB if s["budget_bytes"] else None, 2), _seeds(s),
        ])
    central = summary["centralized"]
    if central:
        rows.append([
            f"Centralized ({central['epochs']} epochs)", "-", _pm(central["best_accuracy"]),
            _pm(central["balanced_accuracy"]), _pm(central["final_accuracy"]), _pm(central["best_loss"]),
            _pm(central["final_loss"]), "-", "-", str(len(central["seeds"])),
        ])
    straight = (summary.get("baselines") or {}).get("always_straight")
    if straight:
        rows.append(["Always straight (baseline)", "-", _fmt(straight["accuracy"]), _fmt(straight["balanced_accuracy"]),
                     "-", "-", "-", "-", "-", "-"])
    lines += _table(
        ["scheme", "cloud rounds", "best accuracy", "balanced accuracy", "final accuracy", "best loss", "final loss",
         "consumed GB", "budget GB", "seeds"],
        rows,
    )
    lines += [
        "",
        "The best model of a run is its cloud model of the highest balanced accuracy (mean recall over the steer "
        "classes in the test set); best accuracy and best loss are that model's. Always straight predicts class 0 "
        "for every test sample: an accuracy at or below its figure is no learning.",
    ]
    network = summary.get("model")
    if network:
        lines += ["", "Network: " + ", ".join(f"{k} {v}" for k, v in network.items()) + " (model.* of the run configs)."]
    lines += _gains(summary["gains"])
    lines += _differences(summary.get("differences") or {}, summary["schemes"])
    lines += _learning(summary)
    for key, caption in (
        ("fig3", "Fig. 3: Accuracy and Loss against FL rounds (round 0: CRCHFL's pretrained model)"),
        ("fig4", "Fig. 4: Accuracy and Loss against consumed bytes"),
        ("centralized", "Centralized upper bound per epoch"),
    ):
        if key in figures:
            lines += _figure(caption, figures[key])
    return lines


def _learning(summary: Mapping[str, Any]) -> list[str]:
    """Per model: the errors after the DAC and per-class recall; each scheme's confusion matrix."""
    models = {NAMES.get(k, k): s for k, s in summary["schemes"].items()}
    if summary["centralized"]:
        models["Centralized"] = summary["centralized"]
    if not any(s.get("recall") for s in models.values()):
        return []
    classes = [f"{v:+.3f}" for v in STEER_CLASS_VALUES]
    lines = [
        "", "### What the best models learned", "",
        "Means over seeds. Steer error: mean |steer after the DAC - the expert's steer|; throttle and brake: mean "
        "absolute error. Recall per steer class (its DAC value; + = right): the share of the test samples of that "
        "class the model classed right.",
        "",
    ]
    rows = [
        [name, _pm(s["balanced_accuracy"]), _pm(s["best_steer_error"], 3), _pm(s["best_throttle_error"], 3),
         _pm(s["best_brake_error"], 3), *(_fmt(r, 2) for r in (s.get("recall") or [None] * len(classes)))]
        for name, s in models.items()
    ]
    straight = (summary.get("baselines") or {}).get("always_straight")
    if straight:
        rows.append(["Always straight (baseline)", _fmt(straight["balanced_accuracy"]),
                     _fmt(straight.get("steer_error"), 3), "-", "-", "1.00", *["0.00"] * (len(classes) - 1)])
    lines += _table(["model", "balanced accuracy", "steer error", "throttle error", "brake error", *classes], rows)
    for name, s in models.items():
        if s.get("confusion"):
            lines += ["", f"Confusion of {name}'s best models, summed over seeds (row: true class, column: predicted):",
                      ""]
            rows = [[c, *map(str, row)] for c, row in zip(classes, s["confusion"])]
            lines += _table(["true / predicted", *classes], rows)
    return lines


def _difference_words(d: Mapping[str, Any], scale: float = 100.0) -> str:
    """'+1.60 points [-0.5, 3.7], p 0.12: not distinguishable at 95 %' of a paired difference."""
    if d.get("mean") is None:
        return "-"
    text = f"{scale * d['mean']:+.2f} points"
    if d.get("ci95"):
        lo, hi = d["ci95"]
        text += f" [{scale * lo:+.2f}, {scale * hi:+.2f}]"
    if d.get("p") is not None:
        text += f", p {d['p']:.3g}"
    if not distinguishable(d.get("ci95")):
        text += ": not distinguishable at 95 %"
    return text


# How the report names the closed-loop keys of summary.json "differences".
CLOSED_LOOP_WORDS = {"success_rate": "closed-loop success", "driving_score": "driving score"}


def _differences(diff: Mapping[str, Any], schemes: Mapping[str, Any]) -> list[str]:
    """CRCHFL against each scheme, paired by seed, in words; and when HFL's models are SFL's."""
    if not diff:
        return []
    lines = ["", "CRCHFL minus each other model, paired by seed (the same data, start and traffic), with the "
             "paired-t 95 % interval and p-value; the closed loop's success rate and driving score over all of a "
             "seed's benchmark episodes, and then paired by episode (the same seed and route):", ""]
    for pair, keys in diff.items():
        other = NAMES.get(pair.split("-", 1)[1], pair)
        by_seed = {key: d for key, d in keys.items() if key != "by_episode"}
        parts = [f"{CLOSED_LOOP_WORDS.get(key, key.replace('_', ' '))} {_difference_words(d)}"
                 for key, d in by_seed.items()]
        line = f"- over {other} ({by_seed[next(iter(by_seed))]['n']} seeds): " + "; ".join(parts) + "."
        if keys.get("by_episode"):
            episodes = keys["by_episode"]
            line += f" By episode ({episodes[next(iter(episodes))]['n']} pairs): " + "; ".join(
                f"{CLOSED_LOOP_WORDS.get(key, key)} {_difference_words(d)}" for key, d in episodes.items()) + "."
        lines.append(line)
    if ((schemes.get("hfl") or {}).get("hyper") or {}).get("cloud_interval") == 1 and "sfl" in schemes:
        lines += ["", "HFL runs here with cloud_interval 1: its two-tier sample-weighted average is then the flat "
                  "one of SFL, so the two train the same models round for round and differ only in the bytes "
                  "they spend, and so in their rounds (docs/federation.md)."]
    return lines


def _gains(gain: Mapping[str, Any]) -> list[str]:
    if "best_accuracy" not in gain:
        return []
    lines = ["", "Gains of CRCHFL's accuracy (means over seeds; relative: 100 (CRCHFL - other) / other):", ""]
    rows = []
    for other, paper in PAPER_GAINS_PERCENT.items():
        if other not in gain["best_accuracy"]:
            continue
        best, final = gain["best_accuracy"][other], gain["final_accuracy"][other]
        rows.append([
            f"over {NAMES[other]}", _percent(best["relative_percent"]), _fmt(best["points"], 2),
            _percent(final["relative_percent"]), _fmt(final["points"], 2), f"+{paper:.2f} %",
        ])
    lines += _table(
        ["", "best accuracy, relative", "best, points", "final accuracy, relative", "final, points", "paper"], rows
    )
    return lines + [
        "",
        "The paper does not say whether its +10.33 % and +12.41 % are relative or in points; both are given here.",
    ]


def _experiment_e(summary: Mapping[str, Any], figures: Mapping[str, str]) -> list[str]:
    """The budget curve: each scheme's balanced accuracy and driving score per budget, where CRCHFL leads,
    and the bytes each scheme needed to reach given balanced accuracies."""
    curve = summary.get("budget_curve") or {}
    if not curve:
        return []
    lines = ["", "## Experiment E: accuracy and driving against the budget", "",
             "HFL's and SFL's schedules do not depend on the budget: their figure at a smaller budget is the best "
             "model their full run had made within it. CRCHFL is planned again by the optimizer for each budget "
             "and runs again. Balanced accuracy and driving score (benchmark, all episodes) are means over seeds "
             "with their 95 % intervals.", ""]
    budgets = list(next(iter(curve.values())))
    rows = []
    for label in budgets:
        row = [label]
        for scheme, points in curve.items():
            point = points.get(label) or {}
            row += [_pm(point["balanced_accuracy"], 3) if point else "-",
                    _pm(point["driving_score"], 1, 100.0) if point else "-"]
        rows.append(row)
    header = ["budget (GB)"] + [f"{NAMES.get(s, s)} {what}" for s in curve for what in ("bal. acc.", "driving score")]
    lines += _table(header, rows)
    lines += ["", lead_sentence(summary.get("budget_differences") or {})]
    if "budget" in figures:
        lines += _figure("Experiment E: balanced accuracy and driving score against the budget", figures["budget"])
    to_accuracy = summary.get("bytes_to_accuracy") or {}
    if to_accuracy:
        targets = list(next(iter(to_accuracy.values())))
        lines += ["", "GB consumed until the first evaluation at each balanced accuracy (mean over seeds; '-': "
                  "not every seed reached it):", ""]
        lines += _table(["scheme", *targets],
                        [[NAMES.get(s, s), *(_fmt(v, 2) for v in values.values())] for s, values in to_accuracy.items()])
    return lines


# The figures the budget curve's sentence speaks of, in its order
LEAD_FIGURES = {"balanced_accuracy": "balanced accuracy", "driving_score": "closed-loop driving score"}


def lead_sentence(differences: Mapping[str, Any]) -> str:
    """One sentence: at which budgets CRCHFL's balanced accuracy and driving score are ahead of (or behind)
    each scheme beyond noise (the paired 95 % interval excludes 0), and where they are not distinguishable."""
    clauses = []
    for key, figure in LEAD_FIGURES.items():
        parts = []
        for pair, by_budget in differences.items():
            words = _budget_words({label: keys.get(key) or {} for label, keys in by_budget.items()})
            if words:
                parts.append(f"over {NAMES.get(pair.split('-', 1)[1], pair)} " + ", ".join(words))
        if parts:
            clauses.append(f"{figure} " + "; ".join(parts))
    if not clauses:
        return "CRCHFL against the other schemes by budget: no paired seeds to compare."
    return "CRCHFL against the other schemes, paired by seed: " + "; ".join(clauses) + "."


def _budget_words(by_budget: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The budgets where one paired difference is ahead, behind, or not distinguishable, in words."""
    ahead, behind, even = [], [], []
    for label, d in by_budget.items():
        if d.get("mean") is None:
            continue
        if not distinguishable(d.get("ci95")):
            even.append(label)
        else:
            (ahead if d["mean"] > 0 else behind).append(label)
    return [f"{what} at {', '.join(labels)} GB" for what, labels in
            (("ahead beyond noise", ahead), ("behind beyond noise", behind), ("not distinguishable at 95 %", even))
            if labels]


def _experiment_d(summary: Mapping[str, Any], figures: Mapping[str, str]) -> list[str]:
    """The edge_interval ablation's table and Fig. 7."""
    if not summary["ablation"]:
        return []
    lines = ["", "## Experiment D: CRCHFL with edge_interval fixed", ""]
    rows = []
    for setting, s in summary["ablation"].items():
        hyper = s["hyper"] or {}
        pct = s["budget_percent"]
        rows.append([
            setting[3:], _fmt(hyper.get("pretrain_batch")), _fmt(hyper.get("cloud_interval")),
            _pm(s["cloud_rounds"], 1), *(_fmt(pct[p], 1) for p in (*STAGES, "unused")),
            _pm(s["best_accuracy"]), _pm(s["final_loss"]), _seeds(s),
        ])
    lines += _table(
        ["edge_interval", "pretrain batch", "cloud_interval", "cloud rounds", "stage I %", "stage II %",
         "stage III %", "unused %", "best accuracy", "final loss", "seeds"],
        rows,
    )
    if "fig7" in figures:
        lines += _figure("Fig. 7: (a) budget split across stages, (b) Loss, (c) Accuracy", figures["fig7"])
    return lines


def _closed_loop(summary: Mapping[str, Any], figures: Mapping[str, str]) -> list[str]:
    """Each model's drive of each route, and Fig. 5 per route."""
    if not summary["closed_loop"]:
        return []
    lines = [
        "", "## Closed loop: each scheme's best model drives", "",
        "The model of the seed with the highest balanced accuracy (its best_model.pt, final_model.pt where its "
        "vehicles labelled with DAgger; centralized: the last "
        "epoch of the seed that ended best) drives each route in SUMO; the reference is the scripted driver.",
    ]
    for route, labels in summary["closed_loop"].items():
        lines += ["", f"### {route}", ""]
        rows = [[NAMES.get(label, label), *(_fmt(m.get(c), 3) for c in DRIVE_COLUMNS)] for label, m in labels.items()]
        lines += _table(["model", *DRIVE_COLUMNS], rows)
        if f"fig5_{route}" in figures:
            lines += _figure(f"Fig. 5, {route}", figures[f"fig5_{route}"])
    return lines


def _drive_bench(summary: Mapping[str, Any]) -> list[str]:
    """The closed-loop benchmark: per town, each model's success, route completion and driving score per task."""
    bench = summary.get("drive_bench") or {}
    spread = summary.get("drive_bench_spread") or {}
    if not bench:
        return []
    lines = [
        "", "## Closed-loop benchmark (`drive-bench`)", "",
        "Each model drives the CoRL2017-style suites of start/goal routes drawn apart from the data vehicles' "
        "routes (docs/drive.md). A cell: success rate [its Wilson 95 % interval over the cell's episodes] / "
        "route completion / driving score (route completion x the CARLA Leaderboard's infraction penalty), "
        "each in %; infractions per km after the bar.",
    ]
    if spread:
        lines += [
            "",
            f"{', '.join(NAMES.get(label, label) for label in spread)}: every seed's model drove the same episodes; "
            "a cell gives all their episodes together, with the sample standard deviation over the seeds' "
            "models after the success rate and the driving score (±).",
        ]
    towns = list(dict.fromkeys(town for results in bench.values() for town in results))
    for town in towns:
        tasks = list(dict.fromkeys(t for results in bench.values() for t in results.get(town, {})))
        rows = []
        for label, results in bench.items():
            cells = []
            for task in tasks:
                r = results.get(town, {}).get(task)
                s = spread.get(label, {}).get(town, {}).get(task)
                ci = None if r is None else r.get("success_ci95")
                wilson = f" [{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]" if ci else ""
                cells.append("-" if r is None else (
                    f"{100 * r['success_rate']:.0f}{wilson}{_seed_std(s, 'success_rate')} / "
                    f"{100 * r['route_completion']:.0f} / "
                    f"{100 * r['driving_score']:.0f}{_seed_std(s, 'driving_score')} | {_fmt(r['infractions_per_km'], 2)}"
                ))
            rows.append([NAMES.get(label, label), *cells])
        lines += ["", f"### {town}", ""]
        lines += _table(["model", *tasks], rows)
    return lines


def _seed_std(spread: Mapping[str, Any] | None, key: str) -> str:
    """' ± S' (S in %) of a benchmark spread entry, '' without one or with a single seed."""
    std = (spread or {}).get(key, {}).get("std")
    return "" if std is None else f" ± {100 * std:.0f}"


def _settings(summary: Mapping[str, Any], results: Mapping[str, Any]) -> list[str]:
    """The reproduction's settings and the hyper-parameters each scheme ran with."""
    config = results["reproduce"].get("config") or {}
    lines = ["", "## Settings", "", "Reproduction settings (reproduce.json):", "", "```json",
             json.dumps(config, indent=2), "```"]
    rows = []
    for name, s in summary["schemes"].items():
        hyper = s["hyper"] or {}
        rows.append([NAMES.get(name, name), *(_fmt(hyper.get(k)) for k in HYPER), ", ".join(map(str, s["seeds"]))])
    if rows:
        lines += ["", "Hyper-parameters the runs used (CRCHFL: the optimizer's plan; cloud_rounds 0 = until the "
                  "budget is spent). Each run's full settings: `runs/SCHEME/seed-S/config.json`.", ""]
        lines += _table(["scheme", *HYPER, "seeds"], rows)
    return lines


def _environment(summary: Mapping[str, Any], results: Mapping[str, Any], figures: Mapping[str, str]) -> list[str]:
    """Versions, machine, and every part's running time."""
    env = results["reproduce"].get("environment") or {}
    lines = [
        "", "## Environment and running time", "",
        f"Python {env.get('python', '-')}, {env.get('platform', '-')}, {env.get('cpu_count', '-')} CPUs "
        f"({env.get('available_cpus', '-')} available), {env.get('torch_threads', '-')} torch threads "
        f"(OMP_WAIT_POLICY {env.get('omp_wait_policy', '-')}), CUDA {_fmt(env.get('cuda'))}, "
        f"bfloat16 arithmetic on the CPU {_fmt(env.get('bfloat16_cpu'))} (train.precision \"auto\" trains in "
        "bfloat16 where it is there).",
        "",
    ]
    lines += _table(["package", "version"], [[k, _fmt(v)] for k, v in (env.get("versions") or {}).items()])
    lines += [""]
    lines += _table(
        ["part", "wall time [s]", "CPU time [s]"],
        [[k, f"{v['wall_s']:.1f}", f"{v['cpu_s']:.1f}"] for k, v in summary["running_time_s"].items()],
    )
    return lines + ["", "Figures: " + ", ".join(f"`figures/{name}`" for name in figures.values()), ""]
