"""MAVLink telemetry log (.tlog): IMU messages and attitude references, by their own clocks.

IMU, in order of preference (or ``imu=`` to choose): HIGHRES_IMU (SI, gauss), RAW_IMU
(integers whose meaning depends on the sender: a ``imu.boards`` profile, default
``ardupilot`` = mG, mrad/s, mGauss in FRD), SCALED_IMU/2/3 (mG, mrad/s, mgauss, FRD).
References: HIL_STATE_QUATERNION is truth; ATTITUDE_QUATERNION, else ATTITUDE (Z-Y-X
Euler), from the same vehicle component as the IMU is the autopilot's own estimate.
Time is ``time_usec`` / ``time_boot_ms`` from the messages, never the log's arrival stamp.
"""

from __future__ import annotations

import os
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from estimators import quat as Q

from ..dataset import Recording, Reference, ReplayInputError
from ..timebase import sample_and_hold
from ._common import clean_stream, make_reference

os.environ["MAVLINK20"] = "1"

IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")
REFERENCE_MESSAGES = ("HIL_STATE_QUATERNION", "ATTITUDE_QUATERNION", "ATTITUDE")
G = 9.80665
HIGHRES_MAG_BITS = 0x1C0  # fields_updated bits 6..8: xmag, ymag, zmag
REBOOT_JUMP_S = 1.0  # board time going back by more than this: the vehicle rebooted
SESSION_PAD_S = 1.0  # reference messages this close to a session's ends belong to it


def read(path: Path, board: str = "ardupilot", imu: str | None = None,
         reference: str = "auto") -> Recording:
    from imu.boards import board_profile

    profile = board_profile(board)
    if imu is not None and imu.upper() not in IMU_MESSAGES:
        raise ReplayInputError(f"unknown IMU message {imu!r}; valid: {list(IMU_MESSAGES)}")
    messages = _collect(path)
    imu_type, src = _pick_imu(messages, imu.upper() if imu else None, path)
    rows = [m for m in messages[imu_type] if (m.get_srcSystem(), m.get_srcComponent()) == src]
    if imu_type == "RAW_IMU":  # several IMUs share RAW_IMU, told apart by `id`
        ids = Counter(getattr(m, "id", 0) for m in rows)
        rows = [m for m in rows if getattr(m, "id", 0) == min(ids)]
    t, gyr, acc, mag = _imu_arrays(imu_type, rows, profile)
    notes = [f"IMU {imu_type} from system {src[0]} component {src[1]}"
             + (f" (board profile {profile.name})" if imu_type == "RAW_IMU" else "")]
    keep, window, note = _longest_session(t, np.array([m._timestamp for m in rows]))
    if note:
        notes.append(note)
    t, gyr, acc, mag = t[keep], gyr[keep], acc[keep], mag[keep]
    t, (gyr, acc, mag), cleanup = clean_stream(t, gyr, acc, mag)
    if len(t) < 2:
        raise ReplayInputError(f"{path}: fewer than 2 usable {imu_type} samples")
    in_session = {k: [m for m in v if window[0] <= m._timestamp <= window[1]]
                  for k, v in messages.items()}
    ref = _reference(in_session, src, reference)
    return Recording(path=path, format="tlog", t=t, gyr=gyr, acc=acc,
                     mag=mag if np.isfinite(mag).any() else None, world="NED", body="FRD",
                     source=imu_type, reference=ref, cleanup=cleanup, notes=tuple(notes))


def _longest_session(t: np.ndarray, arrival: np.ndarray
                     ) -> tuple[np.ndarray, tuple[float, float], str]:
    """Keep the longest stretch between vehicle reboots (board time jumping back > 1 s).

    Boot times of two sessions overlap, so mixing them would pair IMU samples with the
    attitude of another flight. The log's arrival stamps (used only here, never as sample
    time) tell which reference messages belong to the chosen session.
    """
    resets = np.flatnonzero(np.diff(t) < -REBOOT_JUMP_S) + 1
    bounds = np.concatenate(([0], resets, [len(t)]))
    sizes = np.diff(bounds)
    k = int(np.argmax(sizes))
    keep = np.zeros(len(t), dtype=bool)
    keep[bounds[k]:bounds[k + 1]] = True
    window = (float(arrival[bounds[k]]) - SESSION_PAD_S,
              float(arrival[bounds[k + 1] - 1]) + SESSION_PAD_S)
    note = ""
    if len(resets):
        note = (f"board time restarted {len(resets)} time(s) (reboot): used session "
                f"{k + 1} of {len(sizes)} ({sizes[k]} of {len(t)} IMU samples)")
    return keep, window, note


def _collect(path: Path) -> dict[str, list]:
    from pymavlink import mavutil

    wanted = set(IMU_MESSAGES + REFERENCE_MESSAGES)
    out: dict[str, list] = defaultdict(list)
    try:
        conn = mavutil.mavlink_connection(str(path), notimestamps=False)
    except Exception as exc:
        raise ReplayInputError(f"{path}: cannot open as a MAVLink log ({exc})") from exc
    try:
        while True:
            msg = conn.recv_match()
            if msg is None:
                break
            kind = msg.get_type()
            if kind in wanted:
                out[kind].append(msg)
    finally:
        conn.close()
    return out


def _pick_imu(messages: dict[str, list], imu: str | None, path: Path) -> tuple[str, tuple]:
    candidates = [imu] if imu else [m for m in IMU_MESSAGES if messages.get(m)]
    if not candidates or not messages.get(candidates[0]):
        raise ReplayInputError(f"{path}: no IMU samples found (looked for "
                               f"{imu or ', '.join(IMU_MESSAGES)})")
    kind = candidates[0]
    sources = Counter((m.get_srcSystem(), m.get_srcComponent()) for m in messages[kind])
    return kind, sources.most_common(1)[0][0]


def _imu_arrays(kind: str, rows: list, profile) -> tuple[np.ndarray, ...]:
    def fields(*names: str) -> np.ndarray:
        return np.array([[getattr(m, n) for n in names] for m in rows], dtype=float)

    gyro_names = ("xgyro", "ygyro", "zgyro")
    acc_names = ("xacc", "yacc", "zacc")
    mag_names = ("xmag", "ymag", "zmag")
    if kind == "HIGHRES_IMU":
        t = fields("time_usec")[:, 0] * 1e-6
        gyr, acc, mag = fields(*gyro_names), fields(*acc_names), fields(*mag_names)
        updated = fields("fields_updated")[:, 0].astype(np.int64)
        has_mag = (updated & HIGHRES_MAG_BITS) == HIGHRES_MAG_BITS
        if has_mag.any() and not has_mag.all():  # hold the last real magnetometer reading
            mag = sample_and_hold(t[has_mag], mag[has_mag], t)
        elif not has_mag.any():
            mag = np.full_like(mag, np.nan)
        return t, gyr, acc, mag
    if kind == "RAW_IMU":
        t = fields("time_usec")[:, 0] * 1e-6
        return (t, profile.gyro(fields(*gyro_names)), profile.accel(fields(*acc_names)),
                profile.mag(fields(*mag_names)))
    # SCALED_IMU/2/3: mrad/s, mG, mgauss, FRD (MAVLink common.xml)
    t = fields("time_boot_ms")[:, 0] * 1e-3
    return (t, fields(*gyro_names) * 1e-3, fields(*acc_names) * 1e-3 * G,
            fields(*mag_names) * 1e-3)


def _reference(messages: dict[str, list], src: tuple, reference: str) -> Reference | None:
    sysid = src[0]
    if reference in ("auto", "truth"):
        rows = [m for m in messages.get("HIL_STATE_QUATERNION", []) if m.get_srcSystem() == sysid]
        if rows:
            t = np.array([m.time_usec for m in rows], dtype=float) * 1e-6
            q = np.array([m.attitude_quaternion for m in rows], dtype=float)
            return make_reference(t, q, "truth", "HIL_STATE_QUATERNION")
        if reference == "truth":
            return None
    for kind in ("ATTITUDE_QUATERNION", "ATTITUDE"):
        rows = _same_component(messages.get(kind, []), src)
        if not rows:
            continue
        t = np.array([m.time_boot_ms for m in rows], dtype=float) * 1e-3
        if kind == "ATTITUDE_QUATERNION":
            q = np.array([[m.q1, m.q2, m.q3, m.q4] for m in rows], dtype=float)
        else:
            e = np.array([[m.roll, m.pitch, m.yaw] for m in rows], dtype=float)
            q = Q.from_euler(e[:, 0], e[:, 1], e[:, 2])
        return make_reference(t, q, "autopilot", kind)
    return None


def _same_component(rows: list, src: tuple) -> list:
    """The IMU's own autopilot component; else any component of that vehicle."""
    same = [m for m in rows if (m.get_srcSystem(), m.get_srcComponent()) == src]
    return same or [m for m in rows if m.get_srcSystem() == src[0]]
