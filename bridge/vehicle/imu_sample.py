"""What ingest produces and keeps: IMU sources, samples, sensor limits, counters.

Shared by ingest (which fills them), the estimating wing (which consumes samples) and
the status report (which reads the counters), so none of them imports another's
internals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..wire.mav import mavlink
from . import clock as C

MG = 9.80665e-3  # m/s^2 per milli-g
#: Readings are implausible this far beyond the sensor's full scale (scaling, calibration).
RANGE_MARGIN = 1.05

ID_RAW_IMU = mavlink.MAVLINK_MSG_ID_RAW_IMU
ID_SCALED_IMU = mavlink.MAVLINK_MSG_ID_SCALED_IMU
ID_SCALED_IMU2 = mavlink.MAVLINK_MSG_ID_SCALED_IMU2
ID_SCALED_IMU3 = mavlink.MAVLINK_MSG_ID_SCALED_IMU3
ID_HIGHRES_IMU = mavlink.MAVLINK_MSG_ID_HIGHRES_IMU
IMU_MESSAGE_IDS = frozenset((ID_RAW_IMU, ID_SCALED_IMU, ID_SCALED_IMU2, ID_SCALED_IMU3,
                             ID_HIGHRES_IMU))
IMU_MESSAGE_NAMES = {"RAW_IMU": ID_RAW_IMU, "SCALED_IMU": ID_SCALED_IMU,
                     "SCALED_IMU2": ID_SCALED_IMU2, "SCALED_IMU3": ID_SCALED_IMU3,
                     "HIGHRES_IMU": ID_HIGHRES_IMU}


class SourceKey(NamedTuple):
    """One IMU stream: the sending system and component, the message, and its IMU index.

    The message id is part of the key: RAW_IMU (µs), SCALED_IMU (ms) and HIGHRES_IMU
    (µs) of one vehicle are different streams with different clocks.
    """

    sysid: int
    compid: int
    msg: int
    imu: int


@dataclass(frozen=True)
class Limits:
    """Full scale of the sensors: a reading beyond it is not a measurement."""

    gyro_dps: float = 2000.0
    accel_g: float = 16.0
    mag_gauss: float = 8.0

    def validate(self) -> None:
        for name, v in (("gyro_range_dps", self.gyro_dps), ("accel_range_g", self.accel_g),
                        ("mag_range_gauss", self.mag_gauss)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")

    @property
    def gyro_rad_s(self) -> float:
        return math.radians(self.gyro_dps) * RANGE_MARGIN

    @property
    def accel_m_s2(self) -> float:
        return self.accel_g * 9.80665 * RANGE_MARGIN

    @property
    def mag(self) -> float:
        return self.mag_gauss * RANGE_MARGIN


@dataclass(slots=True)
class ImuSample:
    """One accepted IMU sample in SI units, body FRD."""

    key: SourceKey
    t: float  # board time [s], unwrapped
    time_boot_ms: int  # board time for outgoing messages (uint32 ms)
    dt: float | None  # [s] since the previous accepted sample; None: use the nominal rate
    gyr: np.ndarray  # rad/s
    acc: np.ndarray  # m/s^2 specific force (NaN when unusable)
    mag: np.ndarray | None  # any unit (direction only); None when absent or unusable
    arrival: float  # time.perf_counter() when the packet was read (for latency)
    restart: str | None = None  # "reboot" / "gap": start the estimate over at this sample


#: Per-source counters, by cause. Drops remove the sample; the others only flag it.
DROP_CAUSES = (C.DUPLICATE, C.REORDERED, C.JUMP, C.BACKWARDS, "nonfinite", "implausible")
FLAG_CAUSES = ("resync", "reboot", "gap", "reinit", "wrap", "gyro_saturated",
               "acc_saturated", "acc_invalid", "mag_invalid", "mag_disturbed", "stuck")


@dataclass
class SourceState:
    """Clock and counters of one source."""

    clock: C.SampleClock
    accepted: int = 0
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        DROP_CAUSES + FLAG_CAUSES, 0))
    first_arrival: float = 0.0
    last_arrival: float = 0.0
    last_raw: tuple = ()  # previous RAW_IMU gyro+accel integers, to spot a stuck sensor
    repeats: int = 0  # how many readings in a row repeated it
    repeat_from_us: int = 0  # time_usec of the reading being repeated
    stuck: bool = False  # the repeats have lasted STUCK_MIN_US: counted as stuck
    last_good_gyr: np.ndarray | None = None  # last unclipped gyro, held while clipped
    mag_norm: float = 0.0  # slow average of |mag| over accepted readings (0: none yet)
    mag_rejected_since: float = 0.0  # board time of the last accepted magnetometer reading

    @property
    def dropped(self) -> int:
        return sum(self.counts[c] for c in DROP_CAUSES)
