"""The firmware's MAVLink side: turns a chunk of readings into timed MAVLink 2 packets.

What goes out (system id from the config, component MAV_COMP_ID_AUTOPILOT1):

* HEARTBEAT at 1 Hz: a quadrotor, HIL enabled, with the personality's MAV_AUTOPILOT
  (``hil.personality``) and its flight state at that instant: MAV_MODE_FLAG_SAFETY_ARMED
  in base_mode while armed, system_status ACTIVE or STANDBY as the personality says it
  (armed / disarmed; ArduPilot: in the air / on the ground); a bare board,
  ``flight_state=False``: never the armed flag, always ACTIVE;
* EXTENDED_SYS_STATE (vtol_state undefined, landed_state) when asked for, at the asked
  interval (at most one per IMU sample), with the flight state of that sample;
* the IMU stream(s) of the personality at their current rates. ``stm32``: RAW_IMU with
  every sample, the MPU6050 / HMC5883L register counts in the chips' axes (RFU) and
  ``temperature`` from TEMP_OUT in cdegC (the magnetometer fields repeat the last
  reading between its 15 Hz updates), or with ``imu_message`` SCALED_IMU (mG, mrad/s,
  mGauss) or HIGHRES_IMU (SI, gauss) converted to FRD; ``px4``: HIGHRES_IMU with the
  onboard gyro bias removed; ``ardupilot``: RAW_IMU in mG / mrad/s / mGauss (FRD) and
  SCALED_IMU2 (an overflowed magnetometer axis is converted as read). HIGHRES_IMU's
  fields_updated says what is new since the previous HIGHRES_IMU;
* ATTITUDE (and for px4 ATTITUDE_QUATERNION) from the onboard estimator
  (``hil.onboard``), stamped with the time of the sample it belongs to;
* SCALED_PRESSURE with every MS5611 reading (50 Hz), after the datasheet compensation;
* with a GPS: GPS_RAW_INT, GLOBAL_POSITION_INT and LOCAL_POSITION_NED per fix, stamped
  with the instant the fix is valid for but sent ``latency`` later (see ``hil.gps``);
* HIL_STATE_QUATERNION truth with every ``truth_divider``-th IMU sample (each sample up
  to 1 kHz), on the same board clock: attitude FRD -> NED, body rates, position and
  velocity, and the true specific force in mG.

Each packet is due at the true time of the reading it carries (heartbeats at whole
seconds), which the link uses to pace the stream.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink

from estimators import quat

from .config import EmulatorConfig
from .environment import G
from .onboard import make_onboard
from .personality import NATURAL, ON_REQUEST_STREAMS, personality
from .recording import Recording
from .source import frd_from_chip
from .streams import StreamTable

# Order of packets due at the same instant: a barometer reading goes before the IMU
# sample, so that HIGHRES_IMU can already carry it.
ORDER_HEARTBEAT, ORDER_BARO, ORDER_IMU, ORDER_ATTITUDE, ORDER_TRUTH, ORDER_GPS, ORDER_STATE = (
    range(7))
BARO_READING = "baro reading"  # internal item: a reading that may or may not go out
GPS_MESSAGES = ("GPS_RAW_INT", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED")
UINT16_UNKNOWN = 65535
HIGHRES_ACC_GYRO = 0x3F
HIGHRES_MAG = 0x1C0
HIGHRES_BARO = 0x200 | 0x800 | 0x1000  # abs pressure, pressure altitude, temperature


@dataclass(frozen=True)
class Packet:
    due_s: float  # true stream time at which it should leave
    kind: str  # MAVLink message name
    data: bytes


class Firmware:
    """Packs readings into MAVLink 2 with one sequence counter, like an autopilot.

    What it sends, and how often, follows its personality and its stream table (which
    SET_MESSAGE_INTERVAL changes through the link); its onboard estimator runs on every
    sample whether or not ATTITUDE is being sent, as a flight controller's does.
    """

    def __init__(self, config: EmulatorConfig, mpu_lsb: tuple[float, float], mag_lsb: float,
                 streams: StreamTable | None = None):
        self.config = config
        self.personality = personality(config.autopilot)
        self.mav = mavlink.MAVLink(None, srcSystem=config.sysid, srcComponent=config.compid)
        self._reply_mav = mavlink.MAVLink(None, srcSystem=config.sysid,
                                          srcComponent=config.compid)
        self.gyro_lsb_per_dps, self.accel_lsb_per_g = mpu_lsb
        self.mag_lsb_per_gauss = mag_lsb
        self.streams = streams or StreamTable(self.personality, config.imu_message,
                                              1.0 / config.imu_rate_hz, config.flight_state)
        self.onboard = make_onboard(config.autopilot, config.imu_rate_hz, self.gyro_lsb_per_dps,
                                    config.environment.magnetic_declination_deg)
        self._next_heartbeat = 0
        self._pressure_hpa = math.nan  # latest barometer reading, for HIGHRES_IMU
        self._baro_new = False
        self._mag_new: dict[str, bool] = {}  # per IMU stream: a new reading since the last sent

    def packets(self, rec: Recording, t_end: float) -> list[Packet]:
        """Every packet due in [first sample, t_end), in sending order."""
        streams = self.streams
        items: list[tuple[float, int, str, int]] = []
        period = 1.0 / self.config.heartbeat_hz
        while self._next_heartbeat * period < t_end:
            t_hb = self._next_heartbeat * period
            # the flight state of the newest sample at the heartbeat's instant
            k = int(np.clip(np.searchsorted(rec.t_s, t_hb, side="right") - 1, 0, len(rec) - 1))
            items.append((t_hb, ORDER_HEARTBEAT, "HEARTBEAT", k))
            self._next_heartbeat += 1
        # Every barometer reading reaches the firmware (HIGHRES_IMU carries the latest);
        # SCALED_PRESSURE goes out when its stream is due.
        items.extend((t, ORDER_BARO, BARO_READING, m) for m, t in enumerate(rec.baro_t_s.tolist()))
        imu_kinds = streams.active(self.personality.imu_messages)
        att_kinds = streams.active(self.personality.attitude_messages)
        truth_natural = streams.interval("HIL_STATE_QUATERNION") is NATURAL
        state_kinds = streams.active(ON_REQUEST_STREAMS)
        mag_flags: dict[tuple[str, int], bool] = {}
        for k, (t, truth, mag) in enumerate(zip(rec.t_s.tolist(), rec.truth_on_wire.tolist(),
                                                rec.mag_updated.tolist(), strict=True)):
            for kind in imu_kinds:
                self._mag_new[kind] = self._mag_new.get(kind, False) or mag
                if streams.due(kind, t):
                    items.append((t, ORDER_IMU, kind, k))
                    mag_flags[(kind, k)] = self._mag_new[kind]
                    self._mag_new[kind] = False
            items.extend((t, ORDER_ATTITUDE, kind, k) for kind in att_kinds
                         if streams.due(kind, t))
            if truth if truth_natural else streams.due("HIL_STATE_QUATERNION", t):
                items.append((t, ORDER_TRUTH, "HIL_STATE_QUATERNION", k))
            items.extend((t, ORDER_STATE, kind, k) for kind in state_kinds
                         if streams.due(kind, t))
        for g, t in enumerate(rec.gps_sent_t_s.tolist()):
            items.extend((t, ORDER_GPS, kind, g) for kind in GPS_MESSAGES if streams.due(kind, t))
        items.sort(key=lambda i: (i[0], i[1]))
        q, rates = self.onboard.run(rec)
        armed, landed = rec.armed.tolist(), rec.landed_state.tolist()
        build = {
            **self._gps_builders(rec, q),
            **{kind: self._imu_builder(rec, kind, mag_flags, rates) for kind in imu_kinds},
            **self._attitude_builders(rec, q, rates),
            "HEARTBEAT": lambda k: self.heartbeat(bool(armed[k]), landed[k]),
            "EXTENDED_SYS_STATE": lambda k: self.extended_sys_state(landed[k]),
            BARO_READING: self._scaled_pressure_builder(rec),
            "HIL_STATE_QUATERNION": self._truth_builder(rec),
        }
        out = []
        for t, _, kind, i in items:
            msg = build[kind](i)
            if kind == BARO_READING:
                if not streams.due("SCALED_PRESSURE", t):
                    continue
                kind = "SCALED_PRESSURE"
            out.append(Packet(t, kind, self._pack(msg)))
        return out

    def _pack(self, msg: mavlink.MAVLink_message) -> bytes:
        data = bytes(msg.pack(self.mav))
        # pymavlink advances the sequence number in send(), not in pack().
        self.mav.seq = (self.mav.seq + 1) % 256
        return data

    def pack_reply(self, msg: mavlink.MAVLink_message) -> bytes:
        """A reply (COMMAND_ACK, PARAM_VALUE) packed as this autopilot; its own packer,
        because replies are made in the event loop while chunks are packed in a worker
        (the link stamps the shared sequence number when sending)."""
        return bytes(msg.pack(self._reply_mav))

    def heartbeat(self, armed: bool, landed_state: int) -> mavlink.MAVLink_message:
        """HEARTBEAT for the board's flight state (a bare board: never armed, active)."""
        base_mode = mavlink.MAV_MODE_FLAG_HIL_ENABLED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        status = mavlink.MAV_STATE_ACTIVE
        if self.config.flight_state:
            if armed:
                base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            standby = (landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
                       if self.personality.status_follows_landed else not armed)
            if standby:
                status = mavlink.MAV_STATE_STANDBY
        return mavlink.MAVLink_heartbeat_message(
            type=mavlink.MAV_TYPE_QUADROTOR, autopilot=self.personality.autopilot,
            base_mode=base_mode, custom_mode=0, system_status=status, mavlink_version=3)

    @staticmethod
    def extended_sys_state(landed_state: int) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_extended_sys_state_message(
            vtol_state=mavlink.MAV_VTOL_STATE_UNDEFINED, landed_state=int(landed_state))

    def message_now(self, kind: str, armed: bool, landed_state: int
                    ) -> mavlink.MAVLink_message | None:
        """A state message (HEARTBEAT, EXTENDED_SYS_STATE) for a flight state, made on
        request (MAV_CMD_REQUEST_MESSAGE); None for any other kind, or EXTENDED_SYS_STATE
        on a bare board."""
        if kind == "HEARTBEAT":
            return self.heartbeat(armed, landed_state)
        if kind == "EXTENDED_SYS_STATE" and self.config.flight_state:
            return self.extended_sys_state(landed_state)
        return None

    # Each builder converts a whole chunk with numpy once, then makes messages by index.

    def _imu_builder(self, rec: Recording, kind: str, mag_flags: dict, rates: np.ndarray):
        temp = _int16_array(rec.temperature_c * 100.0)
        temp[temp == 0] = 1  # 0 means "no temperature" in RAW_IMU / SCALED_IMU
        temp = temp.tolist()
        acc = frd_from_chip(rec.acc_counts) * (G / self.accel_lsb_per_g)
        gyr = np.radians(frd_from_chip(rec.gyr_counts) / self.gyro_lsb_per_dps)
        mag = frd_from_chip(rec.mag_counts) / self.mag_lsb_per_gauss
        # mG, mrad/s, mGauss, FRD; ArduPilot's float -> int16 conversion truncates toward
        # zero (RAW_IMU and SCALED_IMU alike), the others' round
        cut = self.personality.name == "ardupilot"
        milli = np.hstack([_int16_array(acc / G * 1000.0, truncate=cut),
                           _int16_array(gyr * 1000.0, truncate=cut),
                           _int16_array(mag * 1000.0, truncate=cut)]).tolist()
        if kind == "RAW_IMU":
            time_us = rec.time_us.tolist()
            if cut:  # ArduPilot's RAW_IMU: the same units as its SCALED_IMU
                return lambda k: mavlink.MAVLink_raw_imu_message(time_us[k], *milli[k], 0,
                                                                 temp[k])
            rows = np.hstack([rec.acc_counts, rec.gyr_counts, rec.mag_counts]).tolist()
            return lambda k: mavlink.MAVLink_raw_imu_message(time_us[k], *rows[k], 0, temp[k])
        if kind in ("SCALED_IMU", "SCALED_IMU2"):
            time_ms = (rec.time_us // 1000).tolist()
            cls = (mavlink.MAVLink_scaled_imu_message if kind == "SCALED_IMU"
                   else mavlink.MAVLink_scaled_imu2_message)
            return lambda k: cls(time_ms[k], *milli[k], temp[k])
        if self.personality.name == "px4":
            gyr = rates  # PX4 removes its estimator's gyro bias from HIGHRES_IMU
        time_us = rec.time_us.tolist()
        rows = np.hstack([acc, gyr, mag]).tolist()
        temp_c = rec.temperature_c.tolist()

        def highres(k: int) -> mavlink.MAVLink_message:
            fields = HIGHRES_ACC_GYRO | (HIGHRES_MAG if mag_flags.get((kind, k)) else 0)
            if self._baro_new:
                fields |= HIGHRES_BARO
                self._baro_new = False
            return mavlink.MAVLink_highres_imu_message(
                time_us[k], *rows[k], self._pressure_hpa, 0.0,
                _pressure_altitude(self._pressure_hpa), temp_c[k], fields, 0)
        return highres

    def _attitude_builders(self, rec: Recording, q: np.ndarray, rates: np.ndarray) -> dict:
        """ATTITUDE / ATTITUDE_QUATERNION from the onboard estimate, at its sample time."""
        time_ms = (rec.time_us // 1000).tolist()
        euler = quat.to_euler(q).tolist()
        qs = q.tolist()
        w = rates.tolist()
        return {
            "ATTITUDE": lambda k: mavlink.MAVLink_attitude_message(time_ms[k], *euler[k], *w[k]),
            "ATTITUDE_QUATERNION": lambda k: mavlink.MAVLink_attitude_quaternion_message(
                time_ms[k], *qs[k], *w[k]),
        }

    def _scaled_pressure_builder(self, rec: Recording):
        """Every reading updates what HIGHRES_IMU carries; the message is built too."""
        time_ms = (rec.baro_time_us // 1000).tolist()
        hpa = (rec.pressure_pa / 100.0).tolist()
        temp = _int16_array(rec.baro_temp_cdeg).tolist()

        def scaled_pressure(m: int) -> mavlink.MAVLink_message:
            # Remembered for HIGHRES_IMU, which carries the latest barometer reading.
            self._pressure_hpa = hpa[m]
            self._baro_new = True
            return mavlink.MAVLink_scaled_pressure_message(time_ms[m], hpa[m], 0.0, temp[m], 0)
        return scaled_pressure

    def _truth_builder(self, rec: Recording):
        lat_deg, lon_deg, alt_m = self.config.environment.geodetic(rec.truth_position_ned)
        lat, lon, alt = np.round(lat_deg * 1e7), np.round(lon_deg * 1e7), np.round(alt_m * 1e3)
        speed = np.minimum(65535, np.round(np.linalg.norm(rec.truth_velocity_ned, axis=1) * 100))
        ints = np.column_stack([
            lat, lon, alt, _int16_array(rec.truth_velocity_ned * 100.0), speed, speed,
            _int16_array(rec.truth_specific_force / G * 1000.0)]).astype(np.int64).tolist()
        time_us = rec.time_us.tolist()
        q = rec.truth_q.tolist()
        rates = rec.truth_rates.tolist()

        def truth(k: int) -> mavlink.MAVLink_message:
            i = ints[k]
            return mavlink.MAVLink_hil_state_quaternion_message(
                time_us[k], q[k], *rates[k], *i[0:3], *i[3:6], i[6], i[7], *i[8:11])
        return truth


    def _gps_builders(self, rec: Recording, q: np.ndarray) -> dict:
        """GPS_RAW_INT, GLOBAL_POSITION_INT and LOCAL_POSITION_NED for each fix.

        GLOBAL_POSITION_INT.hdg is the onboard estimate's heading when the fix is sent
        (unknown on the stm32 board, whose 6-axis filter has no heading reference)."""
        gps = self.config.gps
        if gps is None or not len(rec.gps_t_s):
            return {}
        env = self.config.environment
        lat_deg, lon_deg, alt_m = env.geodetic(rec.gps_pos_ned)
        vel = rec.gps_vel_ned
        ground = np.hypot(vel[:, 0], vel[:, 1])
        cog = np.round(np.degrees(np.arctan2(vel[:, 1], vel[:, 0])) % 360.0 * 100.0) % 36000
        ints = np.column_stack([
            np.round(lat_deg * 1e7), np.round(lon_deg * 1e7), np.round(alt_m * 1e3),
            np.round(-rec.gps_pos_ned[:, 2] * 1e3), np.minimum(np.round(ground * 100), 65534),
            cog, _int16_array(vel * 100.0)]).astype(np.int64).tolist()
        time_us = rec.gps_time_us.tolist()
        pos = rec.gps_pos_ned.tolist()
        v = vel.tolist()
        if self.personality.name == "stm32":
            hdg = [UINT16_UNKNOWN] * len(rec.gps_t_s)
        else:
            at = np.clip(np.searchsorted(rec.t_s, rec.gps_sent_t_s, side="right") - 1, 0,
                         len(rec) - 1)
            yaw = np.degrees(quat.to_euler(q[at])[:, 2]) % 360.0
            hdg = (np.round(yaw * 100.0).astype(np.int64) % 36000).tolist()
        accuracy = (round(gps.pos_noise_h_m * 1e3), round(gps.pos_noise_v_m * 1e3),
                    round(gps.vel_noise_h_mps * 1e3))
        dop = (round(gps.hdop * 100), round(gps.vdop * 100))

        def raw(g: int) -> mavlink.MAVLink_message:
            i = ints[g]
            return mavlink.MAVLink_gps_raw_int_message(
                time_us[g], mavlink.GPS_FIX_TYPE_3D_FIX, i[0], i[1], i[2], *dop, i[4], i[5],
                gps.satellites, 0, *accuracy, 0, 0)

        def global_position(g: int) -> mavlink.MAVLink_message:
            i = ints[g]
            return mavlink.MAVLink_global_position_int_message(
                time_us[g] // 1000, i[0], i[1], i[2], i[3], i[6], i[7], i[8], hdg[g])

        def local_position(g: int) -> mavlink.MAVLink_message:
            return mavlink.MAVLink_local_position_ned_message(time_us[g] // 1000, *pos[g], *v[g])

        return {"GPS_RAW_INT": raw, "GLOBAL_POSITION_INT": global_position,
                "LOCAL_POSITION_NED": local_position}


def _int16_array(x: np.ndarray, truncate: bool = False) -> np.ndarray:
    """int16 values of x, rounded to nearest, or truncated toward zero as C's float to
    integer conversion does (what ArduPilot's RAW_IMU carries)."""
    v = np.asarray(x, dtype=float)
    v = np.trunc(v) if truncate else np.round(v)
    return np.clip(v, -32768, 32767).astype(np.int64)


def _pressure_altitude(pressure_hpa: float) -> float:
    """ISA altitude [m] for a static pressure (NaN before the first reading)."""
    if not math.isfinite(pressure_hpa) or pressure_hpa <= 0.0:
        return math.nan
    return 44330.77 * (1.0 - (pressure_hpa / 1013.25) ** 0.190263)
