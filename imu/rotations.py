"""Board/sensor mounting rotations by their PX4 / ArduPilot names.

Both autopilots name a mounting rotation after the Euler angles that turn the board
into the vehicle body: ``ROTATION_ROLL_180_YAW_90`` means roll 180°, then yaw 90°.
A vector measured in board axes is expressed in body (FRD) axes by
``v_body = Rz(yaw) · Ry(pitch) · Rx(roll) · v_board`` — e.g. ``YAW_90`` maps board
x to body y (ArduPilot: x' = -y, y' = x), ``ROLL_180_YAW_90`` gives (y, x, -z).
Any combination of ``ROLL_<deg>``, ``PITCH_<deg>``, ``YAW_<deg>`` is accepted, which
covers both tables (including ArduPilot's ``ROLL_90_PITCH_68_YAW_293``).
"""

from __future__ import annotations

import math
import re

import numpy as np

_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_matrix(name: str) -> np.ndarray:
    """3x3 board -> body matrix for a rotation name (``NONE``, ``YAW_90``, ...).

    The ``ROTATION_`` prefix and case are optional. Exact multiples of 90° give exact
    0/±1 entries. Unknown names raise ValueError with an example of valid ones.
    """
    text = name.strip().upper().removeprefix("ROTATION_")
    if text in ("", "NONE"):
        return np.eye(3)
    parts = text.split("_")
    angles = {"ROLL": 0.0, "PITCH": 0.0, "YAW": 0.0}
    order = list(angles)
    last = -1
    for axis, value in zip(parts[0::2], parts[1::2], strict=False):
        valid = axis in angles and order.index(axis) > last and _NUMBER.fullmatch(value)
        if not valid:
            break
        last = order.index(axis)
        angles[axis] = math.radians(float(value))
    else:
        if len(parts) % 2 == 0:
            last = -2  # sentinel: fully parsed
    if last != -2:
        raise ValueError(f"unknown rotation {name!r}; use NONE or names like YAW_90, "
                         f"ROLL_180, ROLL_180_YAW_45, PITCH_270, ROLL_90_PITCH_68_YAW_293")
    r = _rz(angles["YAW"]) @ _ry(angles["PITCH"]) @ _rx(angles["ROLL"])
    return np.where(np.abs(r) < 1e-12, 0.0, np.round(r, 15))
