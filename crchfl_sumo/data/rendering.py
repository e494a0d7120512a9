"""The data set's camera images: each shard's samples drawn frame by frame (stage 3 of data/generation.py).

All the samples of a frame are drawn in one call (``render_samples``), for as
many shards at a time as ``RENDER_GROUP_BYTES`` of images hold
(``render_groups``); each sample's cameras stand at its own pose, on the track
or perturbed (recovery.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from crchfl_sumo.data.recovery import camera_pose
from crchfl_sumo.data.settings import PlannedShard
from crchfl_sumo.sumo.frame import Frame
from crchfl_sumo.vision.raster import Renderer

RENDER_GROUP_BYTES = 1 << 30  # images of the shards rendered together, held until they are written


@dataclass(frozen=True)
class RenderJob:
    """One shard's samples to draw: its vehicle, the frame of each sample, each sample's perturbation."""

    vehicle: str
    frame_rows: Sequence[int]  # index into the run's frames, per sample
    perturbation: np.ndarray  # float32 [R, 3] (lateral_m, yaw_deg, forward_m)


def render_groups(shards: Sequence[PlannedShard], image_shape: tuple[int, ...], budget_bytes: int = RENDER_GROUP_BYTES):
    """Consecutive shards whose images fit ``budget_bytes`` together (at least one shard a group)."""
    sample_bytes = math.prod(image_shape)
    group: list[PlannedShard] = []
    for shard in shards:
        if group and (sum(s.samples for s in group) + shard.samples) * sample_bytes > budget_bytes:
            yield group
            group = []
        group.append(shard)
    if group:
        yield group


def render_samples(
    renderer: Renderer,
    frames: Sequence[Frame],
    jobs: Sequence[RenderJob],
    vehicles_per_call: int | None = None,
    on_rendered=None,
) -> list[np.ndarray]:
    """Every job's camera images, uint8 [R, 4, H, W, 3], drawn frame by frame.

    The samples that share a frame are rendered in one call, which shares the
    frame's set-up among them (``vehicles_per_call`` caps a call; 1 draws them
    one by one, as the benchmark's baseline). Each sample's cameras stand at
    its own perturbed pose while the others see the vehicle where it is, so
    the images are those of rendering each sample alone. ``on_rendered``
    hears the number of samples drawn so far after every frame.
    """
    images = [np.empty((len(job.frame_rows), *renderer.shape), np.uint8) for job in jobs]
    at_frame: dict[int, list[tuple[int, int]]] = {}  # frame -> [(job, sample)]
    for j, job in enumerate(jobs):
        for k, i in enumerate(job.frame_rows):
            at_frame.setdefault(int(i), []).append((j, k))
    drawn = 0
    for i in sorted(at_frame):
        frame, samples = frames[i], at_frame[i]
        step = vehicles_per_call or len(samples)
        for first in range(0, len(samples), step):
            chunk = samples[first : first + step]
            ids = [jobs[j].vehicle for j, _ in chunk]
            poses = np.array([camera_pose(frame, jobs[j].vehicle, *jobs[j].perturbation[k]) for j, k in chunk])
            for (j, k), sample_images in zip(chunk, renderer.render(frame, ids, poses)):
                images[j][k] = sample_images
        drawn += len(samples)
        if on_rendered is not None:
            on_rendered(drawn)
    return images
