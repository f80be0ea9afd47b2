"""Geometry of the can world: the 4-3-2-1 pyramid, its configurations, fields and angles.

The world is the plane of the throw: x points from the thrower towards the cans, z up,
SI units throughout (metres, seconds). Ten cans, each a box 0.12 m wide (the can's
diameter) and 0.16 m tall, stand 4-3-2-1 on a table top at z = 0; neighbours in a row
are 0.02 m apart and each upper can is centred over the gap between the two below it.
The pyramid's near face (the side the ball comes from) is at x = ``PYRAMID_X`` = 2 m,
where the combined experiment puts it::

        z
        ^           thrower --> ball flies towards +x
   0.64 +                 +----+
        |                 |  9 |                      row 3
   0.48 +            +----+----+----+
        |            |  7 |    |  8 |                 row 2
   0.32 +       +----+----+----+----+----+
        |       |  4 |    |  5 |    |  6 |            row 1
   0.16 +  +----+----+----+----+----+----+----+
        |  |  0 |    |  1 |    |  2 |    |  3 |       row 0
   0.00 +==+====+====+====+====+====+====+====+====== table top
           x = 2.00 (near face)            x = 2.54 (far face)

Can indices run row by row from the bottom, and within a row from the near side
(small x, towards the thrower) to the far side (large x). Can i of row r rests on cans
``SUPPORTERS[i]``. Named groups used by the combined experiment (paper §IV-C):

- ``TOP_THREE = (7, 8, 9)``: the top can and the two below it,
- ``NEAR_FLANK = (0, 4, 7, 9)``: the near diagonal edge, bottom to top,
- ``FAR_FLANK = (3, 6, 8, 9)``: the far diagonal edge, bottom to top.

A configuration is a subset of the ten cans, written as a 10-bit int mask (bit i set:
can i stands at its standard position); :func:`n_cans` is its number of cans. Which
subsets are physically possible is decided by simulation in :mod:`sim2d.configurations`.

An action is a field and an angle. The fields are a grid of 15 columns x 13 rows over
the pyramid's bounding box (0.54 m x 0.64 m); field index = row * 15 + column, row 0 at
the bottom, column 0 at the near side. The angle is the ball's velocity ``ANGLES[angle]``
as its centre passes the field's centre; the ball starts on the entry line
x = ``ENTRY_X`` (:mod:`sim2d.field_throws`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from effect_networks.sim2d.validation import check_index

__all__ = [
    "ANGLES",
    "ANGLE_NAMES",
    "CAN_HEIGHT",
    "CAN_WIDTH",
    "ENTRY_X",
    "FAR_FLANK",
    "FIELD_HEIGHT",
    "FIELD_WIDTH",
    "FULL_PYRAMID",
    "GAP",
    "NEAR_FLANK",
    "N_CANS",
    "N_COLUMNS",
    "N_FIELDS",
    "N_ROWS",
    "PYRAMID_HEIGHT",
    "PYRAMID_WIDTH",
    "PYRAMID_X",
    "ROW_OF",
    "ROW_SIZES",
    "SUPPORTERS",
    "TOP_THREE",
    "can_positions",
    "cans_to_mask",
    "check_mask",
    "n_cans",
    "field_centres",
    "mask_to_cans",
]

# --- the pyramid (paper §IV-A) --------------------------------------------------------------
N_CANS = 10
ROW_SIZES = (4, 3, 2, 1)  # bottom row first
CAN_WIDTH = 0.12  # m, the can's diameter
CAN_HEIGHT = 0.16  # m
GAP = 0.02  # m, between neighbours in a row
PYRAMID_X = 2.0  # m, near face; the combined experiment's pyramid stands at x = 2 m
PYRAMID_WIDTH = ROW_SIZES[0] * CAN_WIDTH + (ROW_SIZES[0] - 1) * GAP  # 0.54 m
PYRAMID_HEIGHT = len(ROW_SIZES) * CAN_HEIGHT  # 0.64 m
FULL_PYRAMID = (1 << N_CANS) - 1

# Row of each can and the two cans each upper can rests on (None for the bottom row).
ROW_OF = tuple(r for r, n in enumerate(ROW_SIZES) for _ in range(n))
_ROW_START = tuple(sum(ROW_SIZES[:r]) for r in range(len(ROW_SIZES)))
SUPPORTERS: tuple[tuple[int, int] | None, ...] = tuple(
    None if r == 0 else (_ROW_START[r - 1] + k, _ROW_START[r - 1] + k + 1)
    for r, n in enumerate(ROW_SIZES)
    for k in range(n)
)
TOP_THREE = (7, 8, 9)
NEAR_FLANK = (0, 4, 7, 9)
FAR_FLANK = (3, 6, 8, 9)

# --- actions (the paper's 195 fields x 3 angles) --------------------------------------------
N_COLUMNS = 15
N_ROWS = 13
N_FIELDS = N_COLUMNS * N_ROWS  # 195
FIELD_WIDTH = PYRAMID_WIDTH / N_COLUMNS  # 0.036 m
FIELD_HEIGHT = PYRAMID_HEIGHT / N_ROWS  # ~0.0492 m
# Ball velocity (vx, vz) in m/s as its centre passes the field centre. The names follow
# the paper's three throwing angles; ours lie in the plane: "30deg" descends
# (atan(4/7) = 29.7 degrees below horizontal), "-30deg" ascends.
ANGLES = ((7.0, 0.0), (7.0, -4.0), (7.0, 4.0))
ANGLE_NAMES = ("0deg", "30deg", "-30deg")
ENTRY_X = PYRAMID_X - 0.1  # m; the entry line where a field throw's ball starts


@lru_cache(maxsize=1)
def _can_positions() -> np.ndarray:
    pitch = CAN_WIDTH + GAP
    rows = [
        (PYRAMID_X + r * pitch / 2 + k * pitch + CAN_WIDTH / 2, r * CAN_HEIGHT + CAN_HEIGHT / 2)
        for r, n in enumerate(ROW_SIZES)
        for k in range(n)
    ]
    out = np.array(rows, dtype=float)
    out.setflags(write=False)
    return out


def can_positions() -> np.ndarray:
    """Standard centres of the ten cans.

    Returns
    -------
    np.ndarray
        ``(10, 2)`` float, metres (a fresh copy): ``(x, z)`` of can i's centre. Order:
        bottom row near to far (0-3), then 4-6, 7-8, and the top can 9 (see the module
        sketch).
    """
    return _can_positions().copy()


@lru_cache(maxsize=1)
def _field_centres() -> np.ndarray:
    column = np.arange(N_FIELDS) % N_COLUMNS
    row = np.arange(N_FIELDS) // N_COLUMNS
    out = np.stack([PYRAMID_X + (column + 0.5) * FIELD_WIDTH, (row + 0.5) * FIELD_HEIGHT], axis=1)
    out.setflags(write=False)
    return out


def field_centres() -> np.ndarray:
    """Centres of the 195 fields.

    Returns
    -------
    np.ndarray
        ``(195, 2)`` float, metres (a fresh copy): ``(x, z)`` of field
        ``row * 15 + column``; row 0 is the bottom, column 0 the near side (smallest x).
    """
    return _field_centres().copy()


def check_mask(mask, name: str = "mask") -> int:
    """``mask`` as an int in ``0..1023`` (any 10-bit configuration mask)."""
    return check_index(mask, name, 1 << N_CANS, "a 10-bit configuration mask")


def mask_to_cans(mask: int) -> tuple[int, ...]:
    """Indices of the cans in a configuration mask, ascending."""
    mask = check_mask(mask)
    return tuple(i for i in range(N_CANS) if mask >> i & 1)


def cans_to_mask(cans) -> int:
    """Configuration mask of an iterable of can indices (0-9)."""
    mask = 0
    for can in cans:
        mask |= 1 << check_index(can, "cans", N_CANS, "a can index")
    return mask


def n_cans(mask: int) -> int:
    """Number of cans in a configuration mask."""
    return check_mask(mask).bit_count()
