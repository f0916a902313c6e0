"""An optional u-blox-like GPS receiver: noisy velocity and position, late on the link.

What a real receiver (u-blox M8/M9 on a quadrotor) does, and why it matters here:

* it measures at 5-10 Hz; velocity comes from Doppler (white-ish noise, 0.05-0.1 m/s
  horizontally, ~0.1-0.15 m/s vertically), position from pseudoranges, whose error
  wanders slowly (atmosphere, multipath): a first-order Gauss-Markov process of about
  0.5-1 m with a correlation time of tens of seconds, not white noise;
* each solution reaches the flight controller ~100 ms after the instant it is valid
  for. The board stamps it with that instant (GPS_RAW_INT.time_usec,
  LOCAL_POSITION_NED / GLOBAL_POSITION_INT.time_boot_ms) but sends it when it has it,
  so an estimator that uses it must account for its age — the emulator reproduces that
  delay instead of handing out fresh truth.

``GpsReceiver.fixes_until`` produces the fixes whose *send* time falls in a chunk, so
the stream stays in time order while every fix is measured ~latency earlier.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .truth import Profile


@dataclass(frozen=True)
class GpsConfig:
    rate_hz: float = 5.0  # navigation solutions per second
    latency_s: float = 0.1  # from validity to sending
    vel_noise_h_mps: float = 0.08  # 1σ per horizontal axis
    vel_noise_v_mps: float = 0.12
    pos_noise_h_m: float = 0.7  # 1σ per horizontal axis, slowly wandering
    pos_noise_v_m: float = 1.0
    pos_correlation_s: float = 30.0
    satellites: int = 14
    hdop: float = 0.8
    vdop: float = 1.2

    def __post_init__(self) -> None:
        if not 1.0 <= self.rate_hz <= 25.0:
            raise ValueError(f"GPS rate must be 1..25 Hz, got {self.rate_hz}")
        if not 0.0 <= self.latency_s <= 1.0:
            raise ValueError(f"GPS latency must be 0..1 s, got {self.latency_s}")
        noise = (self.vel_noise_h_mps, self.vel_noise_v_mps, self.pos_noise_h_m,
                 self.pos_noise_v_m)
        if not all(math.isfinite(v) and v >= 0.0 for v in noise) or self.pos_correlation_s <= 0:
            raise ValueError("GPS noise must be >= 0 and its correlation time > 0")


@dataclass
class GpsFixes:
    """Fixes in one stretch (index g), with the values exactly as they go on the wire."""

    t_s: np.ndarray  # (G,) true time the fix is valid for [s since the first IMU sample]
    time_us: np.ndarray  # (G,) board clock at that instant [µs since boot]
    sent_t_s: np.ndarray  # (G,) true time it is sent (t_s + latency)
    vel_ned: np.ndarray  # (G, 3) measured velocity [m/s], float32 values
    pos_ned: np.ndarray  # (G, 3) measured position from home [m], float32 values
    truth_vel_ned: np.ndarray  # (G, 3) the true velocity at t_s

    @classmethod
    def empty(cls) -> GpsFixes:
        z1, z3 = np.zeros(0), np.zeros((0, 3))
        return cls(z1, np.zeros(0, dtype=np.int64), z1.copy(), z3, z3.copy(), z3.copy())


class GpsReceiver:
    """Draws the fixes in order; the position error carries across chunks."""

    def __init__(self, config: GpsConfig, profile: Profile, rng: np.random.Generator):
        self.config = config
        self.profile = profile
        self.rng = rng
        self.next_fix = 0
        sigma = np.array([config.pos_noise_h_m, config.pos_noise_h_m, config.pos_noise_v_m])
        self._pos_sigma = sigma
        self._pos_error = rng.normal(size=3) * sigma  # stationary start
        self._phi = math.exp(-1.0 / (config.rate_hz * config.pos_correlation_s))

    def fixes_until(self, t_end: float, stamp) -> GpsFixes:
        """Fixes sent before ``t_end`` not produced yet; ``stamp(t)`` -> board µs."""
        c = self.config
        # first fix not yet due (sent at or after t_end; the margin absorbs rounding)
        last = math.ceil((t_end - c.latency_s) * c.rate_hz - 1e-6)
        idx = np.arange(self.next_fix, max(self.next_fix, last))
        if not len(idx):
            return GpsFixes.empty()
        self.next_fix = int(idx[-1]) + 1
        t = idx / c.rate_hz
        truth = self.profile.truth(t)
        vel_sigma = np.array([c.vel_noise_h_mps, c.vel_noise_h_mps, c.vel_noise_v_mps])
        vel = truth.velocity_ned + self.rng.normal(size=(len(t), 3)) * vel_sigma
        err = np.empty((len(t), 3))
        kick = self.rng.normal(size=(len(t), 3)) * self._pos_sigma * math.sqrt(1 - self._phi**2)
        for k in range(len(t)):
            self._pos_error = self._phi * self._pos_error + kick[k]
            err[k] = self._pos_error
        return GpsFixes(
            t_s=t, time_us=stamp(t), sent_t_s=np.round((t + c.latency_s) * 1e6) / 1e6,
            vel_ned=vel.astype(np.float32).astype(float),
            pos_ned=(truth.position_ned + err).astype(np.float32).astype(float),
            truth_vel_ned=truth.velocity_ned)


def aiding_at_samples(imu_t_s: np.ndarray, imu_time_us: np.ndarray, sent_t_s: np.ndarray,
                      fix_time_us: np.ndarray, vel_ned: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The estimators' ``vel`` / ``vel_age`` for IMU samples, from the GPS as sent.

    A fix is given at the first IMU sample sent at or after it (NaN rows elsewhere),
    with its age from the board stamps: IMU sample time - the time the fix is valid for.
    That is exactly what a listener on the link knows, so offline runs match live ones.
    """
    n = len(imu_t_s)
    vel = np.full((n, 3), np.nan)
    age = np.zeros(n)
    at = np.searchsorted(imu_t_s, np.asarray(sent_t_s) - 1e-9, side="left")
    ok = at < n
    vel[at[ok]] = vel_ned[ok]
    age[at[ok]] = (np.asarray(imu_time_us)[at[ok]] - np.asarray(fix_time_us)[ok]) * 1e-6
    return vel, age
