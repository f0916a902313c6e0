"""Noise-free sensor samples for analytic motions, shared by the filter tests.

World NED, magnetic north along +x. Like Mahony's and Madgwick's reference code, the
filters correct the current estimate with a sample's acc/mag and then integrate that
sample's gyro over dt; consistent data therefore carries acc/mag of the attitude at the
*start* of the step (otherwise a filter settles one step, ``ω·dt``, ahead of the truth).
"""

from __future__ import annotations

import math

import numpy as np

from estimators import quat as Q

G = 9.80665
FIELD_NED = np.array([0.19, 0.0, 0.45])  # ~67° dip, any unit
TILT = Q.from_euler(math.radians(15.9), math.radians(9.2), 0.0)  # the paper's static tilt


def sensors(truth: np.ndarray, field: np.ndarray = FIELD_NED) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free accelerometer (specific force at rest) and magnetometer for ``truth``."""
    body = Q.conjugate(truth)
    return Q.rotate(body, np.array([0.0, 0.0, -G])), Q.rotate(body, field)


def constant_rate(w: np.ndarray, seconds: float, rate: float, q0: np.ndarray):
    """Truth after each step and consistent samples for a body rate ``w`` from ``q0``."""
    t = np.arange(0, round(seconds * rate) + 1) / rate
    truth = Q.multiply(q0, Q.from_rotvec(np.outer(t, w)))
    acc, mag = sensors(truth[:-1])
    return truth[1:], np.tile(w, (len(t) - 1, 1)), acc, mag


def static(truth: np.ndarray, seconds: float, rate: float,
           bias: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples at rest at ``truth``; the gyro reads ``bias`` (default zero)."""
    n = round(seconds * rate)
    acc, mag = sensors(truth)
    gyr = np.zeros(3) if bias is None else bias
    return np.tile(gyr, (n, 1)), np.tile(acc, (n, 1)), np.tile(mag, (n, 1))


def deg(x: np.ndarray) -> np.ndarray:
    return np.degrees(x)
