"""Which flight controller the emulated board pretends to be, on the link.

A listener (the bridge, a ground station) meets very different autopilots; the
emulator can be each of them so that a listener's negotiation is tested against what
the real ones do (PX4 and ArduPilot behaviour taken from their MAVLink sources):

* ``stm32`` — the seeds' hobby board (MAV_AUTOPILOT_GENERIC): raw MPU6050/HMC5883L
  counts in RAW_IMU at every sample, the seeds' 6-axis Mahony ``IMUupdate`` on board,
  ATTITUDE at 50 Hz. Its small firmware streams what it has and denies the rest; it
  has no parameters.
* ``px4`` — MAV_AUTOPILOT_PX4: HIGHRES_IMU (SI, FRD, gauss, gyro bias removed with its
  estimator's bias) at 50 Hz until asked otherwise, ATTITUDE and ATTITUDE_QUATERNION
  from its onboard estimator (a Mahony-type filter like PX4's attitude_estimator_q).
  It has no RAW_IMU stream: ``set_message_interval`` finds no stream of that id and
  the command is answered MAV_RESULT_FAILED. Declination parameter ``EKF2_MAG_DECL``
  [deg].
* ``ardupilot`` — MAV_AUTOPILOT_ARDUPILOTMEGA: RAW_IMU in ArduPilot's units (mG, mrad/s,
  mGauss, FRD) and SCALED_IMU2, ATTITUDE from its onboard filter; unknown message ids
  are MAV_RESULT_FAILED; intervals are kept in whole milliseconds (at least 1 ms).
  Declination parameter ``COMPASS_DEC`` [rad]; ``INS_GYRO_FILTER`` 0 (its samples
  are sent as measured, where a real ArduPilot low-passes them: imu.filter_delay).

Every personality also sends SCALED_PRESSURE, the GPS messages when a GPS is fitted,
and the emulator's HIL_STATE_QUATERNION truth.

Every personality tells its flight state as PX4 and ArduPilot do, so that a listener
can learn to trust (or not) what an autopilot says about flying:

* HEARTBEAT base_mode has MAV_MODE_FLAG_SAFETY_ARMED while armed. system_status is
  STANDBY when disarmed and ACTIVE when armed for PX4 (from its arming state) and the
  seeds' board; ArduPilot's follows Copter's ``vehicle_system_status`` (STANDBY while
  ``land_complete``): STANDBY on the ground, armed or not, ACTIVE from take-off to
  touchdown (``status_follows_landed``).
* EXTENDED_SYS_STATE (vtol_state undefined, landed_state) is a stream that is off until
  asked for (SET_MESSAGE_INTERVAL; 1 Hz for "the default rate") or sent once for
  MAV_CMD_REQUEST_MESSAGE.

A bare board (``EmulatorConfig.flight_state=False``) tells neither: no armed flag ever
(system_status always ACTIVE), and no EXTENDED_SYS_STATE stream.

MAV_CMD_REQUEST_MESSAGE for a message without a stream is refused with
``request_refused_result``: PX4 DENIED (its ``handle_request_message_command``),
ArduPilot FAILED (no ``ap_message`` for the id), the seeds' board DENIED.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink

AUTOPILOTS = ("stm32", "px4", "ardupilot")
#: Streams every personality has, at their natural rate unless asked otherwise.
COMMON_STREAMS = ("SCALED_PRESSURE", "GPS_RAW_INT", "GLOBAL_POSITION_INT",
                  "LOCAL_POSITION_NED", "HIL_STATE_QUATERNION")
#: A stream at its natural rate: every sample / reading / fix.
NATURAL = None
#: Streams every personality has but only sends when asked, with the interval [s] that
#: "the default rate" (SET_MESSAGE_INTERVAL with 0 µs) gives them.
ON_REQUEST_STREAMS = {"EXTENDED_SYS_STATE": 1.0}


@dataclass(frozen=True)
class Personality:
    name: str
    autopilot: int  # MAV_AUTOPILOT_* in HEARTBEAT
    imu_messages: tuple[str, ...]  # IMU streams it can send (first: its default)
    attitude_messages: tuple[str, ...]  # its onboard estimate
    #: Initial interval [s] per stream: NATURAL (every sample/reading/fix) or seconds.
    defaults: dict[str, float | None]
    refused_result: int  # COMMAND_ACK result for a message it has no stream of
    declination_param: str | None  # its magnetic declination parameter, if any
    declination_unit: str = "deg"  # "deg" or "rad"
    whole_ms: bool = False  # intervals kept in whole milliseconds (ArduPilot)
    #: COMMAND_ACK result of MAV_CMD_REQUEST_MESSAGE for a message it has no stream of
    request_refused_result: int = mavlink.MAV_RESULT_DENIED
    #: MAV_CMD_REQUEST_MESSAGE: the ACK goes before the message (ArduPilot queues it)
    ack_before_requested: bool = False
    #: HEARTBEAT system_status STANDBY on the ground, ACTIVE in the air (ArduPilot),
    #: instead of STANDBY disarmed, ACTIVE armed (PX4)
    status_follows_landed: bool = False
    #: other parameters it answers (name -> value, REAL32)
    params: tuple[tuple[str, float], ...] = ()

    @property
    def streams(self) -> tuple[str, ...]:
        return self.imu_messages + self.attitude_messages + COMMON_STREAMS


STM32 = Personality(
    name="stm32", autopilot=mavlink.MAV_AUTOPILOT_GENERIC,
    imu_messages=("RAW_IMU", "SCALED_IMU", "HIGHRES_IMU"), attitude_messages=("ATTITUDE",),
    defaults={"ATTITUDE": 0.02}, refused_result=mavlink.MAV_RESULT_DENIED,
    declination_param=None)

PX4 = Personality(
    name="px4", autopilot=mavlink.MAV_AUTOPILOT_PX4,
    imu_messages=("HIGHRES_IMU", "SCALED_IMU"),
    attitude_messages=("ATTITUDE", "ATTITUDE_QUATERNION"),
    defaults={"HIGHRES_IMU": 0.02, "ATTITUDE": 0.02, "ATTITUDE_QUATERNION": 0.02},
    refused_result=mavlink.MAV_RESULT_FAILED, declination_param="EKF2_MAG_DECL")

ARDUPILOT = Personality(
    name="ardupilot", autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    imu_messages=("RAW_IMU", "SCALED_IMU2"), attitude_messages=("ATTITUDE",),
    defaults={"RAW_IMU": 0.02, "SCALED_IMU2": 0.02, "ATTITUDE": 0.02},
    refused_result=mavlink.MAV_RESULT_FAILED, declination_param="COMPASS_DEC",
    declination_unit="rad", whole_ms=True, request_refused_result=mavlink.MAV_RESULT_FAILED,
    ack_before_requested=True, status_follows_landed=True,
    # the emulated sensors' samples go out as measured, not low-passed: the filter is off
    params=(("INS_GYRO_FILTER", 0.0),))

PERSONALITIES = {p.name: p for p in (STM32, PX4, ARDUPILOT)}


def personality(name: str) -> Personality:
    """The personality by name; ValueError listing the valid ones."""
    try:
        return PERSONALITIES[name]
    except KeyError:
        raise ValueError(f"unknown autopilot {name!r}; valid: {', '.join(AUTOPILOTS)}") from None
