"""The flight controller's own attitude estimate, run on the emulated board's readings.

A real flight controller sends its own ATTITUDE; a listener compares against it (the
bridge's VEHICLE columns), so the emulator computes one the way each board does, from
the same imperfect readings it streams (never from the truth):

* ``SeedImuUpdate`` (the ``stm32`` board) — the seeds' 6-axis Mahony ``IMUupdate``,
  implemented from its formulas in the board's own frame (RFU body, world z up, raw
  counts scaled by the datasheet sensitivity, no calibration): accelerometer direction
  vs the predicted gravity ``v = (2(q1q3 - q0q2), 2(q0q1 + q2q3), q0² - q1² - q2² + q3²)``,
  error ``e = a × v``, PI correction ``ω + Kp e + ∫Ki e``, first-order integration
  ``q += ½ q ⊗ (0, ω) dt``, renormalise. Kp = 2.0 and the seeds' Ki = 0.001 per 1 kHz
  sample. Corrected where the seed's C is wrong: all four quaternion components are
  updated from the previous quaternion (the seed overwrites q0 before using it), the
  accelerometer is skipped only when its norm is zero (the seed skips whenever one axis
  reads exactly 0), the integral is scaled by the real time step (so its gain,
  1.0 rad/s² per unit error, is the seed's at 1 kHz at every rate) and the step comes
  from the board's time stamps. Yaw is unobservable to it and drifts with the gyro.
* ``LibraryFilter`` (``px4``, ``ardupilot``) — ``estimators`` Mahony on the SI FRD
  readings with the magnetometer for heading and the WMM declination, like PX4's
  attitude_estimator_q / ArduPilot's DCM (both Mahony-type PI filters). Fed the GPS
  velocity as aiding when the estimator API accepts it (``vel``/``vel_age``).
"""

from __future__ import annotations

import inspect
import math

import numpy as np

import estimators
from estimators import quat

from .recording import Recording

#: PX4 attitude_estimator_q defaults: ATT_W_ACC = 0.2 (proportional), the bias learning
#: ATT_W_GYRO_BIAS = 0.1 times that correction (so ki = 0.02 in Mahony's units).
PX4_GAINS = {"kp": 0.2, "ki": 0.02}
SEED_KP = 2.0
SEED_KI_PER_SAMPLE = 0.001
SEED_RATE_HZ = 1000.0


class SeedImuUpdate:
    """The seeds' IMUupdate on the STM32 (state carries across chunks)."""

    def __init__(self, gyro_lsb_per_dps: float):
        self.gyro_scale = math.radians(1.0 / gyro_lsb_per_dps)  # the seed's Gyro_Gr
        self.q = [1.0, 0.0, 0.0, 0.0]
        self.integral = [0.0, 0.0, 0.0]
        self.ki = SEED_KI_PER_SAMPLE * SEED_RATE_HZ
        self._last_us: int | None = None

    def run(self, rec: Recording) -> tuple[np.ndarray, np.ndarray]:
        """(q FRD -> NED (N, 4), body rates FRD (N, 3)) after each sample."""
        n = len(rec)
        out = np.empty((n, 4))
        gyr = (rec.gyr_counts.astype(float) * self.gyro_scale).tolist()
        acc = rec.acc_counts.astype(float).tolist()
        stamps = rec.time_us.tolist()
        q0, q1, q2, q3 = self.q
        ix, iy, iz = self.integral
        kp, ki = SEED_KP, self.ki
        for k in range(n):
            dt = 0.0 if self._last_us is None else (stamps[k] - self._last_us) * 1e-6
            self._last_us = stamps[k]
            if not 0.0 < dt < 0.5:  # first sample, or a clock step: hold
                out[k] = (q0, q1, q2, q3)
                continue
            gx, gy, gz = gyr[k]
            ax, ay, az = acc[k]
            norm = math.sqrt(ax * ax + ay * ay + az * az)
            if norm > 0.0:
                ax, ay, az = ax / norm, ay / norm, az / norm
                vx = 2.0 * (q1 * q3 - q0 * q2)
                vy = 2.0 * (q0 * q1 + q2 * q3)
                vz = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3
                ex = ay * vz - az * vy
                ey = az * vx - ax * vz
                ez = ax * vy - ay * vx
                ix += ki * ex * dt
                iy += ki * ey * dt
                iz += ki * ez * dt
                gx += kp * ex + ix
                gy += kp * ey + iy
                gz += kp * ez + iz
            h = 0.5 * dt
            q0, q1, q2, q3 = (q0 + (-q1 * gx - q2 * gy - q3 * gz) * h,
                              q1 + (q0 * gx + q2 * gz - q3 * gy) * h,
                              q2 + (q0 * gy - q1 * gz + q3 * gx) * h,
                              q3 + (q0 * gz + q1 * gy - q2 * gx) * h)
            norm = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
            q0, q1, q2, q3 = q0 / norm, q1 / norm, q2 / norm, q3 / norm
            out[k] = (q0, q1, q2, q3)
        self.q = [q0, q1, q2, q3]
        self.integral = [ix, iy, iz]
        # board frame (RFU body -> ENU world) to MAVLink's FRD -> NED
        q_ned = quat.canonical(quat.rfu_to_frd_body(quat.enu_to_ned(out)))
        return q_ned, rec.gyr


class LibraryFilter:
    """An ``estimators`` Mahony as the autopilot's attitude estimator."""

    def __init__(self, rate_hz: float, declination_deg: float, **gains: float):
        self.est = estimators.create("mahony", rate_hz=rate_hz, world="NED",
                                     declination=math.radians(declination_deg), **gains)
        self.aided = "vel" in inspect.signature(self.est.run).parameters
        self._last_us: int | None = None
        self.bias = np.zeros(3)

    def run(self, rec: Recording) -> tuple[np.ndarray, np.ndarray]:
        """(q FRD -> NED (N, 4), bias-corrected body rates (N, 3)) after each sample."""
        stamps = rec.time_us.astype(np.int64)
        prev = stamps[0] - round(1e6 / self.est.rate_hz) if self._last_us is None \
            else self._last_us
        dt = np.diff(stamps, prepend=prev) * 1e-6
        self._last_us = int(stamps[-1])
        kwargs = {}
        if self.aided and len(rec.gps_t_s):
            from .gps import aiding_at_samples
            vel, age = aiding_at_samples(rec.t_s, rec.time_us, rec.gps_sent_t_s,
                                         rec.gps_time_us, rec.gps_vel_ned)
            kwargs = {"vel": vel, "vel_age": age}
        result = self.est.run(rec.gyr, rec.acc, rec.mag, dt=dt, **kwargs)
        self.bias = result.bias[-1]
        return quat.canonical(result.q), rec.gyr - result.bias


def make_onboard(personality: str, rate_hz: float, gyro_lsb_per_dps: float,
                 declination_deg: float):
    """The onboard estimator of a personality."""
    if personality == "stm32":
        return SeedImuUpdate(gyro_lsb_per_dps)
    if personality == "px4":
        return LibraryFilter(rate_hz, declination_deg, **PX4_GAINS)
    return LibraryFilter(rate_hz, declination_deg)
