"""A small known-truth IMU recording, for tuning demos and tests without the emulator.

The motion is smooth multi-axis oscillation (sums of sines in Z-Y-X Euler angles), the
gyro reads the exact rotation between consecutive truth samples (``rotvec(q[i-1]* q[i])
/ dt``, so exact integration reproduces the truth), the accelerometer reads gravity's
specific force plus an optional sinusoidal linear acceleration, the magnetometer a
mid-latitude field; then white noise and a constant gyro bias. It is deliberately
simple and independent of ``hil`` (the register-level GY-86 emulator): it exists so that
replay/tune can be checked against a truth that is known exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimators import quat as Q

from .dataset import Recording, Reference, TimeCleanup

G = 9.80665
FIELD_NED = np.array([0.2, 0.02, 0.43])  # gauss: ~65° inclination, small declination


@dataclass(frozen=True)
class SyntheticConfig:
    duration_s: float = 60.0
    rate_hz: float = 200.0
    amplitude_deg: tuple[float, float, float] = (30.0, 20.0, 60.0)  # roll, pitch, yaw
    period_s: tuple[float, float, float] = (7.0, 11.0, 17.0)
    gyro_noise: float = 0.01  # rad/s per sample (std)
    gyro_bias: tuple[float, float, float] = (0.02, -0.015, 0.01)  # rad/s
    acc_noise: float = 0.5  # m/s^2 per sample (std)
    linear_acc: float = 0.0  # m/s^2 amplitude of a horizontal shaking (non-gravitational)
    mag_noise: float = 0.01  # gauss
    seed: int = 0


def truth_attitude(cfg: SyntheticConfig) -> tuple[np.ndarray, np.ndarray]:
    """(t, q body->NED) of the motion."""
    t = np.arange(round(cfg.duration_s * cfg.rate_hz)) / cfg.rate_hz
    angles = [np.radians(a) * np.sin(2 * np.pi * t / p + 0.7 * k)
              for k, (a, p) in enumerate(zip(cfg.amplitude_deg, cfg.period_s, strict=True))]
    return t, Q.normalize(Q.from_euler(*angles))


def generate(cfg: SyntheticConfig = SyntheticConfig()) -> Recording:
    """A Recording (FRD body, NED world) with HIL-style truth as its reference."""
    rng = np.random.default_rng(cfg.seed)
    t, q = truth_attitude(cfg)
    dt = 1.0 / cfg.rate_hz
    step = Q.canonical(Q.multiply(Q.conjugate(q[:-1]), q[1:]))
    gyr = np.empty((len(t), 3))
    gyr[1:] = Q.to_rotvec(step) / dt
    gyr[0] = gyr[1]
    r = Q.to_dcm(q)
    lin = np.zeros((len(t), 3))
    lin[:, 0] = cfg.linear_acc * np.sin(2 * np.pi * t / 0.9)
    acc = np.einsum("nji,nj->ni", r, lin - np.array([0.0, 0.0, G]))
    mag = np.einsum("nji,j->ni", r, FIELD_NED)
    gyr = gyr + np.asarray(cfg.gyro_bias) + rng.normal(0, cfg.gyro_noise, gyr.shape)
    acc = acc + rng.normal(0, cfg.acc_noise, acc.shape)
    mag = mag + rng.normal(0, cfg.mag_noise, mag.shape)
    ref = Reference(t=t, q=q, kind="truth", source="synthetic truth")
    return Recording(path=Path(f"synthetic-seed{cfg.seed}"), format="synthetic", t=t, gyr=gyr,
                     acc=acc, mag=mag, world="NED", body="FRD", source="synthetic",
                     reference=ref, cleanup=TimeCleanup(kept=len(t)))
