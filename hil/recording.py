"""Arrays of everything the emulated board produced, plus the truth behind it.

One ``Recording`` holds a stretch of IMU samples (index k) and barometer samples
(index m). Vectors named ``*_counts`` are raw register values in the chips' axes (RFU:
X right, Y forward, Z up), exactly what RAW_IMU carries. ``gyr``/``acc``/``mag`` are the
same readings converted to SI (rad/s, m/s^2, gauss) in the FRD body frame, as a flight
controller (or the bridge's ``gy86`` board profile) would; a magnetometer vector with an
overflowed axis (-4096) is NaN.

The magnetometer updates at its own rate (15 Hz by default); between updates the board
holds (and re-sends) the last reading: ``mag_counts``/``mag`` are held values and
``mag_updated`` marks the samples where a new reading arrived.

With a GPS (``EmulatorConfig.gps``), ``gps_*`` hold its fixes (index g) exactly as sent:
``gps_t_s`` the instant each is valid for, ``gps_time_us`` that instant on the board clock
(the stamp on the wire), ``gps_sent_t_s`` when it went out (latency later), the measured
``gps_vel_ned`` / ``gps_pos_ned`` (float32 values, as in LOCAL_POSITION_NED) and the true
velocity at the fix. ``gps_aiding()`` turns them into the estimators' ``vel``/``vel_age``.

Truth is given for every IMU sample, on the same board clock (``truth_time_us`` is
``time_us``); ``truth_on_wire`` marks those also sent as HIL_STATE_QUATERNION.
``armed`` and ``landed_state`` (MAV_LANDED_STATE: 1 on ground, 2 in air, 3 take-off,
4 landing) are the true flight state at each sample (``Profile.flight_state``), whether
or not the board tells it on the link (``EmulatorConfig.flight_state``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from .faults import FaultCounts
from .gps import aiding_at_samples


@dataclass
class Recording:
    # IMU samples (N)
    time_us: np.ndarray  # board clock [µs since boot]
    t_s: np.ndarray  # true time since the first sample [s]
    gyr_counts: np.ndarray  # (N, 3) int16, chip axes
    acc_counts: np.ndarray
    mag_counts: np.ndarray  # held between magnetometer updates
    temp_raw: np.ndarray  # (N,) int16 MPU6050 TEMP_OUT
    mag_updated: np.ndarray  # (N,) bool
    gyr: np.ndarray  # (N, 3) rad/s FRD
    acc: np.ndarray  # (N, 3) m/s^2 FRD (specific force)
    mag: np.ndarray  # (N, 3) gauss FRD, NaN on overflow
    temperature_c: np.ndarray  # (N,) from TEMP_OUT
    truth_q: np.ndarray  # (N, 4) FRD body -> NED
    truth_rates: np.ndarray  # (N, 3) rad/s FRD
    truth_specific_force: np.ndarray  # (N, 3) m/s^2 FRD
    truth_mag: np.ndarray  # (N, 3) Earth's field in the body [gauss], no disturbance
    truth_position_ned: np.ndarray  # (N, 3) m
    truth_velocity_ned: np.ndarray  # (N, 3) m/s
    truth_on_wire: np.ndarray  # (N,) bool
    armed: np.ndarray  # (N,) bool, the true flight state
    landed_state: np.ndarray  # (N,) uint8 MAV_LANDED_STATE
    # barometer samples (M)
    baro_time_us: np.ndarray
    baro_t_s: np.ndarray
    baro_d1: np.ndarray  # 24-bit ADC words
    baro_d2: np.ndarray
    pressure_pa: np.ndarray  # board-compensated P [Pa = 0.01 mbar], int
    baro_temp_cdeg: np.ndarray  # board-compensated TEMP [0.01 °C], int
    truth_pressure_pa: np.ndarray
    # GPS fixes (G), empty without a GPS
    gps_t_s: np.ndarray  # valid at [true s]
    gps_time_us: np.ndarray  # valid at [board µs], as stamped on the wire
    gps_sent_t_s: np.ndarray  # sent at [true s]
    gps_vel_ned: np.ndarray  # (G, 3) m/s, measured
    gps_pos_ned: np.ndarray  # (G, 3) m from home, measured
    gps_truth_vel_ned: np.ndarray  # (G, 3) m/s at gps_t_s
    #: Faults injected while producing these samples (set by ``simulate``).
    faults: FaultCounts | None = None

    @property
    def truth_time_us(self) -> np.ndarray:
        return self.time_us

    def gps_aiding(self) -> tuple[np.ndarray, np.ndarray]:
        """(vel (N, 3) NED with NaN rows, vel_age (N,) s) per IMU sample: each fix at
        the first IMU sample sent after it, aged by the board stamps."""
        return aiding_at_samples(self.t_s, self.time_us, self.gps_sent_t_s, self.gps_time_us,
                                 self.gps_vel_ned)

    def __len__(self) -> int:
        return len(self.time_us)

    @classmethod
    def concatenate(cls, parts: list[Recording]) -> Recording:
        return cls(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                      for f in _array_fields()})


def _array_fields() -> list:
    return [f for f in fields(Recording) if f.name != "faults"]
