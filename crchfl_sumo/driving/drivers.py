"""Drivers: the one path from a checkpoint, or "reference", to a policy with its cameras and its expert.

`drive`, `drive-bench`, `dagger` and the vehicles' DAgger in a run all drive through these:

    driver = driver_for("runs/crchfl/best_model.pt")      # or driver_for("reference")
    policy = driver.policy(route, net)                    # ModelPolicy or RoutePolicy
    renderer = driver.renderer(net_path)                  # the cameras as the model's data drew them
    expert = driver.expert()                              # the steering rack its labels were made with

A ModelDriver travels to a worker process as its path alone; the worker loads the model once.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.schemes import REFERENCE
from crchfl_sumo.data.expert import ExpertConfig, expert_from_labels
from crchfl_sumo.data.route_commands import RouteCommands
from crchfl_sumo.driving.policies import ModelPolicy, Policy, RoutePolicy
from crchfl_sumo.learning.settings import DEFAULT_BRAKE_GAIN, DEFAULT_STEER_DECODING
from crchfl_sumo.sumo.route import RouteGeometry
from crchfl_sumo.sumo.turns import choice_junctions
from crchfl_sumo.vision.raster import Renderer, camera_settings
from crchfl_sumo.vision.world import build_world


@dataclass
class ReferenceDriver:
    """The scripted RoutePolicy: knows the route, reads no images."""

    label: str = REFERENCE
    renders: bool = False

    def policy(self, route: RouteGeometry, net) -> Policy:
        return RoutePolicy(route)

    def expert(self) -> ExpertConfig:
        return ExpertConfig()


@dataclass
class ModelDriver:
    """A trained checkpoint driving through ModelPolicy; the model is loaded once per process."""

    path: str
    label: str = ""
    steer_decoding: str = DEFAULT_STEER_DECODING
    brake_gain: float = DEFAULT_BRAKE_GAIN
    renders: bool = True
    _model: Any = field(default=None, repr=False, compare=False)
    _extra: dict = field(default_factory=dict, repr=False, compare=False)  # the checkpoint's, read with the model

    def __getstate__(self) -> dict:  # workers load the model themselves: only the path travels
        return {**self.__dict__, "_model": None, "_extra": {}}

    def model(self):
        if self._model is None:
            from crchfl_sumo.learning.checkpoint import checkpoint_model, load_checkpoint

            checkpoint = load_checkpoint(self.path)
            self._model, self._extra = checkpoint_model(checkpoint, self.path), checkpoint.extra
        return self._model

    def renderer(self, net_path: str):
        """The cameras as the model's training data drew them (model_renderer)."""
        return model_renderer(net_path, self.model().config, self._extra, self.path)

    def expert(self) -> ExpertConfig:
        """The steering rack and pedal mapping the model's data were labelled with (model_expert)."""
        self.model()
        return model_expert(self._extra, self.path)

    def policy(self, route: RouteGeometry, net) -> Policy:
        # The commands as the training data was labelled: at the junctions of the net with a choice.
        return ModelPolicy(
            self.model(), RouteCommands(route, choice_junctions(net)),
            steer_decoding=self.steer_decoding, brake_gain=self.brake_gain, source=self.path,
        )


def driver_for(
    model: str | Path | None, steer_decoding: str = DEFAULT_STEER_DECODING, brake_gain: float = DEFAULT_BRAKE_GAIN
) -> ReferenceDriver | ModelDriver:
    """The driver of MODEL|reference; a model path must name a checkpoint file."""
    if model is None or str(model) == REFERENCE:
        return ReferenceDriver()
    path = Path(model)
    if not path.is_file():
        raise CrchflError(f"MODEL: no checkpoint at {path}; give a checkpoint.pt written by crchfl-sumo, or 'reference'")
    driver = ModelDriver(str(path), label=path.stem, steer_decoding=steer_decoding, brake_gain=brake_gain)
    driver.model()  # a file that is not a checkpoint fails here, before any episode runs
    return driver


def model_renderer(net_path: str | Path, model_config, extra: dict[str, Any], where: str) -> Renderer:
    """A model's cameras as its training data drew them: the data set's raster and world settings
    (a checkpoint's extra "camera", copied from the manifest), or today's defaults at the model's image
    size for a checkpoint written without them (every head lit, as then)."""
    size = {"height_px": model_config.image_height, "width_px": model_config.image_width}
    camera = extra.get("camera") or {"raster": {"camera": size}}  # written without it: read as an old block
    raster, world = camera_settings(camera, f"{where}: extra.camera")
    return Renderer(build_world(net_path, world), raster)


def model_expert(extra: dict[str, Any], where: str) -> ExpertConfig:
    """The expert settings a model's data set was labelled with (a checkpoint's extra "expert", copied from
    the manifest): the drive's dynamics steer through the same rack. A checkpoint written without them
    was labelled with the linear rack of the time (data.expert.LINEAR_RACK)."""
    return expert_from_labels(extra.get("expert", {}), f"{where}: extra.expert")


@contextlib.contextmanager
def single_torch_thread(active: bool):
    """One torch thread while a model drives: one sample a step gains nothing from more, and on a
    busy machine the threads' spinning made a step 100 times slower (docs/drive.md)."""
    if not active:
        yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
