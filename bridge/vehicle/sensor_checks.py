"""Per-source rules that judge a reading by what came before it from the same sensor.

Both need the source's history (:class:`~bridge.vehicle.imu_sample.SourceState`), which
is why they are not in the per-message conversion:

* a stuck sensor: identical raw readings for milliseconds. Noise makes a 6-axis raw
  reading repeated that long practically impossible, so the sensor (or its driver) is
  re-sending old data. Only for true sensor counts: rounded units (ArduPilot's mG,
  mrad/s) repeat honestly at rest;
* a disturbed magnetometer: the Earth's field strength is constant where a vehicle
  flies, so a reading MAG_NORM_TOLERANCE off the running average has a magnet or motor
  current nearby, and its direction would pull the heading.
"""

from __future__ import annotations

import math

import numpy as np

from .imu_sample import SourceState

MAG_NORM_TOLERANCE = 0.15  # relative deviation of |mag| that marks a disturbed reading
MAG_NORM_GAIN = 0.001  # per-sample weight of the running |mag| average
#: After this long of continuous rejection the new strength is the reference (e.g. a
#: calibration changed).
MAG_REANCHOR_S = 3.0
#: Identical RAW_IMU readings are a stuck sensor once they have lasted this long [µs]:
#: an MPU6050 at 8 kHz repeats itself for a few samples (its accelerometer register
#: changes at 1 kHz, its gyro often by less than a count), never for milliseconds.
STUCK_MIN_US = 5000


def stuck_flags(src: SourceState, raw: tuple, time_usec: int) -> tuple[str, ...]:
    """("stuck",) for a reading that repeats a run lasting STUCK_MIN_US; once the run
    qualifies, all of its repeats count (those before it, at once)."""
    if raw != src.last_raw:
        src.last_raw, src.repeats, src.stuck = raw, 0, False
        src.repeat_from_us = time_usec
        return ()
    src.repeats += 1
    if src.stuck:
        return ("stuck",)
    if time_usec - src.repeat_from_us >= STUCK_MIN_US and src.repeats >= 2:
        src.stuck = True
        src.counts["stuck"] += src.repeats - 1
        return ("stuck",)
    return ()


def guard_mag(src: SourceState, mag: np.ndarray, t: float) -> np.ndarray | None:
    """``mag``, or None for a reading whose strength is far from the usual (counted as
    ``mag_disturbed``); ``t`` is board time."""
    n = math.sqrt(float(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2]))
    ref = src.mag_norm
    if ref > 0.0 and abs(n - ref) > MAG_NORM_TOLERANCE * ref:
        if t - src.mag_rejected_since < MAG_REANCHOR_S:
            src.counts["mag_disturbed"] += 1
            return None
        ref = 0.0
    src.mag_rejected_since = t
    src.mag_norm = n if ref == 0.0 else ref + MAG_NORM_GAIN * (n - ref)
    return mag
