"""A federation run's settings: one TOML file, one table per owning module's dataclass.

``RunConfig`` is what `crchfl-sumo run`, `sweep` and `reproduce` read; this
module also finds the built-in run configs and lays the command line's
--backend over a config.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

from crchfl_sumo.accounting.energy import EnergyConfig
from crchfl_sumo.accounting.ledger import LedgerConfig
from crchfl_sumo.core.backend import BackendConfig
from crchfl_sumo.core.config import from_mapping, read_toml, to_mapping
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_RATE_BPS, MAX_SIMULATED_S, check_range
from crchfl_sumo.core.resources import experiments_dir
from crchfl_sumo.core.schemes import SCHEMES
from crchfl_sumo.data.settings import OnlineConfig
from crchfl_sumo.federation.settings import FederationConfig, VehicleDaggerConfig
from crchfl_sumo.learning.settings import ModelConfig, TrainConfig
from crchfl_sumo.links.channel import ChannelConfig, WirelineConfig
from crchfl_sumo.links.fleet import FleetConfig
from crchfl_sumo.links.macro import MacroLinkConfig
from crchfl_sumo.links.mobility import MobilityConfig
from crchfl_sumo.links.transfer import TransferConfig
from crchfl_sumo.planning.settings import AllocationConfig
from crchfl_sumo.sumo.scenario import SumoConfig


@dataclass(frozen=True)
class ClockConfig(FleetConfig):
    """Which clock the federation runs on (TOML ``[clock]``).

    kind: "sumo" (the scenario in SUMO with the link models: the product) or
        "constant" (no mobility: every vehicle always served by its home edge
        at ``constant_rate_bps``, the macro link at ``constant_macro_rate_bps``;
        for quick runs and checks).
    constant_step_s: sample spacing of the constant clock [s].
    compute_profile, compute_sigma, compute_tiers: each vehicle's compute speed, a factor on
        federation.compute_s_per_sample: "equal" (the paper), "lognormal" or "tiers".
    availability, mean_on_s, mean_off_s, availability_trace: when each vehicle is on (it neither
        trains nor transmits while off): "always" (the paper), "onoff" (exponential on and off periods
        of those means) or "trace" (a CSV file of off periods).
    These last seven are links.fleet.FleetConfig's, which this table extends.
    """

    kind: Literal["sumo", "constant"] = "sumo"
    constant_rate_bps: float = 20e6
    constant_macro_rate_bps: float = 10e6
    constant_step_s: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("sumo", "constant"):
            raise CrchflError(f"clock.kind: {self.kind!r} is not one of 'sumo', 'constant'")
        for key in ("constant_rate_bps", "constant_macro_rate_bps"):
            check_range(getattr(self, key), f"clock.{key}", 0, MAX_RATE_BPS, "bit/s", lo_open=True)
        check_range(self.constant_step_s, "clock.constant_step_s", 0, MAX_SIMULATED_S, "simulated seconds",
                    lo_open=True)
        super().__post_init__()  # the devices' settings


@dataclass(frozen=True)
class RunConfig:
    """A federation run (one TOML file; every table is the owning module's settings).

    scenario: built-in scenario name or .sumocfg path (the SUMO clock drives it).
    dataset: data set folder (``crchfl-sumo dataset``), relative to the
        current directory unless absolute; its train shards are the
        vehicles' data, its test shards the test set.
    data_mode: "fixed": each vehicle trains on its generated shard (the
        paper's setting); "online": vehicles also keep collecting samples as
        they drive (data/online.py; needs the SUMO clock).
    dagger: the vehicles' own DAgger ([dagger], VehicleDaggerConfig; off by default): the run
        needs a labeller (driving/vehicle_dagger.py), which `crchfl-sumo run` and `reproduce` give it.
    energy: the power figures summary.json's ``energy_j`` is computed with (accounting/energy.py).
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
    dagger: VehicleDaggerConfig = field(default_factory=VehicleDaggerConfig)
    energy: EnergyConfig = field(default_factory=EnergyConfig)

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
        if self.dagger.enabled and self.federation.aggregation == "async":
            raise CrchflError("[dagger] labels at cloud rounds of synchronous edges; with federation.aggregation = "
                              "\"async\" remove the [dagger] table (or set every_cloud_rounds = 0)")
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


def resolved_config(config: RunConfig) -> dict:
    """The settings a run's results depend on: all but [backend] (where it runs), and [sumo] only when set;
    train.multi_vehicle and train.precision as the run trains with here ("auto" decided), so that a run
    started in bfloat16 is not continued in float32 on a machine where "auto" means float32."""
    mapping = to_mapping(config)
    mapping["train"] = to_mapping(resolved_train(config))
    del mapping["backend"]
    if config.sumo == SumoConfig():
        del mapping["sumo"]  # folders of runs made before [sumo] existed still resume
    if not config.dagger.enabled:
        del mapping["dagger"]  # nor do runs without it depend on its other settings
    return mapping


def resolved_train(config: RunConfig) -> TrainConfig:
    """[train] as the run trains: multi_vehicle and precision decided here; config.json records it."""
    return dataclasses.replace(config.train, precision=training_precision(config), multi_vehicle=multi_vehicle_method(config))


def multi_vehicle_method(config: RunConfig) -> str:
    """"sequential" or "vmap": how the run trains its vehicles on this machine; "auto" is vmap on a GPU
    only (learning.devices.resolved_multi_vehicle)."""
    from crchfl_sumo.learning.devices import resolved_multi_vehicle

    if config.train.multi_vehicle != "auto":
        return config.train.multi_vehicle
    return resolved_multi_vehicle(config.train, config.model, _training_device(config).type)


def training_precision(config: RunConfig) -> str:
    """"fp32" or "bf16": the arithmetic the run's vehicles train in on this machine; "auto" is bf16 where
    the training device multiplies bfloat16 in hardware (learning.devices.resolved_precision)."""
    from crchfl_sumo.learning.devices import resolved_precision

    if config.train.precision != "auto":
        return config.train.precision
    return resolved_precision(config.train, _training_device(config))


def _training_device(config: RunConfig):
    """The torch device the run's vehicles train on ("auto" decided): Ray tasks train on CPUs."""
    import torch

    from crchfl_sumo.learning.devices import resolve_device

    name = "cpu" if config.backend.kind == "ray" else config.train.device
    return resolve_device(name) if name == "auto" else torch.device(name)


def resolved_as_today(stored: Mapping[str, Any], where: str, backend: BackendConfig = BackendConfig()) -> dict:
    """A stored run's resolved settings read back with today's defaults: a key added since the
    run was written takes its default, so the folder resumes when nothing else differs. Settings
    today's config cannot read come back unchanged (they then differ, and resuming is refused).

    ``backend``: where the run goes on (the stored settings leave it out), which decides where a
    setting stored as "auto" by an earlier version is decided: Ray tasks train on CPUs."""
    try:
        config = from_mapping(RunConfig, {**stored, "backend": to_mapping(backend)}, where)
    except CrchflError:
        return dict(stored)
    return json.loads(json.dumps(resolved_config(config)))  # inf and tuples as JSON reads them back


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
