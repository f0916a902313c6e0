"""Velocity measurements put on the IMU samples the way a vehicle would have used them.

A measurement can only help an estimator from the moment it has arrived, and it
describes the vehicle at an earlier instant. So each one goes to the first IMU sample
at (or after) its arrival, with ``age`` = that sample's time − the instant it was valid;
an unknown validity instant counts as the arrival (the age is then a lower bound).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..dataset import Velocity


@dataclass(frozen=True)
class VelocityRows:
    """Raw measurements of one source, all times on the IMU's clock (seconds)."""

    vel: np.ndarray  # (M, 3) NED m/s; NaN components unknown (GPS vertical)
    arrival: np.ndarray  # (M,) when the vehicle had it; NaN if before any IMU sample
    valid: np.ndarray  # (M,) when it was true; NaN if unknown
    source: str
    # True: arrival is the time of the IMU sample *before* it (tlog order), so the first
    # sample that can use it is the next one; False: arrival is its own publication time.
    after_arrival: bool = True


def place_velocity(rows: VelocityRows | None, t: np.ndarray) -> Velocity | None:
    """(N, 3) velocity and (N,) age on the IMU samples ``t``; None without measurements."""
    if rows is None:
        return None
    n = t.shape[0]
    usable = np.isfinite(rows.arrival) & np.any(np.isfinite(rows.vel), axis=1)
    side = "right" if rows.after_arrival else "left"
    place = np.searchsorted(t, rows.arrival, side=side)
    usable &= place < n
    if not usable.any():
        return None
    place, vel = place[usable], rows.vel[usable]
    valid = np.where(np.isfinite(rows.valid[usable]), rows.valid[usable], rows.arrival[usable])
    age = t[place] - valid
    early = int(np.count_nonzero(age < 0))  # stamped after the sample it arrived by
    out_v = np.full((n, 3), np.nan)
    out_a = np.full(n, np.nan)
    out_v[place] = vel  # several on one sample: the last one in the log wins
    out_a[place] = np.maximum(age, 0.0)
    unknown = int(np.count_nonzero(~np.isfinite(rows.valid[usable])))
    how = ("at the first IMU sample after its arrival" if rows.after_arrival
           else "at the first IMU sample at or after its publication")
    if unknown:
        how += f"; {unknown} without a validity stamp aged from their arrival"
    if early:
        how += f"; {early} stamped after their arrival, age set to 0"
    return Velocity(out_v, out_a, rows.source, how)
