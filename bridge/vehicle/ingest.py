"""IMU messages -> SI samples in the body FRD frame, with board time and drop counting.

Reads RAW_IMU (through a board profile that states what its integers mean),
SCALED_IMU / SCALED_IMU2 / SCALED_IMU3 (mG, mrad/s, mgauss, FRD) and HIGHRES_IMU
(m/s^2, rad/s, gauss, FRD), applies the board mounting rotation and the sensor
calibration (:mod:`imu.calibration`, folded into one matrix), and stamps each
sample with the message's own time. Every source — (sysid, compid, message, IMU id) —
has its own clock (in its message's own units) and counters; which sources are worth
ingesting at all is the caller's choice (one primary IMU per vehicle).

What happens to bad input, and why:

* timestamp problems (duplicate, late, jump, backwards): the sample is dropped and
  counted (see :mod:`bridge.vehicle.clock`); the estimator never sees a wrong ``dt``. A new
  timeline is adopted only on sustained evidence; a reboot, or an outage longer than
  ``reinit_gap_s``, marks the next sample ``restart`` so that the estimate starts over
  instead of continuing from a stale attitude;
* non-finite gyro (HIGHRES_IMU floats): dropped and counted — there is no rate to
  integrate;
* a gyro or accelerometer reading beyond what the sensor can measure (``Limits``; a
  float field can carry anything): dropped and counted as ``implausible`` — it is a
  forged or corrupted value, and integrating it would turn the attitude silently;
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
from typing import NamedTuple

import numpy as np

from imu.boards import BoardProfile
from imu.calibration import SensorCalibration

from ..wire.mav import MAVLinkMessage
from . import clock as C
from .imu_sample import (
    DROP_CAUSES,
    FLAG_CAUSES,
    ID_HIGHRES_IMU,
    ID_RAW_IMU,
    ID_SCALED_IMU,
    ID_SCALED_IMU2,
    ID_SCALED_IMU3,
    IMU_MESSAGE_IDS,
    IMU_MESSAGE_NAMES,
    MG,
    ImuSample,
    Limits,
    SourceKey,
    SourceState,
)
from .sensor_checks import guard_mag, stuck_flags

__all__ = ["DROP_CAUSES", "FLAG_CAUSES", "IMU_MESSAGE_IDS", "IMU_MESSAGE_NAMES", "ImuSample",
           "Ingest", "Limits", "SourceKey", "SourceState"]

_SCALED_IMU_INDEX = {ID_SCALED_IMU: 0, ID_SCALED_IMU2: 1, ID_SCALED_IMU3: 2}
_ONE = (1.0,)  # appended to a message's numbers for the affine (calibrated) maps


def _half_step_out(counts: tuple[int, ...]) -> tuple[float, ...]:
    """Truncated integers as the middle of what they stand for: k ± ½, 0 as 0."""
    return tuple(c + 0.5 if c > 0 else c - 0.5 if c < 0 else 0.0 for c in counts)


def _affine(matrix: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """3x4 [matrix | offset]: ``v -> matrix @ v + offset`` as one multiply on (v, 1)."""
    return np.column_stack([matrix, offset])


class _RawMap(NamedTuple):
    """One board profile's RAW_IMU map (see Ingest._raw_map)."""

    profile: BoardProfile
    linear: np.ndarray  # 9x9: the message's nine numbers -> calibrated FRD SI
    offset: np.ndarray  # 9: the calibration offsets
    gyr_max: float  # counts
    acc_max: float


class _Pending(NamedTuple):
    """A converted reading waiting for the clock's verdict (``flags``: counted when used)."""

    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray | None
    arrival: float
    flags: tuple[str, ...]


class Ingest:
    """Turns IMU messages into :class:`ImuSample`; keeps per-source state."""

    def __init__(self, profile: BoardProfile, rotation: np.ndarray | None = None,
                 jump_s: float = 0.1, reorder_s: float = 0.5,
                 calibration: SensorCalibration | None = None,
                 limits: Limits | None = None, resync_s: float = 1.0,
                 reinit_gap_s: float = 1.0) -> None:
        rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
        cal = SensorCalibration() if calibration is None else calibration
        self.profile = profile
        self.rotation = rot
        self.calibration = cal
        self.jump_s = jump_s
        self.reorder_s = reorder_s
        self.resync_s = resync_s
        self.reinit_gap_s = reinit_gap_s
        lim = Limits() if limits is None else limits
        self.limits = lim
        # Every "message numbers -> calibrated FRD SI" map is affine: one matrix per
        # message type acting on the numbers with a 1 appended, which folds scale,
        # axes, mounting rotation, calibration matrix and offset into a single multiply
        # (the calibration costs nothing per sample). Saturation and overflow are still
        # judged on the message's own numbers.
        gyr_m, gyr_c = cal.affine("gyro")
        acc_m, acc_c = cal.affine("accel")
        mag_m, mag_c = cal.affine("mag")
        self._raw_maps: dict[str, _RawMap] = {}
        self._raw_default = self._raw_map(profile)
        #: RAW_IMU board profile per system id where it is not ``profile`` (the
        #: vehicle's autopilot decides what its integers mean; see set_board).
        self._raw_by_sysid: dict[int, _RawMap] = {}
        #: system ids whose SCALED_IMU integers are truncated, not rounded (ArduPilot's:
        #: see imu.boards.BoardProfile.truncated), read as the middle of their step
        self._scaled_truncated: set[int] = set()
        self._scaled_gyr = _affine(gyr_m @ rot * 1e-3, gyr_c)
        self._scaled_acc = _affine(acc_m @ rot * MG, acc_c)
        self._scaled_mag = _affine(mag_m @ rot * 1e-3, mag_c)
        self._highres_gyr = _affine(gyr_m @ rot, gyr_c)
        self._highres_acc = _affine(acc_m @ rot, acc_c)
        self._highres_mag = _affine(mag_m @ rot, mag_c)
        # Range checks on the message's own numbers (cheap, before any conversion).
        self._scaled_gyr_max = lim.gyro_rad_s * 1e3  # mrad/s
        self._scaled_acc_max = lim.accel_m_s2 / MG  # mG
        self.sources: dict[SourceKey, SourceState] = {}

    def _raw_map(self, profile: BoardProfile) -> _RawMap:
        """All nine RAW_IMU integers -> calibrated FRD SI in one multiply and one add
        per sample, and the profile's range limits in its counts."""
        cached = self._raw_maps.get(profile.name)
        if cached is not None:
            return cached
        gyr_m, gyr_c = self.calibration.affine("gyro")
        acc_m, acc_c = self.calibration.affine("accel")
        mag_m, mag_c = self.calibration.affine("mag")
        raw_axes = self.rotation @ profile.to_frd
        m = np.zeros((9, 9))
        m[0:3, 0:3] = gyr_m @ raw_axes * profile.gyro_scale
        m[3:6, 3:6] = acc_m @ raw_axes * profile.accel_scale
        m[6:9, 6:9] = mag_m @ raw_axes * profile.mag_scale
        made = self._raw_maps[profile.name] = _RawMap(
            profile, m, np.concatenate([gyr_c, acc_c, mag_c]),
            self.limits.gyro_rad_s / profile.gyro_scale,
            self.limits.accel_m_s2 / profile.accel_scale)
        return made

    def board_of(self, sysid: int) -> BoardProfile:
        return self._raw_by_sysid.get(sysid, self._raw_default).profile

    def set_board(self, sysid: int, profile: BoardProfile) -> bool:
        """Read this vehicle's RAW_IMU with ``profile`` from now on; True if that changed
        it (the caller restarts its RAW_IMU sources: their samples meant something else)."""
        if self.board_of(sysid).name == profile.name:
            return False
        self._raw_by_sysid[sysid] = self._raw_map(profile)
        return True

    def scaled_truncated(self, sysid: int) -> bool:
        return sysid in self._scaled_truncated

    def set_scaled_truncated(self, sysid: int, truncated: bool) -> None:
        """Whether this vehicle's SCALED_IMU integers are truncated toward zero (its
        autopilot decides; ArduPilot's are)."""
        if truncated:
            self._scaled_truncated.add(sysid)
        else:
            self._scaled_truncated.discard(sysid)

    def _source(self, key: SourceKey, tick_s: float, wrap: int) -> SourceState:
        state = self.sources.get(key)
        if state is None:
            state = SourceState(C.SampleClock(tick_s, wrap, self.jump_s, self.reorder_s,
                                              self.resync_s))
            self.sources[key] = state
        return state

    def forget(self, key: SourceKey) -> None:
        """Drop a source's state (it went silent, or it is no longer wanted)."""
        self.sources.pop(key, None)

    @staticmethod
    def key_of(msg: MAVLinkMessage) -> SourceKey | None:
        """The source an IMU message belongs to, None for other messages."""
        msg_id = msg.get_msgId()  # not msg.id: RAW_IMU's `id` field (IMU index) shadows it
        if msg_id in (ID_RAW_IMU, ID_HIGHRES_IMU):
            return SourceKey(msg.get_srcSystem(), msg.get_srcComponent(), msg_id, int(msg.id))
        if msg_id in _SCALED_IMU_INDEX:
            return SourceKey(msg.get_srcSystem(), msg.get_srcComponent(), msg_id,
                             _SCALED_IMU_INDEX[msg_id])
        return None

    def handle(self, msg: MAVLinkMessage, arrival: float | None = None) -> ImuSample | None:
        """The newest accepted sample for an IMU message, else None (dropped, held as
        evidence for a new timeline, or not an IMU)."""
        samples = self.handle_all(msg, arrival)
        return samples[-1] if samples else None

    def handle_all(self, msg: MAVLinkMessage, arrival: float | None = None,
                   key: SourceKey | None = None) -> list[ImuSample]:
        """Every sample this message makes usable, in order: usually one; none when it is
        dropped; several when it completes the evidence for a new timeline (the held
        samples come out with it)."""
        key = key or self.key_of(msg)
        if key is None:
            return []
        now = time.perf_counter() if arrival is None else arrival
        if key.msg == ID_RAW_IMU:
            return self._raw_imu(msg, key, now)
        if key.msg == ID_HIGHRES_IMU:
            return self._highres_imu(msg, key, now)
        return self._scaled_imu(msg, key, now)

    def scaled_mag(self, msg: MAVLinkMessage) -> np.ndarray | None:
        """A SCALED_IMU message's field in gauss, FRD, mounted and calibrated (None: it
        carries none): part of every SCALED_IMU sample, and alone a PX4's raw
        magnetometer beside HIGHRES_IMU (:mod:`imu.px4_mag`)."""
        mg = (msg.xmag, msg.ymag, msg.zmag)
        if mg == (0, 0, 0):
            return None
        if msg.get_srcSystem() in self._scaled_truncated:
            mg = _half_step_out(mg)
        return self._scaled_mag @ (mg + _ONE)

    # --- per message type ------------------------------------------------------------
    def _raw_imu(self, m: MAVLinkMessage, key: SourceKey, arrival: float) -> list[ImuSample]:
        src = self._source(key, 1e-6, C.WRAP_32)
        g = (m.xgyro, m.ygyro, m.zgyro)
        a = (m.xacc, m.yacc, m.zacc)
        mg = (m.xmag, m.ymag, m.zmag)
        raw_map = self._raw_by_sysid.get(key.sysid, self._raw_default)
        if max(map(abs, g)) > raw_map.gyr_max or max(map(abs, a)) > raw_map.acc_max:
            src.counts["implausible"] += 1
            return []
        p = raw_map.profile
        gyro_clipped = p.gyro_saturation is not None and max(map(abs, g)) >= p.gyro_saturation
        acc_clipped = p.accel_saturation is not None and max(map(abs, a)) >= p.accel_saturation
        mag_overflow = p.mag_overflow is not None and p.mag_overflow in mg
        raw = g + a
        numbers = p.centred(np.array(raw + mg, dtype=float))  # half steps, if truncated
        si = raw_map.linear @ numbers + raw_map.offset
        acc = np.full(3, np.nan) if acc_clipped else si[3:6]
        mag = None if mg == (0, 0, 0) or mag_overflow else si[6:9]
        flags: tuple[str, ...] = ()
        if gyro_clipped:
            flags += ("gyro_saturated",)
        if acc_clipped:
            flags += ("acc_saturated",)
        if mag_overflow:
            flags += ("mag_invalid",)
        if p.sensor_counts:
            flags += stuck_flags(src, raw, m.time_usec)
        return self._stamp(src, key, m.time_usec, 1e-6,
                           _Pending(si[0:3], acc, mag, arrival, flags), raw)

    def _scaled_imu(self, m: MAVLinkMessage, key: SourceKey,
                    arrival: float) -> list[ImuSample]:
        src = self._source(key, 1e-3, C.WRAP_32)
        g = (m.xgyro, m.ygyro, m.zgyro)
        a = (m.xacc, m.yacc, m.zacc)
        if max(map(abs, g)) > self._scaled_gyr_max or max(map(abs, a)) > self._scaled_acc_max:
            src.counts["implausible"] += 1
            return []
        if key.sysid in self._scaled_truncated:
            g_si, a_si = _half_step_out(g), _half_step_out(a)
        else:
            g_si, a_si = g, a
        gyr = self._scaled_gyr @ (g_si + _ONE)
        acc = self._scaled_acc @ (a_si + _ONE)
        mag = self.scaled_mag(m)
        return self._stamp(src, key, m.time_boot_ms, 1e-3,
                           _Pending(gyr, acc, mag, arrival, ()), g + a)

    def _highres_imu(self, m: MAVLinkMessage, key: SourceKey,
                     arrival: float) -> list[ImuSample]:
        src = self._source(key, 1e-6, C.WRAP_32)
        g = (m.xgyro, m.ygyro, m.zgyro)
        if not all(map(math.isfinite, g)):
            src.counts["nonfinite"] += 1
            return []
        lim = self.limits
        a = (m.xacc, m.yacc, m.zacc)
        a_ok = all(map(math.isfinite, a))
        # `not x <= limit` is also true for NaN.
        if not max(map(abs, g)) <= lim.gyro_rad_s or \
                (a_ok and not max(map(abs, a)) <= lim.accel_m_s2):
            src.counts["implausible"] += 1
            return []
        flags: tuple[str, ...] = ()
        if a_ok:
            acc = self._highres_acc @ (a + _ONE)
        else:
            flags += ("acc_invalid",)
            acc = np.full(3, np.nan)
        mg = (m.xmag, m.ymag, m.zmag)
        if mg == (0.0, 0.0, 0.0):
            mag = None
        elif all(map(math.isfinite, mg)) and max(map(abs, mg)) <= lim.mag:
            mag = self._highres_mag @ (mg + _ONE)
        else:
            flags += ("mag_invalid",)
            mag = None
        return self._stamp(src, key, m.time_usec, 1e-6,
                           _Pending(self._highres_gyr @ (g + _ONE), acc, mag, arrival, flags),
                           g + a)

    def _stamp(self, src: SourceState, key: SourceKey, raw_time: int, tick_s: float,
               pending: _Pending, content: object) -> list[ImuSample]:
        clock = src.clock
        wraps = clock.wraps
        v = clock.classify(int(raw_time), pending.arrival, content, pending)
        if clock.wraps != wraps:
            src.counts["wrap"] += 1
        if not v.accepted:
            src.counts[v.verdict] += 1
            return []
        restart = None
        if v.verdict in (C.RESYNC, C.REBOOT):
            src.counts[v.verdict] += 1
            # The samples held while confirming the new timeline were not glitches.
            for earlier in v.reclassified:
                src.counts[earlier] -= 1
        if v.verdict == C.GAP:
            src.counts["gap"] += 1
        if v.verdict == C.REBOOT:
            restart = C.REBOOT
        elif v.verdict in (C.GAP, C.RESYNC) and v.gap_s >= self.reinit_gap_s:
            restart = C.GAP
        if restart is not None:
            src.counts["reinit"] += 1
        out = []
        for i, acc in enumerate(v.accepted):
            p: _Pending = acc.payload
            for flag in p.flags:
                src.counts[flag] += 1
            gyr = p.gyr
            if "gyro_saturated" in p.flags and src.last_good_gyr is not None:
                # A clipped gyro axis is known to be wrong (rate beyond range, or a
                # knock); for a short event the last unclipped rate is the better guess.
                gyr = src.last_good_gyr
            else:
                src.last_good_gyr = gyr
            if src.accepted == 0:
                src.first_arrival = p.arrival
            src.accepted += 1
            src.last_arrival = p.arrival
            t = acc.ticks * tick_s
            first_of_timeline = i == 0 and v.verdict != C.OK
            if first_of_timeline:
                src.mag_rejected_since = t  # time moved: re-anchoring counts from here
            mag = p.mag
            if mag is not None:
                mag = guard_mag(src, mag, t)
            out.append(ImuSample(key, t, round(t * 1e3) % C.WRAP_32, acc.dt, gyr, p.acc, mag,
                                 p.arrival, restart if i == 0 else None))
        return out
