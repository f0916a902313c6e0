"""Board profiles: what the integers in a RAW_IMU message mean.

RAW_IMU carries "raw" int16 values whose units and axes depend on who sends them:

* ``gy86`` — the HIL emulator (an STM32 reading a GY-86): true MPU6050 / HMC5883L
  register counts in the chips' axes, which on the board are the seeds' frame
  X right, Y forward, Z up (RFU). Scales follow the configured full-scale ranges.
* ``ardupilot`` — ArduPilot fills RAW_IMU with mG, mrad/s and mGauss, already FRD.

A profile turns one message's integers into SI vectors in the FRD body frame and
says which values are unusable (saturated axes, the HMC5883L's -4096 overflow), so
ingest can hand NaN to the estimator instead of a silently wrong vector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

G = 9.80665

#: MPU6050 gyro sensitivity [LSB per deg/s] by FS_SEL (datasheet, table 6.1).
MPU6050_GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
#: MPU6050 full scale [deg/s] by FS_SEL.
MPU6050_GYRO_RANGE_DPS = (250.0, 500.0, 1000.0, 2000.0)
#: MPU6050 accelerometer sensitivity [LSB per g] by AFS_SEL (datasheet, table 6.2).
MPU6050_ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
#: MPU6050 accelerometer full scale [g] by AFS_SEL.
MPU6050_ACCEL_RANGE_G = (2.0, 4.0, 8.0, 16.0)
#: HMC5883L gain [LSB per gauss] by GN (CRB bits 7..5), datasheet table 9.
HMC5883L_LSB_PER_GAUSS = (1370.0, 1090.0, 820.0, 660.0, 440.0, 390.0, 330.0, 230.0)
#: HMC5883L register value that signals an overflowed axis.
HMC5883L_OVERFLOW = -4096

#: Default GY-86 configuration used by the emulator and the ``gy86`` profile.
DEFAULT_FS_SEL = 3  # +-2000 deg/s
DEFAULT_AFS_SEL = 2  # +-8 g
DEFAULT_HMC_GAIN = 1  # 1090 LSB/G, +-1.3 Ga

#: RFU (X right, Y forward, Z up) -> FRD: x_frd = y, y_frd = x, z_frd = -z.
RFU_TO_FRD = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class BoardProfile:
    """Scales and axes of one sender's RAW_IMU integers."""

    name: str
    gyro_scale: float  # rad/s per count
    accel_scale: float  # m/s^2 per count
    mag_scale: float  # gauss per count
    to_frd: np.ndarray  # 3x3: FRD vector = to_frd @ message-axes vector
    gyro_saturation: int | None  # |count| at which an axis is clipped, None if unknown
    accel_saturation: int | None
    mag_overflow: int | None  # count that means "overflow" for an axis
    #: The integers are the sensor's own counts, noisy in their last bits, so a reading
    #: repeated on all six axes is a stuck sensor. ArduPilot's are filtered and truncated
    #: to mG / mrad/s: a quiet board (or a simulator at rest) repeats them honestly.
    sensor_counts: bool = True
    #: The sender made its integers from a float by C's conversion, which truncates
    #: toward zero (ArduPilot: ``gyro * 1000`` into an int16 field): a count k ≠ 0 stands
    #: for a value between k and k ± 1, on average k ± ½, and 0 for one in (−1, 1).
    #: Taken as k, every reading is half a step short of its value on the side away
    #: from zero, which in a steady turn is a gyro bias that flips with the turn.
    truncated: bool = False

    @property
    def gyro_range(self) -> float:
        """Full scale [rad/s] (inf when unknown), for the estimators' saturation check."""
        if self.gyro_saturation is None:
            return math.inf
        return self.gyro_saturation * self.gyro_scale

    @property
    def accel_range(self) -> float:
        """Full scale [m/s^2] (inf when unknown)."""
        if self.accel_saturation is None:
            return math.inf
        return self.accel_saturation * self.accel_scale

    def gyro(self, counts: np.ndarray) -> np.ndarray:
        """Rad/s in FRD; NaN if any axis sits at full scale (clipped, so untrustworthy)."""
        return self._convert(counts, self.gyro_scale, self.gyro_saturation, None)

    def accel(self, counts: np.ndarray) -> np.ndarray:
        """Specific force m/s^2 in FRD; NaN if any axis is clipped."""
        return self._convert(counts, self.accel_scale, self.accel_saturation, None)

    def mag(self, counts: np.ndarray) -> np.ndarray:
        """Gauss in FRD; NaN if any axis overflowed."""
        return self._convert(counts, self.mag_scale, None, self.mag_overflow)

    def centred(self, counts: np.ndarray) -> np.ndarray:
        """The counts as the middle of the values they stand for (see ``truncated``)."""
        c = np.asarray(counts, dtype=float)
        return c + 0.5 * np.sign(c) if self.truncated else c

    def _convert(self, counts: np.ndarray, scale: float, saturation: int | None,
                 overflow: int | None) -> np.ndarray:
        c = np.asarray(counts, dtype=float)
        bad = np.zeros(c.shape[:-1], dtype=bool)
        if saturation is not None:
            bad |= np.any(np.abs(c) >= saturation, axis=-1)
        if overflow is not None:
            bad |= np.any(c == overflow, axis=-1)
        v = (self.centred(c) * scale) @ self.to_frd.T
        return np.where(bad[..., None], np.nan, v)


def gy86(fs_sel: int = DEFAULT_FS_SEL, afs_sel: int = DEFAULT_AFS_SEL,
         hmc_gain: int = DEFAULT_HMC_GAIN) -> BoardProfile:
    """The GY-86 on an STM32 (the emulator): raw counts in the chips' RFU axes."""
    return BoardProfile(
        name="gy86",
        gyro_scale=math.radians(1.0 / MPU6050_GYRO_LSB_PER_DPS[fs_sel]),
        accel_scale=G / MPU6050_ACCEL_LSB_PER_G[afs_sel],
        mag_scale=1.0 / HMC5883L_LSB_PER_GAUSS[hmc_gain],
        to_frd=RFU_TO_FRD,
        # int16 clips at -32768..32767; treat either end as saturated.
        gyro_saturation=32767,
        accel_saturation=32767,
        mag_overflow=HMC5883L_OVERFLOW,
    )


def ardupilot() -> BoardProfile:
    """ArduPilot's RAW_IMU: mG, mrad/s, mGauss, already in FRD (see ../shared/data/logs)."""
    return BoardProfile(
        name="ardupilot",
        gyro_scale=1e-3,
        accel_scale=1e-3 * G,
        mag_scale=1e-3,
        to_frd=np.eye(3),
        gyro_saturation=None,
        accel_saturation=None,
        mag_overflow=None,
        sensor_counts=False,
        truncated=True,  # GCS_MAVLINK::send_raw_imu / send_scaled_imu
    )


PROFILES = {"gy86": gy86, "ardupilot": ardupilot}


def board_profile(name: str) -> BoardProfile:
    """Profile by name; ValueError listing the valid names otherwise."""
    try:
        return PROFILES[name]()
    except KeyError:
        raise ValueError(f"unknown board profile {name!r}; valid: {sorted(PROFILES)}") from None
