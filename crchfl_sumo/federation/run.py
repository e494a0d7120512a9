"""`crchfl-sumo run CONFIG.toml --out DIR [--resume]`: a federation run from config to results folder.

DIR receives (every file written atomically):

  config.toml      the config file as given
  config.json      the resolved run: settings, the four hyper-parameters used, byte sizes
  federation_state.pt  the FederationState after the latest step less its history, and the logs' marks
                   (what --resume reads; a model is never in a file of this name, nor the state in a
                   checkpoint.pt: runs written before this name, as checkpoint.pt, are renamed on resume)
  federation_state.prev.pt  the one of the step before (what --resume reads if the latest is damaged)
  metrics.jsonl    one line per aggregation (stage I, each edge aggregation, each cloud aggregation)
  ledger.jsonl     every charged transfer (first line: the sizes)
  stragglers.jsonl every vehicle that missed an aggregation or a download: what happened (reason)
                   and why (cause: unavailable, out_of_coverage, slow_compute, deadline)
                   (the three .jsonl logs are append-only: federation/logs.py)
  best_model.pt    the best cloud model so far (checkpoint.save_checkpoint format)
  best_model_within_<B>gb.pt  per [ledger] marks_gb B: the best cloud model among the evaluations
                   made within B GB (written once the run has passed B, or at its end)
  final_model.pt   the last cloud model
  summary.json     scheme, cloud_rounds, edge_aggregations, consumed_bytes, budget_bytes,
                   best/final accuracy and loss, sim_time_s, stop_reason, stragglers,
                   selection, skipped_by_selection, wasted_bytes, ...

A run killed at any moment and resumed with --resume continues from the
latest checkpoint and ends with the same files as an uninterrupted run with
the same seed: every step's randomness derives from the seed and the step
number, the clock re-runs SUMO deterministically from the start, and the
logs are cut back to the checkpoint's marks. A step writes its log lines,
then the checkpoint, then the files derived from the state (models, summary),
on a background thread while the next step runs (core/background.py: one
save at a time, in order; the run waits for the last before it returns).
The state it replaces becomes federation_state.prev.pt, so one empty, truncated
or damaged federation_state.pt costs a step, not the run: a resume refuses it with
a message and continues from the previous one. A run or resume first removes
the temporaries a killed atomic write left (core/atomic.py).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from crchfl_sumo.accounting.energy import vehicle_energy_j
from crchfl_sumo.accounting.ledger import GIB, Ledger, budget_marks_bytes, gb_label, resolve_sizes
from crchfl_sumo.core.atomic import (
    atomic_path_keeping_previous,
    atomic_write_text,
    previous_path,
    read_latest,
    remove_stale_temporaries,
)
from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.core.background import BackgroundSaver
from crchfl_sumo.core.config import changed_keys_text, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.json_files import write_json
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.core.result_files import (
    BEST_MODEL_FILE,
    CONFIG_JSON_FILE,
    FINAL_MODEL_FILE,
    MODEL_FILE,
    STATE_FILE,
    SUMMARY_FILE,
)
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.logs import LOGS, Marks, append_logs, restore_logs, start_logs
from crchfl_sumo.federation.loop import Federation
from crchfl_sumo.federation.run_config import (
    RunConfig,
    load_run_config,
    resolve_config_path,
    resolved_as_today,
    resolved_config,
    resolved_train,
    with_backend,
)
from crchfl_sumo.federation.run_data import RunData, make_clock, read_inputs
from crchfl_sumo.federation.settings import HyperParameters
from crchfl_sumo.federation.state import (
    FederationState,
    Labeller,
    LoopInputs,
    check_payload,
    initial_state,
    sim_time_s,
)
from crchfl_sumo.learning.checkpoint import load_weights_only, save_checkpoint
from crchfl_sumo.learning.codecs import encoded_fraction
from crchfl_sumo.learning.evaluation import always_straight
from crchfl_sumo.learning.model import state_size_bytes, with_training_data
from crchfl_sumo.learning.strategies import strategy_from
from crchfl_sumo.learning.trainers import RayTrainer, TorchTrainer
from crchfl_sumo.links.clock import Clock
from crchfl_sumo.links.fleet import draw_fleet
from crchfl_sumo.links.residence import Coverage, sites_coverage
from crchfl_sumo.planning.problem import make_plan
from crchfl_sumo.planning.settings import calibrated
from crchfl_sumo.planning.timing import measured_rates_bps, run_timing

log = logging.getLogger(__name__)

TRANSFER_COUNTS = ("downloads", "downloads_failed", "uploads", "uploads_failed", "relayed_transfers")
CHECKPOINT_FORMAT = "crchfl-sumo-federation/2"  # /2: the history lives in the logs
PREVIOUS_STATE_FILE = previous_path(STATE_FILE).name  # federation_state.prev.pt: the step before's, for a damaged one
LEGACY_STATE_FILE = MODEL_FILE  # the state's name before: now only a model's


# Builds the vehicles' route experts of a run with [dagger] (driving.vehicle_dagger.labeller_factory).
LabellerFactory = Callable[[RunConfig, RunData, Path], Labeller]


def make_trainer(config: RunConfig, inputs: RunData, executor: Executor):
    """The run's Trainer: in this process (local backend) or as tasks (ray). It trains with the precision
    and multi-vehicle method config.json records ("auto" decided here, not again on each Ray worker)."""
    args = (config.model, resolved_train(config), inputs.test, config.federation.seed)
    mu = run_strategy(config).proximal_mu
    return RayTrainer(*args, executor, proximal_mu=mu) if executor.is_ray else TorchTrainer(*args, proximal_mu=mu)


def run_strategy(config: RunConfig):
    """The run's aggregation strategy ([federation] strategy, strategy_options; learning/strategies.py)."""
    return strategy_from(config.federation.strategy, config.federation.strategy_options)



def codec_fractions(config: RunConfig, state) -> tuple[float, float]:
    """(every model transfer's, a vehicle upload's) encoded bytes over the raw ones under [federation]
    update_codec (learning.codecs): int8 shrinks every transfer, topk a vehicle's upload only."""
    fed = config.federation
    if fed.update_codec == "int8":
        fraction = encoded_fraction(state, "int8")
        return fraction, fraction
    if fed.update_codec == "topk":
        return 1.0, encoded_fraction(state, "topk", fed.topk_fraction)
    return 1.0, 1.0


def resolve_hyper(
    config: RunConfig, inputs: RunData, model_bytes: int, clock: Clock, fractions: tuple[float, float] = (1.0, 1.0)
) -> tuple[HyperParameters, dict | None]:
    """The four hyper-parameters: the config's, or (CRCHFL, use_plan) the optimizer's for this run.

    The plan takes the run's topology, its sample counts, and its timing: the
    loop's compute model and the wireless rate measured on ``clock`` (planning/timing.py).
    """
    fed = config.federation
    if not fed.use_plan:
        return HyperParameters(fed.pretrain_batch, fed.edge_interval, fed.cloud_interval, fed.cloud_rounds), None
    per_edge = tuple(sum(1 for v in inputs.vehicles if inputs.home_site[v] == i) for i in range(len(inputs.edges)))
    counts = {v: len(inputs.samples[v]) for v in inputs.vehicles}
    allocation = run_timing(
        dataclasses.replace(calibrated(config.allocation), vehicles_per_edge=per_edge, local_samples=sum(counts.values())),
        samples_per_vehicle=counts,
        compute_s_per_sample=fed.compute_s_per_sample,
        pretrain_epochs=fed.pretrain_epochs,
        rates_bps=measured_rates_bps(clock, inputs.vehicles, config.allocation.rate_window_s),
        wireline_rate_bps=config.wireline.rate_bps,
    )
    plan = make_plan(
        allocation, config.ledger, real_model_bytes=model_bytes, measured_sample_bytes=inputs.measured_sample_bytes,
        fractions=fractions,
    )
    # The solver's timings differ from run to run; the rest of the plan is what the run depends on.
    fixed = {k: v for k, v in plan.to_dict().items() if k not in ("compile_s", "solve_s", "search_s")}
    return HyperParameters(plan.pretrain_batch, plan.edge_interval, plan.cloud_interval, plan.cloud_rounds), fixed


# ------------------------------------------------------------------ the run


def run_federation_dir(
    config: RunConfig,
    inputs: RunData,
    out_dir: str | Path,
    *,
    resume: bool = False,
    config_text: str | None = None,
    trainer=None,
    clock_factory: Callable[[], Any] | None = None,
    progress: Progress | None = None,
    after_checkpoint: Callable[[FederationState], None] | None = None,
    labeller_factory: LabellerFactory | None = None,
) -> dict:
    """Run (or resume) the federation of ``config`` on ``inputs`` into ``out_dir``; returns the summary.

    ``trainer`` defaults to the one of ``config.backend`` (make_trainer),
    ``clock_factory`` to ``make_clock`` (both injectable for tests).
    ``labeller_factory(config, inputs, out_dir)`` builds the vehicles' route experts that [dagger]
    needs (driving.vehicle_dagger.VehicleLabeller: driving sits above this package, so the caller
    passes it); a run with [dagger] on and none given is refused.
    ``after_checkpoint`` is called right after each checkpoint is written,
    before the other files are (tests kill a run there).
    """
    out_dir = Path(out_dir)
    # [model] commands and stop_head unset: the vehicles' data decide them
    config = dataclasses.replace(config, model=with_training_data(config.model, inputs.samples.values()))
    adopt_legacy_state(out_dir)
    if ((out_dir / STATE_FILE).exists() or (out_dir / PREVIOUS_STATE_FILE).exists()) and not resume:
        raise CrchflError(f"{out_dir} already holds a run; pass --resume to continue it or choose another --out")
    if config.dagger.enabled and labeller_factory is None:
        raise CrchflError("[dagger]: this command cannot drive the vehicles' models; run it with `crchfl-sumo run`")
    labeller = labeller_factory(config, inputs, out_dir) if config.dagger.enabled else None
    run = dict(resume=resume, config_text=config_text, clock_factory=clock_factory, progress=progress,
               after_checkpoint=after_checkpoint, labeller=labeller)
    if trainer is not None:
        return _run_with_trainer(config, inputs, out_dir, trainer, **run)
    with Executor(config.backend) as executor:
        return _run_with_trainer(config, inputs, out_dir, make_trainer(config, inputs, executor), **run)


def _run_with_trainer(
    config: RunConfig,
    inputs: RunData,
    out_dir: Path,
    trainer,
    *,
    resume: bool,
    config_text: str | None,
    clock_factory: Callable[[], Any] | None,
    progress: Progress | None,
    after_checkpoint: Callable[[FederationState], None] | None,
    labeller: Labeller | None,
) -> dict:
    checkpoint_path = out_dir / STATE_FILE
    out_dir.mkdir(parents=True, exist_ok=True)
    for path in remove_stale_temporaries(out_dir):
        log.info("removed %s left by an interrupted run", path)
    fed = config.federation
    first = trainer.initial_state()
    baseline = always_straight(inputs.test)  # what the accuracies are read against
    settings = inputs.drive_settings  # kept in the model files, so that a drive renders and steers as the data did
    fractions = codec_fractions(config, first)
    sizes = resolve_sizes(config.ledger, state_size_bytes(first), inputs.measured_sample_bytes, *fractions)
    with (clock_factory or (lambda: make_clock(config, inputs)))() as clock:
        hyper, plan = resolve_hyper(config, inputs, state_size_bytes(first), clock, fractions)
        resolved = {
            "config": resolved_config(config),
            "hyper": dataclasses.asdict(hyper),
            "plan": plan,
            "sizes": sizes.to_dict(),
            "vehicles": list(inputs.vehicles),
            "edges": list(inputs.edges),
        }
        resolved = json.loads(json.dumps(resolved))  # inf and tuples as JSON reads them back
        setup = LoopInputs(
            config=fed,
            hyper=hyper,
            vehicles=inputs.vehicles,
            samples=inputs.samples,
            home_site=inputs.home_site,
            edges=inputs.edges,
            sizes=sizes,
            rule=config.ledger.rule,
            wireline=config.wireline,
            transfer=config.transfer,
            coverage=_coverage(config, inputs),
            budget_marks_bytes=budget_marks_bytes(config.ledger),
            dagger=config.dagger,
            fleet=draw_fleet(config.clock, inputs.vehicles, fed.seed, clock.start_s),
            strategy=run_strategy(config),
        )
        state = None
        if resume and (checkpoint_path.exists() or (out_dir / PREVIOUS_STATE_FILE).exists()):
            state, marks = _load_state(checkpoint_path, resolved, sizes, config.backend)
            if state.done:  # finished before: only the derived files may be missing
                _write_outputs(out_dir, config, setup, state, settings, _handovers(clock, state), baseline)
                return summarize(config, setup, state, _handovers(clock, state), baseline)
            log.info("resuming %s at step %d (cloud round %d)", out_dir, state.steps, state.cloud_rounds)
        else:
            if config_text is not None:
                atomic_write_text(out_dir / "config.toml", config_text)
            write_json(out_dir / CONFIG_JSON_FILE, resolved)
        if state is None:
            state = initial_state(setup, trainer, clock.start_s)
            marks = start_logs(out_dir, sizes)
        data = _online_data(clock, inputs) if config.data_mode == "online" else None
        federation = Federation(setup, clock, trainer, data, labeller)

        def save_step(new: FederationState, handovers: int | None) -> None:
            # on the saver's thread; the logs reach the disk before the checkpoint that names their ends
            nonlocal marks
            marks = append_logs(out_dir, new, marks)
            _save_state(checkpoint_path, resolved, new, marks)
            if after_checkpoint is not None:
                after_checkpoint(new)
            _write_outputs(out_dir, config, setup, new, settings, handovers, baseline)

        def on_step(new: FederationState) -> None:
            saver.submit(save_step, new, _handovers(clock, new))  # the clock moves on: count its handovers now
            if progress is not None:  # a step's postfix costs a pass over the records
                report(progress, "step", new.steps, None, **progress_detail(new, sizes.budget_bytes, hyper))

        with BackgroundSaver("federation-save") as saver:  # a step's files go to disk while the next one runs
            state = federation.run(state, on_step)
        return summarize(config, setup, state, _handovers(clock, state), baseline)


def _coverage(config: RunConfig, inputs: RunData) -> Coverage | None:
    """Where the edge sites stand and how far they reach (None without sites: the constant clock)."""
    if not inputs.sites:
        return None
    return sites_coverage(inputs.sites, config.mobility.coverage_radius_m, config.mobility.time_to_trigger_s)


def _handovers(clock, state: FederationState) -> int | None:
    """The clock's handovers up to the run's latest simulated time (None for a clock that does not count them)."""
    count = getattr(clock, "handovers", None)
    return None if count is None else count(sim_time_s(state))


def _online_data(clock, inputs: RunData) -> Callable[[str, float], Samples]:
    """A vehicle's data at t_s in the online mode: its shard and what it had collected by then."""

    def data(vehicle: str, t_s: float) -> Samples:
        extra = clock.collected(vehicle, t_s)
        return inputs.samples[vehicle] if extra is None else Samples.concat([inputs.samples[vehicle], extra])

    return data


def progress_detail(state: FederationState, budget_bytes: int, hyper: HyperParameters) -> dict[str, str]:
    """What a progress bar shows beside a step: round, GB used / budget, latest loss and accuracy."""
    last = next((m for m in reversed(state.metrics) if m["loss"] is not None), None)
    rounds = hyper.cloud_rounds
    spent = sum(state.ledger_totals.get("link", {}).values())
    return {
        "round": f"{state.cloud_rounds}/{rounds}" if rounds else str(state.cloud_rounds),
        "GB": f"{spent / GIB:.2f}/{budget_bytes / GIB:.2f}",
        "loss": "-" if last is None else f"{last['loss']:.4f}",
        "acc": "-" if last is None else f"{last['accuracy']:.3f}",
    }


def summarize(
    config: RunConfig,
    setup: LoopInputs,
    state: FederationState,
    handovers: int | None = None,
    baseline: Mapping[str, float] | None = None,
) -> dict:
    """summary.json. The best model is the cloud model of the highest balanced accuracy (services._rank);
    best_* are its figures. ``baseline``: the always-straight prediction on the same test set."""
    ledger = Ledger(setup.sizes, byte_totals=state.ledger_totals)
    final = next((m for m in reversed(state.metrics) if m["stage"] in ("I", "III")), None)
    best = state.best
    return {
        "scheme": config.federation.scheme,
        "model": to_mapping(config.model),  # which network learned (arch, size, inputs)
        "rule": setup.rule,
        "cloud_rounds": state.cloud_rounds,
        "edge_aggregations": state.edge_aggregations,
        "consumed_bytes": ledger.spent_bytes,
        "budget_bytes": ledger.budget_bytes,
        "bytes_by_link": ledger.totals("link"),
        "bytes_by_stage": ledger.totals("stage"),
        **{k: state.transfers.get(k, 0) for k in TRANSFER_COUNTS},
        "relay_bytes": ledger.totals("link")["relay"],
        "model_bytes": setup.sizes.model_bytes,
        "sample_bytes": setup.sizes.sample_bytes,
        "best_accuracy": None if best is None else best["accuracy"],
        "balanced_accuracy": None if best is None else best.get("balanced_accuracy"),
        "best_steer_error": None if best is None else best.get("steer_error"),
        "best_throttle_error": None if best is None else best.get("throttle_error"),
        "best_brake_error": None if best is None else best.get("brake_error"),
        "best_recall": None if best is None else best.get("recall"),
        "best_confusion": None if best is None else best.get("confusion"),
        "best_loss": None if best is None else best["loss"],
        "best_cloud_round": None if best is None else best["cloud_round"],
        "final_accuracy": None if final is None else final["accuracy"],
        "final_balanced_accuracy": None if final is None else final.get("balanced_accuracy"),
        "final_loss": None if final is None else final["loss"],
        "sim_time_s": sim_time_s(state),
        "stragglers": len(state.stragglers),
        "straggler_causes": dict(Counter(s.get("cause", "not recorded") for s in state.stragglers)),
        "energy_j": vehicle_energy_j(state.records, state.train_s, setup.vehicles, config.energy,
                                     setup.fleet.off_s_within),
        **({"compute_factors": dict(setup.fleet.compute_factor)} if setup.fleet.compute_factor else {}),
        **({"off_share": off_share(setup, state)} if setup.fleet.intermittent else {}),
        "selection": config.federation.selection,
        "skipped_by_selection": state.skipped,
        "wasted_bytes": state.wasted_bytes,
        "mean_uplink_rate_mbps": mean_uplink_rate_mbps(state.records),
        "handovers": handovers,
        "stop_reason": state.stop_reason,
        "baselines": {"always_straight": dict(baseline)} if baseline is not None else {},
        "hyper": dataclasses.asdict(setup.hyper),
        "vehicles": list(setup.vehicles),
        "samples_per_vehicle": {v: setup.count(v) for v in setup.vehicles},
        "budget_marks": {
            gb_label(gb): None if line is None else {k: line.get(k) for k in MARK_KEYS}
            for gb, (line, _, _) in budget_mark_results(config, setup, state).items()
        },
        # [dagger]: the cloud rounds after which the vehicles drove and labelled (their labels: dagger/)
        **({"dagger_rounds": list(state.dagger_rounds)} if config.dagger.enabled else {}),
    }


def off_share(setup: LoopInputs, state: FederationState) -> float:
    """The share of the run's simulated time (from the federation's start to its latest moment) the
    vehicles were off, over all of them (links/fleet.py)."""
    start_s, end_s = setup.fleet.start_s, sim_time_s(state)
    if end_s <= start_s:
        return 0.0
    off = sum(setup.fleet.off_s_within(v, start_s, end_s) for v in setup.vehicles)
    return off / (len(setup.vehicles) * (end_s - start_s))


def mean_uplink_rate_mbps(records) -> float | None:
    """The mean rate of the wireless uplinks [Mbit/s]: each charged transfer's bytes over its duration (None:
    none took time). What a loaded cell (links/clock.py) and the traffic density change."""
    rates = [8.0 * r.size_bytes / (r.end_s - r.start_s) / 1e6 for r in records
             if r.link == "wireless" and r.direction == "uplink" and r.end_s > r.start_s]
    return sum(rates) / len(rates) if rates else None


MARK_KEYS = ("balanced_accuracy", "accuracy", "loss", "consumed_bytes", "cloud_round", "step")


def mark_model_file(gb: float) -> str:
    """The file of the best model within budget mark ``gb`` in a run folder."""
    return f"best_model_within_{gb_label(gb)}gb.pt"


def run_model_file(summary: Mapping[str, Any]) -> str:
    """The model of a run (its summary.json) that drives: its best cloud model, or its last where its vehicles
    labelled with DAgger (``dagger_rounds``): the offline test set holds none of the states those labels teach,
    and the last drove as well as the best offline round or better (docs/beyond_paper.md)."""
    return FINAL_MODEL_FILE if summary.get("dagger_rounds") else BEST_MODEL_FILE


def budget_mark_results(config: RunConfig, setup: LoopInputs, state: FederationState) -> dict[float, tuple]:
    """Per budget mark [GB]: (the best metrics line within it, its model, whether the run has passed the
    mark); line and model are None if no evaluation was within it; a mark not passed has the best so far."""
    results = {}
    for gb, mark in zip(config.ledger.marks_gb, setup.budget_marks_bytes):
        key = str(mark)
        if key in state.budget_marks:
            results[gb] = (state.budget_marks[key], state.budget_mark_models.get(key), True)
        else:
            results[gb] = (state.best, state.best_model, False)
    return results


def adopt_legacy_state(out_dir: Path) -> None:
    """A run folder written when the state was checkpoint.pt (and checkpoint.prev.pt): rename them to today's
    names, so that it resumes. A folder is a run's when it holds the run's config.json beside them."""
    legacy = out_dir / LEGACY_STATE_FILE
    if (out_dir / CONFIG_JSON_FILE).is_file() and legacy.is_file() and not (out_dir / STATE_FILE).exists():
        for old, new in ((previous_path(legacy), out_dir / PREVIOUS_STATE_FILE), (legacy, out_dir / STATE_FILE)):
            if old.is_file():
                os.replace(old, new)
                log.info("renamed %s to %s (the federation state's name since)", old, new.name)


def _save_state(path: Path, resolved: dict, state: FederationState, marks: Marks) -> None:
    """Write federation_state.pt atomically; the one it replaces becomes federation_state.prev.pt (core.atomic)."""
    with atomic_path_keeping_previous(path) as tmp:
        torch.save({"format": CHECKPOINT_FORMAT, "resolved": resolved, "state": state.to_payload(), "logs": marks}, tmp)


def _read_checkpoint(path: Path) -> dict:
    """A federation checkpoint's payload, its parts checked; CrchflError if the file is missing, unreadable or malformed."""
    if not path.is_file():
        raise CrchflError(f"{path}: missing")
    payload = load_weights_only(path, "federation checkpoint", "delete the folder to start afresh")
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CrchflError(
            f"{path}: not a crchfl-sumo federation checkpoint of this version ({CHECKPOINT_FORMAT}); "
            "rerun into another --out"
        )
    resolved = payload.get("resolved")
    if not isinstance(resolved, dict) or not isinstance(resolved.get("config", {}), dict) or not _is_marks(payload.get("logs")):
        raise CrchflError(f"{path}: malformed federation checkpoint (resolved settings or log marks); delete the folder")
    check_payload(payload.get("state"), str(path))
    return payload


def _is_marks(marks: Any) -> bool:
    """Marks of the three logs: each a byte offset and a line count >= 0."""
    return isinstance(marks, dict) and set(marks) == set(LOGS) and all(
        isinstance(m, dict) and set(m) == {"offset", "lines"}
        and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in m.values())
        for m in marks.values()
    )


def _load_state(path: Path, resolved: dict, sizes, backend: BackendConfig) -> tuple[FederationState, Marks]:
    """The checkpointed state, its history read back from the logs (cut back to their marks), and the marks.

    A federation_state.pt that is missing, empty, truncated or malformed is refused
    with a warning and the previous step's federation_state.prev.pt is read instead;
    with neither readable the resume stops with both reasons.
    """
    payload, path = read_latest(path, _read_checkpoint, "checkpoint", "delete the folder to start afresh")
    stored = payload["resolved"]
    stored_config = resolved_as_today(stored.get("config", {}), f"{path}: config", backend)
    stored = {**stored, "config": stored_config}
    if stored != resolved:
        raise CrchflError(_precision_refusal(path, stored, resolved) or (
            f"{path}: written by a run with other settings or data (they differ in "
            f"{changed_keys_text(stored, resolved)}); resume with the original config (see config.json there) "
            "or choose another --out"
        ))
    marks = payload["logs"]
    return FederationState.from_payload(payload["state"], *restore_logs(path.parent, marks, sizes)), marks


def _precision_refusal(path: Path, stored: dict, resolved: dict) -> str | None:
    """The refusal of a run that differs from the stored one in its training precision alone ("auto"
    decided on another machine, or another precision asked for); None when something else differs."""
    stored_config = stored["config"]
    train = stored_config.get("train") if isinstance(stored_config, dict) else None
    here = resolved["config"]["train"]["precision"]
    if not isinstance(train, dict) or train.get("precision") == here:
        return None
    if {**stored, "config": {**stored_config, "train": {**train, "precision": here}}} != resolved:
        return None
    return (
        f"{path}: the run trained in {train.get('precision')}; with these settings this machine would continue "
        f"it in {here}. Set [train] precision = \"{train.get('precision')}\" to continue it, or choose another --out"
    )


def _write_outputs(
    out_dir: Path,
    config: RunConfig,
    setup: LoopInputs,
    state: FederationState,
    drive_settings: dict | None,
    handovers: int | None = None,
    baseline: Mapping[str, float] | None = None,
) -> None:
    """The files derived from the state, rewritten each step (each of a fixed size); the logs are apart.

    ``drive_settings``: the data set's camera and expert settings (Manifest.drive_settings), kept in the model files.
    """
    extra = {"scheme": config.federation.scheme, "cloud_round": state.cloud_rounds, **(drive_settings or {})}
    save_checkpoint(out_dir / FINAL_MODEL_FILE, config.model, state.cloud_model, extra)
    if state.best_model is not None:
        save_checkpoint(out_dir / BEST_MODEL_FILE, config.model, state.best_model, {**extra, "metrics": state.best})
    for gb, (line, model, passed) in budget_mark_results(config, setup, state).items():
        path = out_dir / mark_model_file(gb)
        # a passed mark's model never changes: written once (again if lost), and every mark at the end
        if model is not None and (state.done or (passed and not path.exists())):
            save_checkpoint(path, config.model, model, {**extra, "metrics": line})
    summary = summarize(config, setup, state, handovers, baseline)
    write_json(out_dir / SUMMARY_FILE, summary)


def run_command(
    config_path: str | Path,
    out_dir: str | Path,
    resume: bool = False,
    progress: Progress | None = None,
    backend: str | None = None,
    address: str | None = None,
    labeller_factory: LabellerFactory | None = None,
) -> dict:
    """What `crchfl-sumo run CONFIG --out DIR [--resume] [--backend B] [--address A]` does; returns the summary.

    CONFIG is a TOML file or the name of a built-in experiment (crchfl, hfl, sfl); ``labeller_factory``:
    what a config with [dagger] needs (run_federation_dir).
    """
    config_path = resolve_config_path(config_path)
    config = with_backend(load_run_config(config_path), backend, address)
    inputs = read_inputs(config)
    return run_federation_dir(
        config, inputs, out_dir, resume=resume, config_text=config_path.read_text(encoding="utf-8"), progress=progress,
        labeller_factory=labeller_factory,
    )
