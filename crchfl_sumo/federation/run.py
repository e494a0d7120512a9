"""`crchfl-sumo run CONFIG.toml --out DIR [--resume]`: a federation run from config to results folder.

DIR receives (every file written atomically):

  config.toml      the config file as given
  config.json      the resolved run: settings, the four hyper-parameters used, byte sizes
  checkpoint.pt    the whole FederationState after the latest step (what --resume reads)
  metrics.jsonl    one line per aggregation (stage I, each edge aggregation, each cloud aggregation)
  ledger.jsonl     every charged transfer (ledger.Ledger.save; first line: the sizes)
  stragglers.jsonl every vehicle that missed an aggregation or a download, and why
  best_model.pt    the best cloud model so far (checkpoint.save_checkpoint format)
  final_model.pt   the last cloud model
  summary.json     scheme, cloud_rounds, edge_aggregations, consumed_bytes, budget_bytes,
                   best/final accuracy and loss, sim_time_s, stop_reason, ...

A run killed at any moment and resumed with --resume continues from the
latest checkpoint and ends with the same files as an uninterrupted run with
the same seed: every step's randomness derives from the seed and the step
number, and the clock re-runs SUMO deterministically from the start.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Mapping

import numpy as np
import torch

from crchfl_sumo.accounting.ledger import Ledger, LedgerConfig, resolve_sizes
from crchfl_sumo.core.atomic import atomic_path, atomic_write_text
from crchfl_sumo.core.backend import BackendConfig, Executor
from crchfl_sumo.core.config import from_mapping, read_toml, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.progress import Progress, report
from crchfl_sumo.core.resources import experiments_dir
from crchfl_sumo.core.schemes import SCHEMES
from crchfl_sumo.data.online import OnlineConfig
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.loop import (
    Federation,
    FederationConfig,
    FederationState,
    Hyper,
    Setup,
    initial_state,
    sim_time_s,
)
from crchfl_sumo.learning.checkpoint import save_checkpoint
from crchfl_sumo.learning.model import ModelConfig, state_size_bytes
from crchfl_sumo.learning.trainers import RayTrainer, TorchTrainer
from crchfl_sumo.learning.training import TrainConfig
from crchfl_sumo.links.channel import ChannelConfig, WirelineConfig
from crchfl_sumo.links.clock import Clock, ScriptedClock
from crchfl_sumo.links.mobility import MacroLinkConfig, MobilityConfig
from crchfl_sumo.links.transfer import TransferConfig
from crchfl_sumo.planning.plan_command import calibrated
from crchfl_sumo.planning.problem import AllocationConfig, make_plan
from crchfl_sumo.planning.timing import measured_rates_bps, run_timing
from crchfl_sumo.sumo.scenario import SumoConfig

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "crchfl-sumo-federation/1"


@dataclass(frozen=True)
class ClockConfig:
    """Which clock the federation runs on (TOML ``[clock]``).

    kind: "sumo" (the scenario in SUMO with the link models: the product) or
        "constant" (no mobility: every vehicle always served by its home edge
        at ``constant_rate_bps``, the macro link at ``constant_macro_rate_bps``;
        for quick runs and checks).
    constant_step_s: sample spacing of the constant clock [s].
    """

    kind: Literal["sumo", "constant"] = "sumo"
    constant_rate_bps: float = 20e6
    constant_macro_rate_bps: float = 10e6
    constant_step_s: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("sumo", "constant"):
            raise CrchflError(f"clock.kind: {self.kind!r} is not one of 'sumo', 'constant'")
        for key in ("constant_rate_bps", "constant_macro_rate_bps", "constant_step_s"):
            if not getattr(self, key) > 0:
                raise CrchflError(f"clock.{key} must be > 0, got {getattr(self, key)}")


@dataclass(frozen=True)
class RunConfig:
    """A federation run (one TOML file; every table is the owning module's settings).

    scenario: built-in scenario name or .sumocfg path (the SUMO clock drives it).
    dataset: data set folder (``crchfl-sumo dataset``), relative to the
        current directory unless absolute; its train shards are the
        vehicles' data, its test shards the test set.
    data_mode: "fixed": each vehicle trains on its generated shard (the
        paper's setting); "online": vehicles also keep collecting samples as
        they drive (online.py; needs the SUMO clock).
    """

    scenario: str = "paper"
    dataset: str = "data/paper"
    data_mode: Literal["fixed", "online"] = "fixed"
    federation: FederationConfig = field(default_factory=FederationConfig)
    ledger: LedgerConfig = field(default_factory=LedgerConfig)
    allocation: AllocationConfig = field(default_factory=AllocationConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    clock: ClockConfig = field(default_factory=ClockConfig)
    channel: ChannelConfig = field(default_factory=ChannelConfig)
    mobility: MobilityConfig = field(default_factory=MobilityConfig)
    wireline: WirelineConfig = field(default_factory=WirelineConfig)
    sfl_link: MacroLinkConfig = field(default_factory=MacroLinkConfig)
    transfer: TransferConfig = field(default_factory=TransferConfig)
    online: OnlineConfig = field(default_factory=OnlineConfig)
    sumo: SumoConfig = field(default_factory=SumoConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)

    def __post_init__(self) -> None:
        if self.data_mode not in ("fixed", "online"):
            raise CrchflError(f"data_mode: {self.data_mode!r} is not one of 'fixed', 'online'")
        if self.data_mode == "online" and self.clock.kind != "sumo":
            raise CrchflError(
                "data_mode = 'online' collects samples from the SUMO run; set [clock] kind = \"sumo\" "
                "or data_mode = \"fixed\""
            )
        if self.clock.kind != "sumo" and self.sumo != SumoConfig():
            raise CrchflError("[sumo] changes the SUMO run; set [clock] kind = \"sumo\" or remove the [sumo] table")
        if self.backend.kind == "ray":
            if self.train.multi_vehicle == "vmap":
                raise CrchflError(
                    "train.multi_vehicle = 'vmap' trains every vehicle in one process; the ray backend trains each "
                    "vehicle as its own task: set multi_vehicle = \"sequential\" or backend kind \"local\""
                )
            if self.train.device == "cuda":
                raise CrchflError(
                    "train.device = 'cuda': Ray tasks ask for CPUs only (GPU tasks are not built); "
                    "use device \"cpu\" or \"auto\", or backend kind \"local\""
                )


def load_run_config(path: str | Path) -> RunConfig:
    return from_mapping(RunConfig, read_toml(path), where=str(path))


def make_trainer(config: RunConfig, inputs: Inputs, executor: Executor):
    """The run's Trainer: in this process (local backend) or as tasks (ray)."""
    args = (config.model, config.train, inputs.test, config.federation.seed)
    return RayTrainer(*args, executor) if executor.is_ray else TorchTrainer(*args)


# ------------------------------------------------------------------ inputs


@dataclass(frozen=True)
class Inputs:
    """What a run reads before it starts: the vehicles' data, the test set, edges, sizes."""

    vehicles: tuple[str, ...]
    samples: Mapping[str, Samples]
    test: Samples
    edges: tuple[str, ...]
    home_site: Mapping[str, int]
    measured_sample_bytes: int | None
    root: Path | None = None  # the data set folder (the online mode reads its camera settings)


def read_inputs(config: RunConfig) -> Inputs:
    """Load the data set (train shards per vehicle, test shards) and map vehicles to edge sites."""
    from crchfl_sumo.data.dataset import load_samples, load_vehicle_samples, measured_sample_bytes
    from crchfl_sumo.data.shards import read_manifest

    root = Path(config.dataset)
    manifest = read_manifest(root)
    if (manifest.image_height, manifest.image_width) != (config.model.image_height, config.model.image_width):
        raise CrchflError(
            f"model.image_height/image_width: {config.model.image_height} x {config.model.image_width} does not "
            f"match the data set's {manifest.image_height} x {manifest.image_width} ({root}); "
            "set them to the data's size"
        )
    samples = load_vehicle_samples(root, "train")
    if not samples:
        raise CrchflError(f"{root}: the data set has no train shards; generate it with `crchfl-sumo dataset`")
    test = load_samples(root, "test")
    if len(test) == 0:
        raise CrchflError(f"{root}: the data set has no test shards; the run evaluates on them")
    shards = {s.vehicle: s for s in manifest.select("train")}
    vehicles = tuple(shards)
    if config.clock.kind == "sumo":
        from crchfl_sumo.sumo.scenario import configured_scenario

        scenario = configured_scenario(config.scenario, config.sumo, config.mobility.coverage_radius_m)
        edges = tuple(site.name for site in scenario.edge_sites)
        named = {v for town in scenario.towns for v in town.data_vehicles}
        unknown = sorted(set(vehicles) - named)
        if named and unknown:
            raise CrchflError(
                f"{root}: vehicle(s) {', '.join(unknown)} are not data vehicles of scenario {config.scenario!r} "
                f"({', '.join(sorted(named))}); use the scenario the data set was generated with"
            )
    else:
        edges = tuple(dict.fromkeys(s.edge for s in shards.values()))
    home = {}
    if config.clock.kind == "sumo" and config.sumo.replaces_sites:
        home = nearest_sites(root, manifest, scenario.edge_sites)
    for v, shard in shards.items():
        if v in home:
            continue
        if shard.edge not in edges:
            raise CrchflError(
                f"{root}: vehicle {v} was recorded at edge {shard.edge!r}, which scenario {config.scenario!r} "
                f"does not have ({', '.join(edges)}); use the scenario the data set was generated with"
            )
        home[v] = edges.index(shard.edge)
    measured = measured_sample_bytes(manifest) if config.ledger.sample_size == "measured" else None
    return Inputs(vehicles, samples, test, edges, home, measured, root)


def nearest_sites(root: Path, manifest, sites) -> dict[str, int]:
    """Each vehicle's home: the site nearest its first recorded sample (the run's sites are not the data set's)."""
    from crchfl_sumo.data.shards import read_shard

    xy = np.array([(site.x_m, site.y_m) for site in sites])
    home = {}
    for shard in manifest.select("train"):
        data = read_shard(root, shard, verify=False, images=False)
        first = int(np.argmin(data.t_s))
        home[shard.vehicle] = int(np.argmin(np.hypot(xy[:, 0] - data.x_m[first], xy[:, 1] - data.y_m[first])))
    return home


def resolve_hyper(config: RunConfig, inputs: Inputs, model_bytes: int, clock: Clock) -> tuple[Hyper, dict | None]:
    """The four hyper-parameters: the config's, or (CRCHFL, use_plan) the optimizer's for this run.

    The plan takes the run's topology, its sample counts, and its timing: the
    loop's compute model and the wireless rate measured on ``clock`` (plan_timing.py).
    """
    fed = config.federation
    if not fed.use_plan:
        return Hyper(fed.pretrain_batch, fed.edge_interval, fed.cloud_interval, fed.cloud_rounds), None
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
        allocation, config.ledger, real_model_bytes=model_bytes, measured_sample_bytes=inputs.measured_sample_bytes
    )
    # The solver's timings differ from run to run; the rest of the plan is what the run depends on.
    fixed = {k: v for k, v in plan.to_dict().items() if k not in ("compile_s", "solve_s", "search_s")}
    return Hyper(plan.pretrain_batch, plan.edge_interval, plan.cloud_interval, plan.cloud_rounds), fixed


def make_clock(config: RunConfig, inputs: Inputs):
    """The clock of ``config.clock`` (a context manager for SUMO; a plain object otherwise)."""
    if config.clock.kind == "constant":
        clock = ScriptedClock.constant(
            inputs.home_site,
            config.clock.constant_rate_bps,
            config.clock.constant_step_s,
            config.clock.constant_macro_rate_bps,
        )
        return _NoContext(clock)
    from crchfl_sumo.links.clock import SumoClock
    from crchfl_sumo.sumo.scenario import configured_scenario

    scenario = configured_scenario(config.scenario, config.sumo, config.mobility.coverage_radius_m)
    kinds = ("edge",) if config.federation.hierarchical else ("macro",)
    collector = online_collector(config, inputs, scenario) if config.data_mode == "online" else None
    return SumoClock(
        scenario,
        inputs.vehicles,
        config.federation.seed,
        kinds,
        config.channel,
        config.mobility,
        config.sfl_link,
        collector,
    )


def online_collector(config: RunConfig, inputs: Inputs, scenario):
    """The online mode's collector, rendering and labelling exactly as the data set was made."""
    from crchfl_sumo.data.expert import ExpertConfig
    from crchfl_sumo.data.online import OnlineCollector
    from crchfl_sumo.data.shards import read_manifest, read_shard
    from crchfl_sumo.vision.raster import RasterConfig
    from crchfl_sumo.vision.world import WorldConfig

    manifest = read_manifest(inputs.root)
    where = f"{inputs.root}/manifest.json"
    raster = from_mapping(RasterConfig, manifest.camera.get("raster", {}), f"{where}: camera.raster")
    world = from_mapping(WorldConfig, manifest.camera.get("world", {}), f"{where}: camera.world")
    expert = from_mapping(ExpertConfig, manifest.labels.get("expert", {}), f"{where}: labels.expert")
    if (raster.camera.height_px, raster.camera.width_px) != (manifest.image_height, manifest.image_width):
        raise CrchflError(f"{where}: camera settings do not match the image size; regenerate the data set")
    # each vehicle goes on collecting after the last sample of its shard
    last_s = {
        s.vehicle: float(np.max(read_shard(inputs.root, s, verify=False, images=False).t_s, initial=-np.inf))
        for s in manifest.select("train")
    }
    return OnlineCollector(
        scenario.net_path,
        inputs.vehicles,
        last_s,
        manifest.sample_period_s,
        scenario.step_length_s,
        raster,
        world,
        expert,
        config.online,
    )


class _NoContext:
    def __init__(self, clock: Clock) -> None:
        self.clock = clock

    def __enter__(self) -> Clock:
        return self.clock

    def __exit__(self, *exc_info) -> None:
        return None


# ------------------------------------------------------------------ the run


def run_federation_dir(
    config: RunConfig,
    inputs: Inputs,
    out_dir: str | Path,
    *,
    resume: bool = False,
    config_text: str | None = None,
    trainer=None,
    clock_factory: Callable[[], Any] | None = None,
    progress: Progress | None = None,
    after_checkpoint: Callable[[FederationState], None] | None = None,
) -> dict:
    """Run (or resume) the federation of ``config`` on ``inputs`` into ``out_dir``; returns the summary.

    ``trainer`` defaults to the one of ``config.backend`` (make_trainer),
    ``clock_factory`` to ``make_clock`` (both injectable for tests).
    ``after_checkpoint`` is called right after each checkpoint is written,
    before the other files are (tests kill a run there).
    """
    out_dir = Path(out_dir)
    checkpoint_path = out_dir / "checkpoint.pt"
    if checkpoint_path.exists() and not resume:
        raise CrchflError(f"{out_dir} already holds a run; pass --resume to continue it or choose another --out")
    if trainer is None:
        with Executor(config.backend) as executor:
            return run_federation_dir(
                config,
                inputs,
                out_dir,
                resume=resume,
                config_text=config_text,
                trainer=make_trainer(config, inputs, executor),
                clock_factory=clock_factory,
                progress=progress,
                after_checkpoint=after_checkpoint,
            )
    out_dir.mkdir(parents=True, exist_ok=True)
    fed = config.federation
    first = trainer.initial_state()
    sizes = resolve_sizes(config.ledger, state_size_bytes(first), inputs.measured_sample_bytes)
    with (clock_factory or (lambda: make_clock(config, inputs)))() as clock:
        hyper, plan = resolve_hyper(config, inputs, state_size_bytes(first), clock)
        resolved = {
            "config": resolved_config(config),
            "hyper": dataclasses.asdict(hyper),
            "plan": plan,
            "sizes": dataclasses.asdict(sizes),
            "vehicles": list(inputs.vehicles),
            "edges": list(inputs.edges),
        }
        resolved = json.loads(json.dumps(resolved))  # inf and tuples as JSON reads them back
        setup = Setup(
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
        )
        state = None
        if resume and checkpoint_path.exists():
            state = _load_state(checkpoint_path, resolved)
            if state.done:  # finished before: only the derived files may be missing
                _write_outputs(out_dir, config, setup, state, _handovers(clock, state))
                return summarize(config, setup, state, _handovers(clock, state))
            log.info("resuming %s at step %d (cloud round %d)", out_dir, state.steps, state.cloud_rounds)
        else:
            if config_text is not None:
                atomic_write_text(out_dir / "config.toml", config_text)
            atomic_write_text(out_dir / "config.json", json.dumps(resolved, indent=2) + "\n")
        if state is None:
            state = initial_state(setup, trainer, clock.start_s)
        data = _online_data(clock, inputs) if config.data_mode == "online" else None
        federation = Federation(setup, clock, trainer, data)

        def on_step(new: FederationState) -> None:
            _save_state(checkpoint_path, resolved, new)
            if after_checkpoint is not None:
                after_checkpoint(new)
            _write_outputs(out_dir, config, setup, new, _handovers(clock, new))
            if progress is not None:  # a step's postfix costs a pass over the records
                report(progress, "step", new.steps, None, **progress_postfix(progress_info(new, sizes.budget_bytes, hyper)))

        state = federation.run(state, on_step)
        return summarize(config, setup, state, _handovers(clock, state))


def resolved_config(config: RunConfig) -> dict:
    """The settings a run's results depend on: all but [backend] (where it runs), and [sumo] only when set."""
    mapping = to_mapping(config)
    del mapping["backend"]
    if config.sumo == SumoConfig():
        del mapping["sumo"]  # folders of runs made before [sumo] existed still resume
    return mapping


def _handovers(clock, state: FederationState) -> int | None:
    """The clock's handovers up to the run's latest simulated time (None for a clock that does not count them)."""
    count = getattr(clock, "handovers", None)
    return None if count is None else count(sim_time_s(state))


def _online_data(clock, inputs: Inputs) -> Callable[[str, float], Samples]:
    """A vehicle's data at t_s in the online mode: its shard and what it had collected by then."""

    def data(vehicle: str, t_s: float) -> Samples:
        extra = clock.collected(vehicle, t_s)
        return inputs.samples[vehicle] if extra is None else Samples.concat([inputs.samples[vehicle], extra])

    return data


def progress_info(state: FederationState, budget_bytes: int, hyper: Hyper) -> dict:
    """What a progress bar shows: round, bytes used / budget, latest loss and accuracy."""
    ledger_bytes = sum(r.size_bytes for r in state.records)
    last = next((m for m in reversed(state.metrics) if m["loss"] is not None), None)
    return {
        "cloud_round": state.cloud_rounds,
        "cloud_rounds": hyper.cloud_rounds or None,
        "edge_aggregations": state.edge_aggregations,
        "consumed_bytes": ledger_bytes,
        "budget_bytes": budget_bytes,
        "loss": None if last is None else last["loss"],
        "accuracy": None if last is None else last["accuracy"],
        "sim_time_s": sim_time_s(state),
        "done": state.done,
    }


def progress_postfix(info: dict) -> dict[str, str]:
    """A progress bar's postfix for ``progress_info``: round, GB used / budget, loss, accuracy."""
    rounds = info["cloud_rounds"]
    gib = 1024**3
    return {
        "round": f"{info['cloud_round']}/{rounds}" if rounds else str(info["cloud_round"]),
        "GB": f"{info['consumed_bytes'] / gib:.2f}/{info['budget_bytes'] / gib:.2f}",
        "loss": "-" if info["loss"] is None else f"{info['loss']:.4f}",
        "acc": "-" if info["accuracy"] is None else f"{info['accuracy']:.3f}",
    }


def summarize(config: RunConfig, setup: Setup, state: FederationState, handovers: int | None = None) -> dict:
    ledger = Ledger(setup.sizes, state.records)
    cloud_lines = [m for m in state.metrics if m["stage"] in ("I", "III")]
    final = cloud_lines[-1] if cloud_lines else None
    best = state.best
    return {
        "scheme": config.federation.scheme,
        "rule": setup.rule,
        "cloud_rounds": state.cloud_rounds,
        "edge_aggregations": state.edge_aggregations,
        "consumed_bytes": ledger.spent_bytes,
        "budget_bytes": ledger.budget_bytes,
        "bytes_by_link": ledger.totals("link"),
        "bytes_by_stage": ledger.totals("stage"),
        "model_bytes": setup.sizes.model_bytes,
        "sample_bytes": setup.sizes.sample_bytes,
        "best_accuracy": None if best is None else best["accuracy"],
        "best_loss": None if best is None else best["loss"],
        "best_cloud_round": None if best is None else best["cloud_round"],
        "final_accuracy": None if final is None else final["accuracy"],
        "final_loss": None if final is None else final["loss"],
        "sim_time_s": sim_time_s(state),
        "stragglers": len(state.stragglers),
        "handovers": handovers,
        "stop_reason": state.stop_reason,
        "hyper": dataclasses.asdict(setup.hyper),
        "vehicles": list(setup.vehicles),
        "samples_per_vehicle": {v: setup.count(v) for v in setup.vehicles},
    }


def _save_state(path: Path, resolved: dict, state: FederationState) -> None:
    with atomic_path(path) as tmp:
        torch.save({"format": CHECKPOINT_FORMAT, "resolved": resolved, "state": state.to_payload()}, tmp)


def _load_state(path: Path, resolved: dict) -> FederationState:
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt files
        raise CrchflError(
            f"{path}: not a readable federation checkpoint ({exc}); delete the folder to start afresh"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CrchflError(f"{path}: not a crchfl-sumo federation checkpoint ({CHECKPOINT_FORMAT})")
    if payload["resolved"] != resolved:
        raise CrchflError(
            f"{path}: written by a run with other settings or data; resume with the original config "
            "(see config.json there) or choose another --out"
        )
    return FederationState.from_payload(payload["state"])


def _write_outputs(
    out_dir: Path, config: RunConfig, setup: Setup, state: FederationState, handovers: int | None = None
) -> None:
    atomic_write_text(out_dir / "metrics.jsonl", "".join(json.dumps(m) + "\n" for m in state.metrics))
    atomic_write_text(out_dir / "stragglers.jsonl", "".join(json.dumps(s) + "\n" for s in state.stragglers))
    Ledger(setup.sizes, state.records).save(out_dir / "ledger.jsonl")
    extra = {"scheme": config.federation.scheme, "cloud_round": state.cloud_rounds}
    save_checkpoint(out_dir / "final_model.pt", config.model, state.cloud_model, extra)
    if state.best_model is not None:
        save_checkpoint(out_dir / "best_model.pt", config.model, state.best_model, {**extra, "metrics": state.best})
    summary = summarize(config, setup, state, handovers)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")


def run_command(
    config_path: str | Path,
    out_dir: str | Path,
    resume: bool = False,
    progress: Progress | None = None,
    backend: str | None = None,
    address: str | None = None,
) -> dict:
    """What `crchfl-sumo run CONFIG --out DIR [--resume] [--backend B] [--address A]` does; returns the summary.

    CONFIG is a TOML file or the name of a built-in experiment (crchfl, hfl, sfl).
    """
    config_path = resolve_config_path(config_path)
    config = with_backend(load_run_config(config_path), backend, address)
    inputs = read_inputs(config)
    return run_federation_dir(
        config, inputs, out_dir, resume=resume, config_text=config_path.read_text(encoding="utf-8"), progress=progress
    )


def resolve_config_path(config_path: str | Path) -> Path:
    """A run config file, or the file of a built-in experiment name."""
    config_path = Path(config_path)
    builtins = builtin_experiments()
    if not config_path.is_file() and str(config_path) in builtins:
        return builtins[str(config_path)]
    return config_path


def with_backend(config: RunConfig, kind: str | None, address: str | None) -> RunConfig:
    """``config`` with the command line's --backend / --address in place of its [backend] table."""
    if kind is None and address is None:
        return config
    kind = kind or config.backend.kind
    if address is not None and kind != "ray":
        raise CrchflError(f"--address {address}: joining a cluster needs --backend ray")
    if kind == "local":
        address = ""  # the config's cluster address means nothing without Ray
    backend = dataclasses.replace(config.backend, kind=kind, address=config.backend.address if address is None else address)
    return dataclasses.replace(config, backend=backend)




def builtin_experiments() -> dict[str, Path]:
    """The built-in run configs of the paper's three schemes (scenarios/experiments/NAME.toml) by name."""
    folder = experiments_dir()
    return {name: folder / f"{name}.toml" for name in SCHEMES}
