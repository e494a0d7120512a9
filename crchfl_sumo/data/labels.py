"""The label schema: action vector, the 7 steer classes (the paper's digitizer and DAC), route commands.

Action vector (throttle, steer, brake): throttle and brake in [0, 1], steer in
[-1, 1], positive steer turns RIGHT, negative LEFT (the CRCHFL paper's CARLA
convention; its left turn at a T-junction carries steer -0.275).

Route command (Conditional Imitation Learning, Codevilla et al. 2018): what
the vehicle's route does at the next junction within the command look-ahead
(data/route_commands.py): follow the lane (no junction near), turn left, turn right,
or go straight across; on a multi-lane road, also change to the lane on the
left or on the right (CARLA's CHANGELANELEFT and CHANGELANERIGHT), from a
little before the sideways move until it ends. Code k is COMMAND_NAMES[k].
A network of JUNCTION_COMMANDS heads (the paper's and CIL's four) reads a
lane-change command as follow (learning/model.py).

Signal ahead (data set format 5): the state of the next signal on the sample's
route for its link, code k = SIGNAL_NAMES[k] ("unknown" where the data does not
say: shards of format 4, DAgger's samples), with the distance to its stop line.
"""

from __future__ import annotations

import numpy as np

ACTION_NAMES = ("throttle", "steer", "brake")

# Class k decodes to STEER_CLASS_VALUES[k] (the paper's reference implementation).
STEER_CLASS_VALUES = np.array([0.0, 0.125, 0.275, 0.425, -0.125, -0.275, -0.425], dtype=np.float32)
NUM_STEER_CLASSES = len(STEER_CLASS_VALUES)

COMMAND_NAMES = ("follow", "left", "right", "straight", "change_left", "change_right")
FOLLOW, LEFT, RIGHT, STRAIGHT, CHANGE_LEFT, CHANGE_RIGHT = range(len(COMMAND_NAMES))
NUM_COMMANDS = len(COMMAND_NAMES)
JUNCTION_COMMANDS = 4  # follow, left, right, straight: the commands of a network without lane-change heads


SIGNAL_NAMES = ("unknown", "none", "red", "yellow", "green", "green_minor", "off")
SIGNAL_UNKNOWN, SIGNAL_NONE, SIGNAL_RED, SIGNAL_YELLOW, SIGNAL_GREEN, SIGNAL_GREEN_MINOR, SIGNAL_OFF = range(
    len(SIGNAL_NAMES)
)
# SUMO's signal letters: r red, u red-yellow, s stop sign (stop, then go), y/Y yellow, G major green,
# g minor green (go, but yield), o/O off (blinking / no signal)
_SIGNAL_OF_LETTER = {
    "": SIGNAL_NONE, "r": SIGNAL_RED, "u": SIGNAL_RED, "s": SIGNAL_RED, "y": SIGNAL_YELLOW, "Y": SIGNAL_YELLOW,
    "G": SIGNAL_GREEN, "g": SIGNAL_GREEN_MINOR, "o": SIGNAL_OFF, "O": SIGNAL_OFF,
}


def signal_codes(letters) -> np.ndarray:
    """int8 [N] SIGNAL_NAMES codes of SUMO signal letters ('' = no signal ahead; an unknown letter: off)."""
    return np.array([_SIGNAL_OF_LETTER.get(str(letter), SIGNAL_OFF) for letter in letters], dtype=np.int8)


def digitize_steer(steer: np.ndarray | float) -> np.ndarray:
    """Analogue steer -> class index of the nearest STEER_CLASS_VALUES (ties: lower index)."""
    return nearest_bin(steer, STEER_CLASS_VALUES)


def steer_bin_values(bins: int) -> np.ndarray:
    """The steer values of a steer head's ``bins`` classes: the paper's 7 (STEER_CLASS_VALUES, in its
    order) for 7, else ``bins`` evenly spaced over [-1, 1] (odd counts, so one of them is 0)."""
    if bins == NUM_STEER_CLASSES:
        return STEER_CLASS_VALUES
    return np.linspace(-1.0, 1.0, bins, dtype=np.float32)


def nearest_bin(steer: np.ndarray | float, values: np.ndarray) -> np.ndarray:
    """Analogue steer -> index of the nearest of ``values`` (ties: lower index)."""
    steer = np.asarray(steer, dtype=np.float32)
    return np.abs(steer[..., None] - values).argmin(axis=-1).astype(np.int64)


def steer_from_class(steer_class: np.ndarray | int) -> np.ndarray:
    """The DAC: class index -> analogue steer value."""
    steer_class = np.asarray(steer_class)
    if steer_class.size and (steer_class.min() < 0 or steer_class.max() >= NUM_STEER_CLASSES):
        raise ValueError(f"steer class out of range 0..{NUM_STEER_CLASSES - 1}")
    return STEER_CLASS_VALUES[steer_class]
