"""IMU messages -> SI samples in the body FRD frame, with board time and drop counting.

Reads RAW_IMU (through a board profile that states what its integers mean),
SCALED_IMU / SCALED_IMU2 / SCALED_IMU3 (mG, mrad/s, mgauss, FRD) and HIGHRES_IMU
(m/s^2, rad/s, gauss, FRD), applies the board mounting rotation and the sensor
calibration (:mod:`imu.calibration`, folded into one matrix), and stamps each
sample with the message's own time. Every source — (sysid, compid, IMU id) — has its
own clock and counters, so several vehicles or IMUs can share one link.

What happens to bad input, and why:

* timestamp problems (duplicate, late, jump, backwards): the sample is dropped and
  counted (see :mod:`bridge.clock`); the estimator never sees a wrong ``dt``;
* non-finite gyro (HIGHRES_IMU floats): dropped and counted — there is no rate to
  integrate;
* non-finite or clipped accelerometer: passed as NaN so the estimator runs gyro-only
  for that sample (it counts it), and counted here;
* clipped gyro: replaced by the last unclipped reading (a short knock or an
  over-range spin reads wrong on that axis) and counted;
* missing, overflowed or non-finite magnetometer: passed as ``None`` and counted;
* magnetometer strength far from its running average (a magnet or motor current
  nearby): passed as ``None`` and counted as ``mag_disturbed``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from imu.boards import BoardProfile
from imu.calibration import SensorCalibration

from . import clock as C
from .mav import MAVLinkMessage, mavlink

MG = 9.80665e-3  # m/s^2 per milli-g
MAG_NORM_TOLERANCE = 0.15  # relative deviation of |mag| that marks a disturbed reading
MAG_NORM_GAIN = 0.001  # per-sample weight of the running |mag| average
MAG_REANCHOR_S = 3.0

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
_SCALED_IMU_INDEX = {ID_SCALED_IMU: 0, ID_SCALED_IMU2: 1, ID_SCALED_IMU3: 2}
_ONE = (1.0,)  # appended to a message's numbers for the affine (calibrated) maps


def _affine(matrix: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """3x4 [matrix | offset]: ``v -> matrix @ v + offset`` as one multiply on (v, 1)."""
    return np.column_stack([matrix, offset])


class SourceKey(NamedTuple):
    """One IMU stream: the sending system and component, and its IMU index."""

    sysid: int
    compid: int
    imu: int


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


#: Per-source counters, by cause. Drops remove the sample; the others only flag it.
DROP_CAUSES = (C.DUPLICATE, C.REORDERED, C.JUMP, C.BACKWARDS, "clock_step", "nonfinite")
FLAG_CAUSES = ("resync", "wrap", "gyro_saturated", "acc_saturated", "acc_invalid",
               "mag_invalid", "mag_disturbed", "stuck")


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
    last_good_gyr: np.ndarray | None = None  # last unclipped gyro, held while clipped
    mag_norm: float = 0.0  # slow average of |mag| over accepted readings (0: none yet)
    mag_rejected_since: float = 0.0  # board time of the last accepted magnetometer reading

    @property
    def dropped(self) -> int:
        return sum(self.counts[c] for c in DROP_CAUSES)


class Ingest:
    """Turns IMU messages into :class:`ImuSample`; keeps per-source state."""

    def __init__(self, profile: BoardProfile, rotation: np.ndarray | None = None,
                 jump_s: float = 0.1, reorder_s: float = 0.5,
                 calibration: SensorCalibration | None = None) -> None:
        rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
        cal = SensorCalibration() if calibration is None else calibration
        self.profile = profile
        self.rotation = rot
        self.calibration = cal
        self.jump_s = jump_s
        self.reorder_s = reorder_s
        # Every "message numbers -> calibrated FRD SI" map is affine: one matrix per
        # message type acting on the numbers with a 1 appended, which folds scale,
        # axes, mounting rotation, calibration matrix and offset into a single multiply
        # (the calibration costs nothing per sample). Saturation and overflow are still
        # judged on the message's own numbers.
        gyr_m, gyr_c = cal.affine("gyro")
        acc_m, acc_c = cal.affine("accel")
        mag_m, mag_c = cal.affine("mag")
        raw_axes = rot @ profile.to_frd
        # All nine RAW_IMU integers (+1) in one multiply (one numpy call per sample).
        self._raw_all = np.zeros((9, 10))
        self._raw_all[0:3, 0:3] = gyr_m @ raw_axes * profile.gyro_scale
        self._raw_all[3:6, 3:6] = acc_m @ raw_axes * profile.accel_scale
        self._raw_all[6:9, 6:9] = mag_m @ raw_axes * profile.mag_scale
        self._raw_all[:, 9] = np.concatenate([gyr_c, acc_c, mag_c])
        self._scaled_gyr = _affine(gyr_m @ rot * 1e-3, gyr_c)
        self._scaled_acc = _affine(acc_m @ rot * MG, acc_c)
        self._scaled_mag = _affine(mag_m @ rot * 1e-3, mag_c)
        self._highres_gyr = _affine(gyr_m @ rot, gyr_c)
        self._highres_acc = _affine(acc_m @ rot, acc_c)
        self._highres_mag = _affine(mag_m @ rot, mag_c)
        self.sources: dict[SourceKey, SourceState] = {}

    def _source(self, key: SourceKey, tick_s: float, wrap: int) -> SourceState:
        state = self.sources.get(key)
        if state is None:
            state = SourceState(C.SampleClock(tick_s, wrap, self.jump_s, self.reorder_s))
            self.sources[key] = state
        return state

    def handle(self, msg: MAVLinkMessage, arrival: float | None = None) -> ImuSample | None:
        """An accepted sample for an IMU message, else None (dropped or not an IMU)."""
        msg_id = msg.get_msgId()  # not msg.id: RAW_IMU's own `id` field (IMU index) shadows it
        if msg_id == ID_RAW_IMU:
            return self._raw_imu(msg, arrival)
        if msg_id in _SCALED_IMU_INDEX:
            return self._scaled_imu(msg, _SCALED_IMU_INDEX[msg_id], arrival)
        if msg_id == ID_HIGHRES_IMU:
            return self._highres_imu(msg, arrival)
        return None

    # --- per message type ------------------------------------------------------------
    def _raw_imu(self, m: MAVLinkMessage, arrival: float | None) -> ImuSample | None:
        key = SourceKey(m.get_srcSystem(), m.get_srcComponent(), int(m.id))
        src = self._source(key, 1e-6, C.WRAP_32)
        g = (m.xgyro, m.ygyro, m.zgyro)
        a = (m.xacc, m.yacc, m.zacc)
        mg = (m.xmag, m.ymag, m.zmag)
        p = self.profile
        gyro_clipped = p.gyro_saturation is not None and max(map(abs, g)) >= p.gyro_saturation
        acc_clipped = p.accel_saturation is not None and max(map(abs, a)) >= p.accel_saturation
        mag_overflow = p.mag_overflow is not None and p.mag_overflow in mg
        # A clipped gyro axis is known to be wrong (rate beyond range, or a knock); for
        # a short event the last unclipped rate is the better guess.
        raw = g + a
        si = self._raw_all @ np.array(raw + mg + _ONE, dtype=float)
        gyr = src.last_good_gyr if gyro_clipped and src.last_good_gyr is not None else si[0:3]
        acc = np.full(3, np.nan) if acc_clipped else si[3:6]
        mag = None if mg == (0, 0, 0) or mag_overflow else si[6:9]
        sample = self._stamp(src, key, m.time_usec, 1e-6, gyr, acc, mag, arrival, raw)
        if sample is None:
            return None
        if gyro_clipped:
            src.counts["gyro_saturated"] += 1
        else:
            src.last_good_gyr = gyr
        if acc_clipped:
            src.counts["acc_saturated"] += 1
        if mag_overflow:
            src.counts["mag_invalid"] += 1
        # Noise makes two identical 6-axis raw readings in a row practically impossible:
        # a repeat means the sensor (or its driver) re-sends old data.
        if raw == src.last_raw:
            src.counts["stuck"] += 1
        src.last_raw = raw
        return sample

    def _scaled_imu(self, m: MAVLinkMessage, index: int,
                    arrival: float | None) -> ImuSample | None:
        key = SourceKey(m.get_srcSystem(), m.get_srcComponent(), index)
        src = self._source(key, 1e-3, C.WRAP_32)
        gyr = self._scaled_gyr @ (m.xgyro, m.ygyro, m.zgyro, 1.0)
        acc = self._scaled_acc @ (m.xacc, m.yacc, m.zacc, 1.0)
        mg = (m.xmag, m.ymag, m.zmag)
        mag = None if mg == (0, 0, 0) else self._scaled_mag @ (mg + _ONE)
        return self._stamp(src, key, m.time_boot_ms, 1e-3, gyr, acc, mag, arrival,
                           (m.xgyro, m.ygyro, m.zgyro, m.xacc, m.yacc, m.zacc))

    def _highres_imu(self, m: MAVLinkMessage, arrival: float | None) -> ImuSample | None:
        key = SourceKey(m.get_srcSystem(), m.get_srcComponent(), int(m.id))
        src = self._source(key, 1e-6, C.WRAP_32)
        g = (m.xgyro, m.ygyro, m.zgyro)
        if not all(map(math.isfinite, g)):
            src.counts["nonfinite"] += 1
            return None
        a = (m.xacc, m.yacc, m.zacc)
        if all(map(math.isfinite, a)):
            acc = self._highres_acc @ (a + _ONE)
        else:
            src.counts["acc_invalid"] += 1
            acc = np.full(3, np.nan)
        mg = (m.xmag, m.ymag, m.zmag)
        if mg == (0.0, 0.0, 0.0):
            mag = None
        elif all(map(math.isfinite, mg)):
            mag = self._highres_mag @ (mg + _ONE)
        else:
            src.counts["mag_invalid"] += 1
            mag = None
        return self._stamp(src, key, m.time_usec, 1e-6, self._highres_gyr @ (g + _ONE), acc,
                           mag, arrival,
                           g + a)

    def _stamp(self, src: SourceState, key: SourceKey, raw_time: int, tick_s: float,
               gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray | None,
               arrival: float | None, content: object = None) -> ImuSample | None:
        clock = src.clock
        wraps = clock.wraps
        verdict, ticks, dt = clock.classify(int(raw_time), content)
        if clock.wraps != wraps:
            src.counts["wrap"] += 1
        if verdict not in C.ACCEPTED:
            src.counts[verdict] += 1
            return None
        if verdict == C.RESYNC:
            src.counts["resync"] += 1
            # The samples dropped while confirming the new timeline were not glitches.
            for earlier in clock.reclassified:
                src.counts[earlier] -= 1
                src.counts["clock_step"] += 1
        now = time.perf_counter() if arrival is None else arrival
        if src.accepted == 0:
            src.first_arrival = now
        src.accepted += 1
        src.last_arrival = now
        t = ticks * tick_s
        if mag is not None:
            mag = self._guard_mag(src, mag, t)
        return ImuSample(key, t, round(t * 1e3) % C.WRAP_32, dt, gyr, acc, mag, now)

    def _guard_mag(self, src: SourceState, mag: np.ndarray, t: float) -> np.ndarray | None:
        """None for a reading whose strength is far from the usual (a magnet nearby).

        The Earth's field strength is constant where a vehicle flies, so a reading
        MAG_NORM_TOLERANCE off the running average is disturbed: its direction would
        pull the heading. After MAG_REANCHOR_S of continuous rejection the new strength
        is taken as the reference (e.g. a calibration change).
        """
        n = math.sqrt(float(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2]))
        ref = src.mag_norm
        if ref > 0.0 and abs(n - ref) > MAG_NORM_TOLERANCE * ref:
            if t - src.mag_rejected_since < MAG_REANCHOR_S:
                src.counts["mag_disturbed"] += 1
                return None
            ref = 0.0
        src.mag_rejected_since = t
        src.mag_norm = n if ref == 0.0 else ref + MAG_NORM_GAIN * (n - ref)
        return mag
