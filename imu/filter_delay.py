"""How late an autopilot's IMU stream is: the low-pass filter it runs before sending.

ArduPilot sends RAW_IMU and SCALED_IMU/2/3 from the gyro its rate controller uses, after
the ``INS_GYRO_FILTER`` [Hz] low-pass (a 2-pole Butterworth; by default 20 Hz on
copters, helicopters and planes, 4 Hz on rovers and boats; 0 turns it off), and the
accelerometer after ``INS_ACCEL_FILTER`` (the same defaults). An attitude integrated
from such samples describes the body one group delay ago: for a 2-pole Butterworth at
frequencies well below its cut-off that is ``√2 / (2π·f_c)``, 11.3 ms at 20 Hz, which is
0.65° of attitude at 1 rad/s. The estimators take it as ``imu_delay`` and carry their
output forward by it (``estimators.base.turned_forward``); the filter being the same on
gyro and accelerometer, the estimate itself stays consistent.

PX4's HIGHRES_IMU comes from ``sensor_combined``: the driver's samples integrated, not
the rate controller's low-pass (``IMU_GYRO_CUTOFF``), so no delay is taken. The GY-86
emulator and a bare board send what the sensor measured: none either.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

#: MAV_AUTOPILOT_ARDUPILOTMEGA
ARDUPILOT = 3
GYRO_FILTER_PARAM = "INS_GYRO_FILTER"
#: ArduPilot's default INS_GYRO_FILTER [Hz] by MAV_TYPE where it differs from 20 Hz:
#: ground rover and surface boat (Rover firmware).
_DEFAULT_CUTOFF_HZ = {10: 4.0, 11: 4.0}
DEFAULT_CUTOFF_HZ = 20.0
#: Lowest cut-off taken [Hz]: a lower one is no filter a flight controller runs, and
#: the delay would exceed what the estimators accept (``MAX_IMU_DELAY_S``).
MIN_CUTOFF_HZ = 2.5


@dataclass(frozen=True)
class FilterDelay:
    """The IMU stream's delay [s] and where it came from (shown to the user)."""

    seconds: float
    source: str

    @property
    def ms(self) -> float:
        return self.seconds * 1e3

    @property
    def from_parameter(self) -> bool:
        """The vehicle's own INS_GYRO_FILTER gave it (not a default or a fallback)."""
        return self.source.startswith(GYRO_FILTER_PARAM)


NONE = FilterDelay(0.0, "none")


def butterworth2_delay_s(cutoff_hz: float) -> float:
    """Group delay at low frequency of a 2-pole Butterworth low-pass: √2 / (2π·f_c)."""
    return math.sqrt(2.0) / (2.0 * math.pi * cutoff_hz)


def default_cutoff_hz(mav_type: int | None) -> float:
    """ArduPilot's default INS_GYRO_FILTER for a vehicle of this MAV_TYPE."""
    return _DEFAULT_CUTOFF_HZ.get(-1 if mav_type is None else int(mav_type),
                                  DEFAULT_CUTOFF_HZ)


def from_cutoff(cutoff_hz: float, source: str) -> FilterDelay:
    """The delay of an INS_GYRO_FILTER value; ValueError for one that is no cut-off."""
    if not math.isfinite(cutoff_hz) or cutoff_hz < 0.0:
        raise ValueError(f"{GYRO_FILTER_PARAM} = {cutoff_hz!r} is no cut-off frequency")
    if cutoff_hz == 0.0:
        return FilterDelay(0.0, f"{source} 0 (filter off)")
    if cutoff_hz < MIN_CUTOFF_HZ:
        raise ValueError(f"{GYRO_FILTER_PARAM} = {cutoff_hz:g} Hz is below "
                         f"{MIN_CUTOFF_HZ:g} Hz")
    return FilterDelay(butterworth2_delay_s(cutoff_hz), f"{source} {cutoff_hz:g} Hz")


def imu_filter_delay(autopilot: int | None, params: Mapping[str, float],
                     mav_type: int | None = None) -> FilterDelay:
    """The delay of the IMU messages ``autopilot`` (MAV_AUTOPILOT) sends (ArduPilot
    fills every one of them from its filtered gyro and accelerometer), from its
    ``INS_GYRO_FILTER`` in ``params`` when known, else ArduPilot's default for the
    vehicle type. A value that is no cut-off falls back to the default, said in the
    source."""
    if autopilot != ARDUPILOT:
        return NONE
    default = from_cutoff(default_cutoff_hz(mav_type), f"ArduPilot default {GYRO_FILTER_PARAM}")
    value = params.get(GYRO_FILTER_PARAM)
    if value is None:
        return default
    try:
        return from_cutoff(float(value), GYRO_FILTER_PARAM)
    except ValueError as err:
        return FilterDelay(default.seconds, f"{default.source} ({err})")
