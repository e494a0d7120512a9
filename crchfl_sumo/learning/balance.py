"""Balanced learning: how an epoch's batches are drawn, and how the steer loss weighs the classes.

86 % of the steer labels are "straight", so plain training can sit on the
majority class. Two levers, each computed from the samples being trained on
(for a vehicle: its own data):

Sampling (``TrainConfig.sampling``), one epoch = N draws for N samples:

- ``uniform``: a fresh permutation cut into batches (every sample once);
- ``class_balanced``: N draws with replacement, sample i drawn with
  probability proportional to 1 / (samples of its steer class): every class
  present is drawn equally often on average;
- ``command_balanced``: the same with the route command in place of the class;
- ``pedal_balanced``: the same with the pedal state (``pedal_states``: holding
  still, throttle, cruising, braking) in place of the class. Standing at red
  and cruising make most samples; pulling away and braking are rare.

Signal emphasis (``TrainConfig.red_weight``, ``red_window_m``): on top of any
sampling, a sample whose next signal shows red or yellow within the window
(approaching it, or standing at it) is drawn ``red_weight`` times as often.
Such samples are few (they decide the red-light runs of docs/measurements.md);
1 leaves the draws exactly as without it. Yield emphasis (``yield_weight``,
``yield_window_m``) does the same for a sample whose nearest junction foe to
yield to is within the window of the conflict point (the unprotected left turns
of the traffic collisions); a sample both near red and near a foe gets both.

Loss weighting (``TrainConfig.class_weighting``), per steer class c with n_c of N samples
and K classes present:

- ``none``: plain cross-entropy;
- ``inverse``: w_c = N / (K n_c);
- ``sqrt_inverse``: w_c proportional to 1 / sqrt(n_c), scaled so that sum_c n_c w_c = N.

Either way a batch's steer loss is sum_i w_{y_i} CE_i / sum_i w_{y_i} (torch's
weighted cross-entropy). Draws use the caller's torch.Generator only, so the
same seed gives the same batches.
"""

from __future__ import annotations

import torch

from crchfl_sumo.data.expert import ExpertConfig
from crchfl_sumo.data.labels import NUM_COMMANDS, NUM_STEER_CLASSES, SIGNAL_RED, SIGNAL_YELLOW
from crchfl_sumo.data.samples import Samples


def inverse_frequency(codes: torch.Tensor, num_codes: int) -> torch.Tensor:
    """float64 [len(codes)]: 1 / (how often each sample's code occurs)."""
    counts = torch.bincount(codes.cpu(), minlength=num_codes).to(torch.float64)
    return 1.0 / counts[codes.cpu()]


HOLD, THROTTLE, CRUISE, BRAKE = range(4)  # pedal states
NUM_PEDAL_STATES = 4
PRESSED_MIN = 0.5  # a throttle (or brake) above this is pulling away (or braking); below it, cruising


def pedal_states(
    actions: torch.Tensor, speed_mps: torch.Tensor, stop_speed_mps: float = ExpertConfig.stop_speed_mps
) -> torch.Tensor:
    """int64 [N]: each sample's pedal state from its label (actions [N, 3]) and speed [N].

    HOLD: standing (speed below ``stop_speed_mps``, the expert's) without throttle; THROTTLE:
    throttle above PRESSED_MIN; BRAKE: moving with brake above it; CRUISE: the rest.
    """
    throttle, brake = actions[:, 0], actions[:, 2]
    states = torch.full((len(actions),), CRUISE, dtype=torch.int64, device=actions.device)
    states[(speed_mps >= stop_speed_mps) & (brake > PRESSED_MIN)] = BRAKE
    states[(speed_mps < stop_speed_mps) & (throttle <= PRESSED_MIN)] = HOLD
    states[throttle > PRESSED_MIN] = THROTTLE
    return states


def near_red(samples: Samples, window_m: float) -> torch.Tensor:
    """bool [N] (CPU): the next signal shows red or yellow and its stop line lies within ``window_m``."""
    state = samples.signal_state.cpu()
    red = (state == SIGNAL_RED) | (state == SIGNAL_YELLOW)
    return red & (samples.signal_distance_m.cpu() <= window_m)


def near_yield(samples: Samples, window_m: float) -> torch.Tensor:
    """bool [N] (CPU): a junction foe the car must yield to is within ``window_m`` of the conflict point."""
    return samples.yield_gap_m.cpu() <= window_m


def epoch_batches(
    samples: Samples, batch_size: int, sampling: str, generator: torch.Generator,
    red_weight: float = 1.0, red_window_m: float = 30.0, yield_weight: float = 1.0, yield_window_m: float = 30.0,
) -> list[torch.Tensor]:
    """Index batches (CPU int64) of one epoch by ``sampling`` and the signal emphasis; the last batch
    may be shorter."""
    n = len(samples)
    if n == 0:
        return []
    if sampling == "uniform" and red_weight == 1.0 and yield_weight == 1.0:
        order = torch.randperm(n, generator=generator)
    else:
        if sampling == "uniform":
            weights = torch.ones(n, dtype=torch.float64)
        else:
            codes, num_codes = {
                "class_balanced": lambda: (samples.steer_class, NUM_STEER_CLASSES),
                "command_balanced": lambda: (samples.command, NUM_COMMANDS),
                "pedal_balanced": lambda: (pedal_states(samples.actions, samples.speed_mps), NUM_PEDAL_STATES),
            }[sampling]()
            weights = inverse_frequency(codes, num_codes)
        if red_weight != 1.0:
            weights = torch.where(near_red(samples, red_window_m), weights * red_weight, weights)
        if yield_weight != 1.0:
            weights = torch.where(near_yield(samples, yield_window_m), weights * yield_weight, weights)
        order = torch.multinomial(weights, n, replacement=True, generator=generator)
    return list(order.split(batch_size))


def class_weights(
    steer_class: torch.Tensor, weighting: str, num_classes: int = NUM_STEER_CLASSES
) -> torch.Tensor | None:
    """float32 [num_classes] cross-entropy weights for ``weighting`` (None for "none"); absent classes get 0."""
    if weighting == "none" or len(steer_class) == 0:
        return None
    counts = torch.bincount(steer_class.cpu(), minlength=num_classes).to(torch.float64)
    present = counts > 0
    raw = torch.zeros(num_classes, dtype=torch.float64)
    raw[present] = 1.0 / (counts[present] if weighting == "inverse" else counts[present].sqrt())
    weights = raw * counts.sum() / (raw * counts).sum()
    return weights.to(torch.float32)
