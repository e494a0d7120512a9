"""The closed-loop driving benchmark: a driver (a trained model or the scripted reference) drives every
task's episodes in each town; success, route completion, driving score and infractions per task.

    summary = run_benchmark("runs/crchfl/best_model.pt", "out/bench/crchfl", episodes=5, jobs=2)
    summary = run_benchmark(None, "out/bench/reference")          # the scripted reference driver
    summary["results"]["town01"]["one_turn"]["success_rate"]

Episodes run in groups, each group in its own spawned process when jobs > 1
(libsumo holds one simulation per process); every group builds its town's
renderer once. drive_bench_tasks.py draws the episodes, drive_bench_score.py scores them,
drive_bench_plots.py draws them. docs/drive.md describes the benchmark.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.json_files import write_json
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.core.result_files import EPISODES_FILE, RESULTS_CSV_FILE, RESULTS_MD_FILE, SUMMARY_FILE
from crchfl_sumo.driving.drive import DriveConfig, drive, sumo_warnings
from crchfl_sumo.driving.drive_bench_behaviour import ABILITIES, behaviour
from crchfl_sumo.driving.drive_bench_plots import plot_benchmark
from crchfl_sumo.driving.drive_bench_score import INFRACTIONS, route_completion, score_episode, summarize_task
from crchfl_sumo.driving.drive_bench_tasks import (
    DEFAULT_TOWNS,
    TASK_NAMES,
    TASKS,
    Episode,
    TaskConfig,
    draw_episodes,
    task_by_name,
    without_traffic,
)
from crchfl_sumo.driving.drivers import ReferenceDriver, driver_for, single_torch_thread
from crchfl_sumo.learning.settings import (
    DEFAULT_BRAKE_GAIN,
    DEFAULT_STEER_DECODING,
    check_brake_gain,
    check_steer_decoding,
)
from crchfl_sumo.sumo.route import read_net, route_geometry
from crchfl_sumo.sumo.scenario import Scenario, load_scenario

PATH_EVERY_S = 1.0  # the driven path is kept at this spacing for the figure
# An episode ends when the ego has not moved on for one signal cycle of the towns (90 s):
# longer than any red (50 s) with a queue to start, shorter than the long time limits.
STUCK_S = 90.0
SUMMARY_KEYS = ("episodes", "success_rate", "route_completion", "driving_score", "infractions_per_km",
                "strict_success_rate", "red_lights_per_km", "efficiency", "smoothness", "driving_score_lb2",
                "agent_blocked", "route_timeouts")


@dataclass(frozen=True)
class BenchConfig:
    """Settings of a benchmark run.

    tasks           the suites driven, in this order (drive_bench_tasks.TASKS)
    routes          how start/goal routes are drawn (drive_bench_tasks.TaskConfig)
    drive           the drive loop's settings (an episode ends stuck after STUCK_S); each episode
                    sets its own warm-up
    group_episodes  episodes a worker drives one after the other (one process start, one renderer each)
    steer_decoding  how a model's steer scores become a steer (learning.settings.STEER_DECODINGS;
                    the reference driver has none)
    brake_gain      a target-speed model reaches lower targets in its speed horizon / brake_gain
                    (policies.ModelPolicy)
    """

    tasks: tuple[str, ...] = TASK_NAMES
    routes: TaskConfig = field(default_factory=TaskConfig)
    drive: DriveConfig = field(default_factory=lambda: DriveConfig(stuck_s=STUCK_S))
    group_episodes: int = 4
    steer_decoding: str = DEFAULT_STEER_DECODING
    brake_gain: float = DEFAULT_BRAKE_GAIN

    def __post_init__(self) -> None:
        if not self.tasks:
            raise CrchflError(f"--tasks: name at least one task ({', '.join(TASK_NAMES)})")
        for name in self.tasks:
            task_by_name(name)
        if self.group_episodes < 1:
            raise CrchflError(f"bench.group_episodes must be >= 1, got {self.group_episodes}")
        check_steer_decoding(self.steer_decoding)
        check_brake_gain(self.brake_gain)


# --- one group of episodes (runs in a worker process) -------------------------------------------------


# SUMO's warnings of a benchmark's drives (collisions it saw, vehicles moved by TraCI): a file an episode
# in this folder of --out instead of the console; summary.json counts them.
SUMO_LOG_DIR = "sumo-logs"


def episode_log(log_dir: Path | None, town: str, task: str, index: int) -> Path | None:
    """The file SUMO's warnings of one episode go to (None without ``log_dir``: the console)."""
    return None if log_dir is None else Path(log_dir) / f"{town}-{task}-{index}.log"


def drive_episodes(
    driver, scenario_name: str, episodes: Sequence[Episode], config: BenchConfig, log_dir: Path | None = None
) -> list[dict]:
    """Drive ``episodes`` (all in one town) one after the other; one record per episode. SUMO's warnings go
    to ``log_dir``/TOWN-TASK-INDEX.log when given."""
    scenario = load_scenario(scenario_name)
    empty = without_traffic(scenario)
    traffic_of = {t.name: t.traffic for t in TASKS}
    net = read_net(Path(scenario.net_path))
    renderer = driver.renderer(scenario.net_path) if driver.renders else None
    records = []
    with single_torch_thread(driver.renders):
        for episode in episodes:
            route = route_geometry(net, episode.edges)
            result = drive(
                scenario if traffic_of[episode.task] else empty,
                route,
                driver.policy(route, net),
                seed=episode.sumo_seed,
                max_s=episode.time_limit_s,
                config=dataclasses.replace(config.drive, warmup_s=episode.warmup_s),
                renderer=renderer,
                expert=driver.expert(),
                keep_frames=False,
                sumo_log=episode_log(log_dir, episode.town, episode.task, episode.index),
            )
            records.append(episode_record(episode, result, config.drive.finish_before_end_m, scenario.step_length_s))
    return records


def episode_record(episode: Episode, result, finish_before_end_m: float, step_s: float) -> dict[str, Any]:
    """What the benchmark keeps of a drive: the episode, its metrics, its score and its path (JSON-ready)."""
    log, metrics = result.log, result.metrics
    completion = route_completion(
        log.progress_m, log.on_road, float(log.progress_m[0]), result.route.length_m - finish_before_end_m
    )
    extra = behaviour(log, result.route.crossings, float(log.progress_m[0]),
                      result.route.length_m - finish_before_end_m, step_s, result.route.lane_changes)
    every = max(1, round(PATH_EVERY_S / step_s))
    keep = list(range(0, len(log), every)) + ([len(log) - 1] if (len(log) - 1) % every else [])
    return {
        **asdict(episode),
        "edges": list(episode.edges),
        **{k: metrics[k] for k in ("end_reason", "completion", "duration_s", "distance_m", "mean_speed_mps",
                                   "max_abs_offset_m", *INFRACTIONS)},
        **score_episode(metrics, completion, extra["min_speed_penalty"]),
        **extra,
        "path_xy": [[round(float(log.x_m[i]), 2), round(float(log.y_m[i]), 2)] for i in keep],
        "route_xy": [[round(float(x), 2), round(float(y), 2)] for x, y in result.route.xy_m],
    }


# --- the benchmark ------------------------------------------------------------------------------------


def run_benchmark(
    model: str | Path | None,
    out_dir: str | Path,
    episodes: int = 5,
    jobs: int = 1,
    seed: int = 0,
    towns: Sequence[str] = DEFAULT_TOWNS,
    config: BenchConfig = BenchConfig(),
    progress: Progress | None = None,
    driver=None,
) -> dict[str, Any]:
    """Run the benchmark and write OUT/summary.json, results.md, results.csv, episodes.json, trajectories.png.

    ``model``: a checkpoint path, or None / 'reference' for the scripted
    driver. ``driver`` (instead of ``model``) is any object with ``label``,
    ``renders``, ``policy(route, net)`` (net: the sumolib network), ``expert()``
    (the ExpertConfig whose steering rack the dynamics use) and, if it renders,
    ``renderer(net_path)``; with ``jobs`` > 1 it must pickle. Returns the
    summary: ``results[TOWN][TASK]`` holds episodes, success_rate,
    route_completion, driving_score and infractions_per_km.
    """
    if episodes < 1:
        raise CrchflError(f"--episodes must be >= 1 (episodes per task and town), got {episodes}")
    if jobs < 1:
        raise CrchflError(f"--jobs must be >= 1 (parallel processes), got {jobs}")
    if seed < 0:
        raise CrchflError(f"--seed must be >= 0, got {seed}")
    if not towns:
        raise CrchflError(f"--towns: name at least one town ({', '.join(DEFAULT_TOWNS)} or a .sumocfg)")
    driver = driver or driver_for(model, config.steer_decoding, config.brake_gain)
    started = time.perf_counter()
    tasks = [task_by_name(t) for t in config.tasks]
    scenarios: dict[str, Scenario] = {}
    for name in towns:
        try:
            scenarios[str(name)] = load_scenario(name)
        except CrchflError as exc:
            raise CrchflError(f"--towns: {exc}") from None
    drawn = {name: draw_episodes(s, tasks, episodes, seed, config.routes) for name, s in scenarios.items()}
    log_dir = Path(out_dir) / SUMO_LOG_DIR
    for stale in log_dir.glob("*.log"):  # an earlier run's, in a folder run again
        stale.unlink()
    calls = []
    for name, town_episodes in drawn.items():
        groups = math.ceil(len(town_episodes) / config.group_episodes)
        calls += [(driver, name, town_episodes[g::groups], config, log_dir) for g in range(groups)]  # tasks mixed
    total = sum(len(e) for e in drawn.values())
    done = {"episodes": 0, "successes": 0}

    def on_result(_, records) -> None:
        done["episodes"] += len(records)
        done["successes"] += sum(r["success"] for r in records)
        report(progress, "episode", done["episodes"], total, success=f"{done['successes']}/{done['episodes']}")

    report(progress, "episode", 0, total)
    with Executor(BackendConfig(num_cpus=jobs)) as executor:
        grouped = executor.map(drive_episodes, calls, isolate=jobs > 1, on_result=on_result)
    town_names = [s.name for s in scenarios.values()]
    records = sorted(
        (r for group in grouped for r in group),
        key=lambda r: (town_names.index(r["town"]), config.tasks.index(r["task"]), r["index"]),
    )
    drawn_tasks = {scenarios[name].name: {e.task for e in town_episodes} for name, town_episodes in drawn.items()}
    # a task without a candidate route in a town is left out of its results and listed as skipped
    skipped = [{"town": town, "task": task, "reason": "no candidate route"}
               for town in town_names for task in config.tasks if task not in drawn_tasks[town]]
    results = {
        town: {
            task: summarize_task([r for r in records if r["town"] == town and r["task"] == task])
            for task in config.tasks if task in drawn_tasks[town]
        }
        for town in town_names
    }
    summary = {
        "driver": driver.label,
        "model": "" if isinstance(driver, ReferenceDriver) else str(getattr(driver, "path", driver.label)),
        "episodes_per_task": episodes,
        "seed": seed,
        "towns": town_names,
        "tasks": list(config.tasks),
        "results": results,
        "skipped": skipped,
        "sumo_warnings": sumo_warnings(log_dir),
        "jobs": jobs,
        "wall_s": round(time.perf_counter() - started, 1),
    }
    write_outputs(Path(out_dir), summary, records, scenarios)
    return summary


# --- outputs ------------------------------------------------------------------------------------------


def write_outputs(out: Path, summary: dict, records: list[dict], scenarios: dict[str, Scenario]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / SUMMARY_FILE, summary)
    write_json(out / EPISODES_FILE, records, indent=1)
    atomic_write_text(out / RESULTS_MD_FILE, results_table(summary) + "\n")
    atomic_write_text(out / RESULTS_CSV_FILE, results_csv(summary))
    plot_benchmark(records, {s.name: Path(s.net_path) for s in scenarios.values()}, summary["tasks"],
                   out / "trajectories.png", title=f"drive-bench: {summary['driver']}")


def _rows(summary: dict):
    for town, tasks in summary["results"].items():
        for task, r in tasks.items():
            yield town, task, r


def _per_km(value) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def results_table(summary: dict) -> str:
    """The per-task results as a markdown table."""
    lines = [
        f"Driver: {summary['driver']}; {summary['episodes_per_task']} episodes per task, seed {summary['seed']}.",
        "",
        "| town | task | episodes | success [95 % CI] | strict success | route completion | driving score "
        "| infractions / km | red lights / km | efficiency | smoothness |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for town, task, r in _rows(summary):
        ci = r.get("success_ci95")  # summaries written before it have none
        interval = f" [{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]" if ci else ""
        lines.append(
            f"| {town} | {task} | {r['episodes']} | {100 * r['success_rate']:.0f} %{interval} | "
            f"{_percent(r.get('strict_success_rate'))} | {100 * r['route_completion']:.1f} % | "
            f"{100 * r['driving_score']:.1f} | {_per_km(r['infractions_per_km'])} | {_per_km(r.get('red_lights_per_km'))} | "
            f"{_percent(r.get('efficiency'), 0.01)} | {_percent(r.get('smoothness'))} |"
        )
    abilities = _ability_lines(summary)
    skipped = [f"Skipped: {s['task']} in {s['town']} ({s['reason']})." for s in summary.get("skipped", [])]
    return "\n".join(lines + ([""] + abilities if abilities else []) + ([""] + skipped if skipped else []))


def _percent(value, scale: float = 1.0) -> str:
    return "n/a" if value is None else f"{100 * scale * value:.0f} %"


def _ability_lines(summary: dict) -> list[str]:
    """Per town, each ability's successes of attempts over all its tasks (those it never attempted left out:
    the towns have no lane to change to)."""
    lines = []
    for town, tasks in summary["results"].items():
        if not all("abilities" in r for r in tasks.values()):
            continue
        parts = []
        for name in ABILITIES:
            attempts = sum(r["abilities"].get(name, {}).get("attempts", 0) for r in tasks.values())
            ok = sum(r["abilities"].get(name, {}).get("successes", 0) for r in tasks.values())
            if attempts:
                parts.append(f"{name.replace('_', ' ')} {ok} of {attempts}")
        if parts:
            lines.append(f"Abilities in {town}: " + ", ".join(parts) + ".")
    return lines


def results_csv(summary: dict) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["town", "task", *SUMMARY_KEYS, "success_ci_lo", "success_ci_hi"])
    for town, task, r in _rows(summary):
        values = [r.get(k) for k in SUMMARY_KEYS] + list(r.get("success_ci95", (None, None)))
        writer.writerow([town, task, *("" if v is None else v for v in values)])
    return buffer.getvalue()

