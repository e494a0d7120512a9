"""What the cameras see above the ground: vehicles as shaded boxes in a colour of their own, and signal heads (pole, housing, three lamps) lit by SUMO's signal letters.
"""

from __future__ import annotations

import zlib

import numpy as np

from crchfl_sumo.vision.world import World

VEHICLE_PALETTE_RGB = (
    (200, 40, 40),
    (40, 90, 210),
    (230, 230, 225),
    (240, 170, 30),
    (40, 160, 90),
    (150, 60, 170),
    (30, 170, 190),
    (120, 90, 60),
)


POLE_RGB = (55, 55, 55)


HOUSING_RGB = (20, 20, 20)


LAMP_RED_RGB = (255, 30, 30)


LAMP_YELLOW_RGB = (255, 200, 0)


LAMP_GREEN_RGB = (30, 255, 90)


# Signal head geometry [m]: a pole to HEAD_BOTTOM_M, a housing above it,
# three lamps (red on top) on the housing's face towards the traffic.
POLE_SIZE_M = 0.12


HEAD_BOTTOM_M = 2.0


HEAD_HEIGHT_M = 0.9


HEAD_DEPTH_M = 0.3


HEAD_WIDTH_M = 0.35


LAMP_RADIUS_M = 0.11


LAMP_HEIGHTS_M = (HEAD_BOTTOM_M + 0.75, HEAD_BOTTOM_M + 0.45, HEAD_BOTTOM_M + 0.15)  # red, yellow, green


# A permissive green (SUMO 'g': go, but yield to the traffic that has priority, as a left turn
# across oncoming traffic does) in its own colour, when RasterConfig.mark_permissive is on: in
# plain green a camera cannot tell it from a protected green ('G'), yet it decides whether to wait.
LAMP_PERMISSIVE_RGB = (255, 0, 255)


# SUMO signal letter -> lit lamps (0 red, 1 yellow, 2 green, 3 permissive green). 'o'/'O'
# (off) and unknown letters light nothing.
LIT_LAMPS = {"r": (0,), "s": (0,), "u": (0, 1), "y": (1,), "Y": (1,), "g": (2,), "G": (2,)}
PERMISSIVE_LAMP = 3
LIT_LAMPS_MARKED = {**LIT_LAMPS, "g": (PERMISSIVE_LAMP,)}


LAMP_RGB = (LAMP_RED_RGB, LAMP_YELLOW_RGB, LAMP_GREEN_RGB, LAMP_PERMISSIVE_RGB)
LAMP_PLACE = (0, 1, 2, 2)  # the housing position (LAMP_HEIGHTS_M) of each lamp: permissive where green is


# Box corner k = 4*ix + 2*iy + iz: ix 0 rear / 1 front, iy 0 right / 1 left, iz 0 bottom / 1 top.
FACES = np.array(
    [
        [4, 6, 7, 5],  # front
        [0, 2, 3, 1],  # rear (a signal head's lamp face)
        [2, 6, 7, 3],  # left
        [0, 4, 5, 1],  # right
        [1, 5, 7, 3],  # top
        [0, 4, 6, 2],  # bottom
    ]
)


REAR_FACE = 1


FACE_SHADE = np.array([0.85, 0.85, 0.7, 0.7, 1.0, 0.5])


def box_corners(x_m, y_m, heading_rad, length_m, width_m, z_bottom_m, z_top_m) -> np.ndarray:
    """World corners [B, 8, 3] of yaw-only boxes centred at (x, y) (corner order: FACES)."""
    columns = (x_m, y_m, heading_rad, length_m, width_m, z_bottom_m, z_top_m)
    x_m, y_m, heading_rad, length_m, width_m, z_bottom_m, z_top_m = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in columns)
    )
    k = np.arange(8)
    ix, iy, iz = (k >> 2) & 1, (k >> 1) & 1, k & 1
    along = (ix - 0.5)[None, :] * length_m[:, None]
    across = (iy - 0.5)[None, :] * width_m[:, None]
    c, s = np.cos(heading_rad)[:, None], np.sin(heading_rad)[:, None]
    z = np.where(iz[None, :] == 1, z_top_m[:, None], z_bottom_m[:, None])
    return np.stack([x_m[:, None] + c * along - s * across, y_m[:, None] + s * along + c * across, z], axis=-1)


def vehicle_rgb(vehicle_id: str) -> tuple[int, int, int]:
    """A vehicle's body colour: fixed by its id (crc32, not Python's salted hash)."""
    return VEHICLE_PALETTE_RGB[zlib.crc32(vehicle_id.encode()) % len(VEHICLE_PALETTE_RGB)]


def lit_lamps(world: World, tls_states: dict[str, str], mark_permissive: bool = False) -> list[tuple[int, ...]]:
    """For each signal head of ``world``: the lamps its SUMO state letter lights (``mark_permissive``:
    a permissive green lights PERMISSIVE_LAMP instead of the green one)."""
    lit = LIT_LAMPS_MARKED if mark_permissive else LIT_LAMPS
    out = []
    for head in world.heads:
        state = tls_states.get(head.tls_id, "")
        letter = state[head.link_index] if head.link_index < len(state) else ""
        out.append(lit.get(letter, ()))
    return out
