"""MAVLink telemetry log (.tlog): IMU messages and attitude references, by their own clocks.

IMU, in order of preference (or ``imu=`` to choose): HIGHRES_IMU (SI, gauss), RAW_IMU
(integers whose meaning depends on the sender: an ``imu.boards`` profile, detected from
gravity unless ``board=`` names one), SCALED_IMU/2/3 (mG, mrad/s, mgauss, FRD).
References: HIL_STATE_QUATERNION (PX4 SITL) or SIMSTATE (ArduPilot SITL) is truth;
ATTITUDE_QUATERNION, else ATTITUDE (Z-Y-X
Euler), from the same vehicle component as the IMU is the autopilot's own estimate.

Time is ``time_usec`` / ``time_boot_ms`` from the messages. A message without a usable
stamp (PX4 SITL sends HIL_STATE_QUATERNION with ``time_usec = 0``) gets the board time of
the IMU message just before it in the file: same link, same sender thread. The log's
8-byte arrival stamps cannot be mapped by a constant offset instead: the sender's
clock and the recorder's drift apart (about 1 % for PX4 SITL) and arrive in bursts.
Also read: the vehicle's parameters (PARAM_VALUE), its position and the date (for the
declination) and its velocity (for aiding, see :mod:`replay.readers.velocity`).
"""

from __future__ import annotations

import datetime as _dt
import math
import operator
import os
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimators import quat as Q

from ..board import choose_board, magnitude_warning
from ..dataset import Position, Recording, Reference, ReplayInputError, StateEvent
from ..timebase import sample_and_hold
from ._common import clean_stream, make_reference, other_autopilot, pick_reference, require_imu
from .velocity import VelocityRows, place_velocity

if TYPE_CHECKING:
    from pymavlink.dialects.v20.ardupilotmega import MAVLink

os.environ["MAVLINK20"] = "1"

IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")
REFERENCE_MESSAGES = ("HIL_STATE_QUATERNION", "SIMSTATE", "ATTITUDE_QUATERNION", "ATTITUDE")
VELOCITY_MESSAGES = ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "GPS_RAW_INT")
OTHER_MESSAGES = ("PARAM_VALUE", "SYSTEM_TIME", "GPS_GLOBAL_ORIGIN", "HOME_POSITION",
                  "HEARTBEAT", "EXTENDED_SYS_STATE")
G = 9.80665
HIGHRES_MAG_BITS = 0x1C0  # fields_updated bits 6..8: xmag, ymag, zmag
REBOOT_JUMP_S = 1.0  # board time going back by more than this: the vehicle rebooted
SESSION_PAD_S = 1.0  # reference messages this close to a session's ends belong to it
STAMP_SLACK_S = 10.0  # a stamp this far outside the IMU's time span is on another clock
UINT16_UNKNOWN = 65535
MAVLINK1_STX, MAVLINK2_STX = 0xFE, 0xFD
FRAME_HEADER_BYTES = 10  # what _frame reads: a MAVLink 2 header up to the message id
STAMP_JUMP_US = 86_400_000_000  # consecutive arrival stamps a day apart: misframed record
CLOCK_CONFIRM_RECORDS = 3  # whole records in a row that make such a jump the recorder's
GPS_FIX_3D = 3
MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
#: MAV_COMP_ID_ONBOARD_COMPUTER..4: companions (this bridge sends from 191). Their
#: attitude in a record is a companion's estimate, never the autopilot's own.
COMPANION_COMPONENTS = range(191, 195)


def read(path: Path, board: str | None = None, imu: str | None = None,
         reference: str = "auto", raw_mag: bool = True) -> Recording:
    """``raw_mag``: a PX4 log's HIGHRES_IMU field may be replaced by SCALED_IMU's raw one
    (:mod:`imu.px4_mag`, as the live bridge does); False keeps HIGHRES_IMU's."""
    if imu is not None and imu.upper() not in IMU_MESSAGES:
        raise ReplayInputError(f"unknown IMU message {imu!r}; valid: {list(IMU_MESSAGES)}")
    walk = _collect(path)
    messages, unreadable, tail = walk.messages, walk.unreadable, walk.tail
    damage = f"file ends mid-record: last {tail} bytes ignored" if tail else ""
    imu_type, src = _pick_imu(messages, imu.upper() if imu else None, path, damage)
    rows = [m for m in messages[imu_type] if (m.get_srcSystem(), m.get_srcComponent()) == src]
    if imu_type == "RAW_IMU":  # several IMUs share RAW_IMU, told apart by `id`
        ids = Counter(getattr(m, "id", 0) for m in rows)
        rows = [m for m in rows if getattr(m, "id", 0) == min(ids)]
    notes = [f"IMU {imu_type} from system {src[0]} component {src[1]}"]
    lost = [damage] if damage else []
    if unreadable:
        lost.append(f"skipped {unreadable} unreadable stretch(es) of the log (bad CRC, "
                    f"cut frames or bytes between records)")
    notes += lost
    if walk.jumps:
        notes.append(walk.jump_note())
    warnings: list[str] = []
    profile_name = None
    if imu_type == "RAW_IMU":
        choice = choose_board(_fields(rows, "xacc", "yacc", "zacc"), board)
        profile_name = choice.name
        notes.append(choice.note())
        if (w := choice.warning()) is not None:
            warnings.append(w)
    truncated = imu_type.startswith("SCALED_IMU") and any(
        m.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA
        for m in _same_component(messages.get("HEARTBEAT", []), src))
    if truncated:
        notes.append(f"{imu_type} integers read as the middle of their step (ArduPilot "
                     f"truncates them toward zero)")
    t, gyr, acc, mag = _imu_arrays(imu_type, rows, profile_name, truncated)
    if imu_type == "HIGHRES_IMU" and raw_mag and _is_px4(messages, src):
        mag, mag_note = _px4_raw_mag(rows, messages.get("SCALED_IMU", []), src, mag,
                                     _params(messages, src))
        if mag_note:
            notes.append(mag_note)
    if imu_type != "RAW_IMU" and (w := magnitude_warning(acc, imu_type)) is not None:
        warnings.append(w)
    keep, window, note = _longest_session(t, np.array([m._timestamp for m in rows]))
    if note:  # (the other sessions are left out)
        notes.append(note)
        lost.append(note)
    clock = BoardClock(np.array([m._order for m in rows])[keep], t[keep])
    t, gyr, acc, mag = t[keep], gyr[keep], acc[keep], mag[keep]
    t, (gyr, acc, mag), cleanup = clean_stream(t, gyr, acc, mag)
    if len(t) < 2:
        raise ReplayInputError(f"{path}: fewer than 2 usable {imu_type} samples"
                               + (f"; {damage}" if damage else ""))
    in_session = {k: [m for m in v if window[0] <= m._timestamp <= window[1]]
                  for k, v in messages.items()}
    found = {"truth": _truth(in_session, src, clock),
             "autopilot": _autopilot(in_session, src, clock)}
    ref, references = pick_reference(found, reference)
    when, when_source = _date(in_session, src)
    velocity = place_velocity(_velocity_rows(in_session, src, clock), t)
    own_beats = _same_component(messages.get("HEARTBEAT", []), src)
    beats = [m.type for m in own_beats]
    autopilots = [m.autopilot for m in own_beats]
    events, events_source, foreign = _state_events(in_session, src, clock)
    if foreign:
        notes.append(f"ignored {foreign} HEARTBEAT/EXTENDED_SYS_STATE message(s) from "
                     f"other systems than the IMU's (system {src[0]})")
    return Recording(path=path, format="tlog", t=t, gyr=gyr, acc=acc,
                     mag=mag if np.isfinite(mag).any() else None, world="NED", body="FRD",
                     source=imu_type, reference=ref, cleanup=cleanup, notes=tuple(notes),
                     damage=tuple(lost),
                     warnings=tuple(warnings), board=profile_name,
                     params=_params(messages, src), position=_position(in_session, src),
                     when=when, when_source=when_source, velocity=velocity,
                     mav_type=Counter(beats).most_common(1)[0][0] if beats else None,
                     mav_type_source="HEARTBEAT" if beats else "",
                     mav_autopilot=(Counter(autopilots).most_common(1)[0][0] if autopilots
                                    else None),
                     state_events=events, state_events_source=events_source,
                     references=references, autopilot=other_autopilot(found, ref))


def _state_events(messages: dict[str, list], src: tuple, clock: BoardClock
                  ) -> tuple[tuple[StateEvent, ...], str, int]:
    """The vehicle's flight-state reports (HEARTBEAT armed flag, EXTENDED_SYS_STATE) on the
    IMU clock; only from the IMU's own system and component: a ground station's heartbeat
    or another vehicle's state (spoofed or not) says nothing about this vehicle. Also the
    count of such reports from other systems."""
    beats = [m for m in messages.get("HEARTBEAT", [])  # not a GCS's or a companion's
             if m.type != MAV_TYPE_GCS and m.autopilot != MAV_AUTOPILOT_INVALID]
    states = messages.get("EXTENDED_SYS_STATE", [])
    foreign = sum(1 for m in [*beats, *states] if m.get_srcSystem() != src[0])
    events: list[StateEvent] = []
    used = []
    for kind, rows in (("heartbeat", _same_component(beats, src)),
                       ("landed_state", _same_component(states, src))):
        if not rows:
            continue
        used.append("HEARTBEAT" if kind == "heartbeat" else "EXTENDED_SYS_STATE")
        t = clock.preceding(np.array([m._order for m in rows]))
        for m, tk in zip(rows, t.tolist(), strict=True):
            if not math.isfinite(tk):
                continue
            if kind == "heartbeat":
                events.append(StateEvent(tk, kind, int(m.base_mode), int(m.autopilot)))
            else:
                events.append(StateEvent(tk, kind, int(m.landed_state)))
    events.sort(key=lambda e: e.t)
    return tuple(events), " + ".join(used), foreign


@dataclass(frozen=True)
class BoardClock:
    """Board time of the IMU message preceding any message in the file.

    ``order``: file positions of the session's IMU messages (increasing); ``t``: their
    board times. A message without a usable stamp of its own was sent after that IMU
    message by the same sender, so that IMU sample's time is the closest honest bound.
    """

    order: np.ndarray
    t: np.ndarray

    def preceding(self, order: np.ndarray) -> np.ndarray:
        running = np.maximum.accumulate(self.t) if self.t.size else self.t
        idx = np.searchsorted(self.order, order, side="right") - 1
        out = np.full(np.shape(order), np.nan)
        ok = idx >= 0
        out[ok] = running[idx[ok]]
        return out

    def usable(self, stamps: np.ndarray) -> np.ndarray:
        """Which stamps are on this board clock: positive and near the IMU's span."""
        lo, hi = np.min(self.t) - STAMP_SLACK_S, np.max(self.t) + STAMP_SLACK_S
        return np.isfinite(stamps) & (stamps > 0) & (stamps >= lo) & (stamps <= hi)


def _longest_session(t: np.ndarray, arrival: np.ndarray
                     ) -> tuple[np.ndarray, tuple[float, float], str]:
    """Keep the longest stretch between vehicle reboots (board time jumping back > 1 s).

    Boot times of two sessions overlap, so mixing them would pair IMU samples with the
    attitude of another flight. The log's arrival stamps tell which other messages
    belong to the chosen session.
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


@dataclass
class Walk:
    """What reading a tlog's records gave: the messages replay uses, by type, how many
    unreadable stretches were skipped, how many bytes at the end were a record cut short
    (the recorder stopped mid-write), and where the recorder's clock jumped."""

    messages: dict[str, list]
    unreadable: int = 0
    tail: int = 0
    records: int = 0
    jumps: list[tuple[int, int]] = field(default_factory=list)  # (record, jump µs)

    def jump_note(self) -> str:
        """The clock jumps in the recording's notes: the records after them are kept."""
        first, _ = self.jumps[0]
        largest = max((jump for _, jump in self.jumps), key=abs)
        return (f"the recorder's clock (tlog arrival stamps) jumped {len(self.jumps)} "
                f"time(s), by up to {largest * 1e-6 / 86_400:+.1f} days (first at record "
                f"{first + 1} of {self.records}): the {self.records - first} records from "
                f"there are kept, their arrival times moved to follow on from before the "
                f"jump")


def _collect(path: Path) -> Walk:
    """The messages replay uses, by type, and what the walk met on the way (:class:`Walk`).

    Each message gets ``_timestamp`` (arrival, s) and ``_order``, its record's position.

    A tlog is records of an 8-byte big-endian arrival time in µs and one MAVLink frame.
    Walking the records and decoding only the wanted message ids is 2-3x faster than
    pymavlink's generic log reader, which decodes everything. A record that does not
    parse (bad CRC, bytes lost) is skipped: the walk resumes at the next position that
    looks like a record (a start byte after a time stamp close to the last good one).

    A stamp more than a day from the last one is a misframed record, unless whole
    records with good CRCs follow on from it: then the recorder's clock was set (a
    companion computer taking the network's time mid-flight) and the walk goes on. The
    arrival times only order the messages and tell which belong to a session, so the
    later ones are moved by the jump to follow on from the earlier ones.
    """
    from pymavlink.dialects.v20 import ardupilotmega as common  # common + SIMSTATE

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ReplayInputError(f"{path}: cannot read ({exc.strerror})") from exc
    wanted = set(IMU_MESSAGES + REFERENCE_MESSAGES + VELOCITY_MESSAGES + OTHER_MESSAGES)
    ids = {mid for mid, cls in common.mavlink_map.items() if cls.msgname in wanted}
    mav, checker = common.MAVLink(None), common.MAVLink(None)
    walk = Walk(defaultdict(list))
    i, size, last, shift = 0, len(data), None, 0
    while i + 16 <= size:
        stamp = int.from_bytes(data[i:i + 8], "big")
        frame = _frame(data, i + 8)
        if frame is None and i + 8 + FRAME_HEADER_BYTES > size:
            break  # the end of the file cuts the frame's header
        far = last is not None and abs(stamp - last) > STAMP_JUMP_US
        if frame is not None and far and _records_follow(data, i, checker):
            walk.jumps.append((walk.records, stamp - last))
            shift += stamp - last
        elif frame is None or far:
            walk.unreadable += 1
            i = _resync(data, i + 1, last, checker)
            continue
        length, msgid = frame
        end = i + 8 + length
        if end > size:
            break
        if msgid in ids:
            try:
                msg = mav.decode(bytearray(data[i + 8:end]))
            except Exception:  # pymavlink raises MAVError and struct errors on bad frames
                walk.unreadable += 1
                i = _resync(data, i + 1, last, checker)
                continue
            msg._timestamp = (stamp - shift) * 1e-6
            msg._order = walk.records
            walk.messages[msg.get_type()].append(msg)
        last = stamp
        walk.records += 1
        i = end
    walk.tail = size - i
    return walk


def _frame(data: bytes, k: int) -> tuple[int, int] | None:
    """(frame length, message id) of a MAVLink 1 or 2 frame starting at ``k``."""
    if k + FRAME_HEADER_BYTES > len(data):
        return None
    if data[k] == MAVLINK2_STX:
        signed = 13 if data[k + 2] & 0x01 else 0
        return 12 + data[k + 1] + signed, data[k + 7] | data[k + 8] << 8 | data[k + 9] << 16
    if data[k] == MAVLINK1_STX:
        return 8 + data[k + 1], data[k + 5]
    return None


def _resync(data: bytes, k: int, last: int | None, checker: MAVLink) -> int:
    """The next position from ``k`` where a record plausibly starts: a start byte after a
    stamp near the last good one, or records that follow on from each other on a clock
    that jumped (see :func:`_records_follow`; the recorder may have restarted mid-record
    with another time)."""
    while k + 16 <= len(data):
        if data[k + 8] in (MAVLINK1_STX, MAVLINK2_STX):
            stamp = int.from_bytes(data[k:k + 8], "big")
            if (last is None or abs(stamp - last) <= STAMP_JUMP_US
                    or _records_follow(data, k, checker)):
                return k
        k += 1
    return len(data)


def _records_follow(data: bytes, k: int, checker: MAVLink) -> bool:
    """Whether ``CLOCK_CONFIRM_RECORDS`` whole records start at ``k``, one after the
    other, each a MAVLink frame that decodes with a good CRC and a stamp within a day of
    the first's. Bytes that merely look like a record header (a misframe) would need a
    CRC right by chance, and the genuine records after them have stamps near the last
    good one, not near the misframed one: a far stamp that passes is the recorder's
    clock being set, not damage.

    ``checker``: a pymavlink ``MAVLink`` parser of its own, so that these trial decodes
    leave the walk's parser (its sequence and loss counters) alone.
    """
    first = int.from_bytes(data[k:k + 8], "big")
    for _ in range(CLOCK_CONFIRM_RECORDS):
        frame = _frame(data, k + 8)
        if frame is None or k + 8 + frame[0] > len(data):
            return False
        if abs(int.from_bytes(data[k:k + 8], "big") - first) > STAMP_JUMP_US:
            return False
        try:
            checker.decode(bytearray(data[k + 8:k + 8 + frame[0]]))
        except Exception:  # pymavlink raises MAVError and struct errors on bad frames
            return False
        k += 8 + frame[0]
    return True


def _is_px4(messages: dict[str, list], src: tuple) -> bool:
    return any(m.autopilot == MAV_AUTOPILOT_PX4
               for m in _same_component(messages.get("HEARTBEAT", []), src))


def _px4_raw_mag(rows: list, scaled: list, src: tuple, mag: np.ndarray,
                 params: dict[str, float]) -> tuple[np.ndarray, str]:
    """HIGHRES_IMU's fields with SCALED_IMU's raw one where :mod:`imu.px4_mag` takes it
    (``params``: the log's parameters): every message of both in the order they were
    recorded, as the live bridge met them."""
    from imu.px4_mag import RawMagnetometer

    scaled = [m for m in scaled if (m.get_srcSystem(), m.get_srcComponent()) == src]
    if not scaled:
        return mag, ""
    raw = _imu_arrays("SCALED_IMU", scaled, None)[3]
    chooser = RawMagnetometer()
    chooser.set_parameters(params)
    out = mag.copy()
    events = sorted([(m._order, 0, i) for i, m in enumerate(scaled)]
                    + [(m._order, 1, i) for i, m in enumerate(rows)],
                    key=operator.itemgetter(0, 1))
    for _, kind, item in events:
        if kind == 0:
            chooser.offer_raw(raw[item], scaled[item]._timestamp)
            continue
        m = rows[item]
        numbers = (m.xmag, m.ymag, m.zmag)
        own = (np.array(numbers, float) if any(numbers) and all(map(math.isfinite, numbers))
               else None)
        chosen = chooser.choose(own, m._timestamp)
        if chosen is not None and chosen is not own:
            out[item] = chosen
    return out, chooser.describe() + (f", {chooser.used} readings replaced"
                                      if chooser.used else "")


def _pick_imu(messages: dict[str, list], imu: str | None, path: Path,
              damage: str = "") -> tuple[str, tuple]:
    candidates = [imu] if imu else [m for m in IMU_MESSAGES if messages.get(m)]
    if not candidates or not messages.get(candidates[0]):
        require_imu(0, path, imu or ", ".join(IMU_MESSAGES), damage)
    kind = candidates[0]
    sources = Counter((m.get_srcSystem(), m.get_srcComponent()) for m in messages[kind])
    return kind, sources.most_common(1)[0][0]


def _fields(rows: list, *names: str) -> np.ndarray:
    """(len(rows), len(names)) array of the named fields of each message."""
    get = operator.attrgetter(*names)
    if len(names) == 1:
        return np.fromiter(map(get, rows), dtype=float, count=len(rows))[:, None]
    return np.array(list(map(get, rows)), dtype=float).reshape(len(rows), len(names))


def _imu_arrays(kind: str, rows: list, board: str | None, truncated: bool = False
                ) -> tuple[np.ndarray, ...]:
    """Times [s] and FRD gyro [rad/s], specific force [m/s²], field [gauss] of the IMU
    messages. ``truncated``: SCALED_IMU integers made by truncation toward zero, read as
    the middle of their step (imu.boards.BoardProfile.truncated)."""
    gyro_names = ("xgyro", "ygyro", "zgyro")
    acc_names = ("xacc", "yacc", "zacc")
    mag_names = ("xmag", "ymag", "zmag")
    if kind == "HIGHRES_IMU":
        t = _fields(rows, "time_usec")[:, 0] * 1e-6
        gyr, acc, mag = (_fields(rows, *gyro_names), _fields(rows, *acc_names),
                         _fields(rows, *mag_names))
        updated = _fields(rows, "fields_updated")[:, 0].astype(np.int64)
        # Unset fields are 0, not "no change": hold the last real magnetometer reading.
        has_mag = (updated & HIGHRES_MAG_BITS) == HIGHRES_MAG_BITS
        if has_mag.any() and not has_mag.all():
            mag = sample_and_hold(t[has_mag], mag[has_mag], t)
        elif not has_mag.any():
            mag = np.full_like(mag, np.nan)
        return t, gyr, acc, mag
    if kind == "RAW_IMU":
        from imu.boards import board_profile

        profile = board_profile(board or "ardupilot")
        t = _fields(rows, "time_usec")[:, 0] * 1e-6
        return (t, profile.gyro(_fields(rows, *gyro_names)),
                profile.accel(_fields(rows, *acc_names)), profile.mag(_fields(rows, *mag_names)))
    # SCALED_IMU/2/3: mrad/s, mG, mgauss, FRD (MAVLink common.xml)
    t = _fields(rows, "time_boot_ms")[:, 0] * 1e-3

    def numbers(names: tuple[str, ...]) -> np.ndarray:
        v = _fields(rows, *names)
        return v + 0.5 * np.sign(v) if truncated else v

    return (t, numbers(gyro_names) * 1e-3, numbers(acc_names) * 1e-3 * G,
            numbers(mag_names) * 1e-3)


def _message_times(rows: list, field: str, scale: float, clock: BoardClock
                   ) -> tuple[np.ndarray, str]:
    """Each message's own time where it is on the board clock, else its arrival's."""
    own = np.array([getattr(m, field) for m in rows], dtype=float) * scale
    ok = clock.usable(own)
    if ok.all():
        return own, ""
    arrival = clock.preceding(np.array([m._order for m in rows]))
    how = (f"{field} unusable ({np.count_nonzero(~ok)} of {len(rows)}): aligned by arrival "
           f"(board time of the IMU message before it)")
    return np.where(ok, own, arrival), how


def _truth(messages: dict[str, list], src: tuple, clock: BoardClock) -> Reference | None:
    """The simulator's attitude: HIL_STATE_QUATERNION (PX4 SITL), else SIMSTATE."""
    sysid = src[0]
    rows = [m for m in messages.get("HIL_STATE_QUATERNION", []) if m.get_srcSystem() == sysid]
    if rows:
        t, how = _message_times(rows, "time_usec", 1e-6, clock)
        q = np.array([m.attitude_quaternion for m in rows], dtype=float)
        return make_reference(t, q, "truth", "HIL_STATE_QUATERNION", timing=how)
    rows = [m for m in messages.get("SIMSTATE", []) if m.get_srcSystem() == sysid]
    if rows:
        # ArduPilot SITL's simulator state (true north); it carries no time stamp
        t = clock.preceding(np.array([m._order for m in rows]))
        e = np.array([[m.roll, m.pitch, m.yaw] for m in rows], dtype=float)
        return make_reference(t, Q.from_euler(e[:, 0], e[:, 1], e[:, 2]), "truth",
                              "SIMSTATE", timing="no time stamp: aligned by arrival "
                              "(board time of the IMU message before it)")
    return None


def _autopilot(messages: dict[str, list], src: tuple, clock: BoardClock
               ) -> Reference | None:
    """The vehicle's own estimate: ATTITUDE_QUATERNION, else ATTITUDE, from the IMU's own
    component first (an emulated board that sends only ATTITUDE has it there, while a
    bridge's record also holds the bridge's ATTITUDE_QUATERNION under the vehicle's
    system id), then from another component of the vehicle that is not a companion."""
    candidates = [(kind, [m for m in messages.get(kind, [])
                          if (m.get_srcSystem(), m.get_srcComponent()) == src])
                  for kind in ("ATTITUDE_QUATERNION", "ATTITUDE")]
    candidates += [(kind, [m for m in messages.get(kind, [])
                           if m.get_srcSystem() == src[0] and m.get_srcComponent() != src[1]
                           and m.get_srcComponent() not in COMPANION_COMPONENTS])
                   for kind in ("ATTITUDE_QUATERNION", "ATTITUDE")]
    for kind, rows in candidates:
        if not rows:
            continue
        t, how = _message_times(rows, "time_boot_ms", 1e-3, clock)
        if kind == "ATTITUDE_QUATERNION":
            q = np.array([[m.q1, m.q2, m.q3, m.q4] for m in rows], dtype=float)
        else:
            e = np.array([[m.roll, m.pitch, m.yaw] for m in rows], dtype=float)
            q = Q.from_euler(e[:, 0], e[:, 1], e[:, 2])
        # PX4 and ArduPilot both apply their declination: their yaw is from true north.
        return make_reference(t, q, "autopilot", kind, timing=how)
    return None


def _same_component(rows: list, src: tuple) -> list:
    """The IMU's own autopilot component; else any component of that vehicle."""
    same = [m for m in rows if (m.get_srcSystem(), m.get_srcComponent()) == src]
    return same or [m for m in rows if m.get_srcSystem() == src[0]]


def _params(messages: dict[str, list], src: tuple) -> dict[str, float]:
    """The vehicle's parameters as last reported (PARAM_VALUE), by name: from the whole
    log, since a ground station downloads them once, often before a reboot. For the
    declination the last value is also the one flown with: PX4 replaces a saved
    EKF2_MAG_DECL from its own tables on the ground without a PARAM_VALUE and announces
    the value its EKF used when it disarms (docs/replay.md, "Declination")."""
    out: dict[str, float] = {}
    for m in messages.get("PARAM_VALUE", []):
        if m.get_srcSystem() == src[0]:
            name = m.param_id.rstrip("\x00") if isinstance(m.param_id, str) else str(m.param_id)
            out[name] = float(m.param_value)
    return out


def _position(messages: dict[str, list], src: tuple) -> Position | None:
    """The vehicle's position from the first message type that has a real one."""
    def own(kind: str) -> list:
        return [m for m in messages.get(kind, []) if m.get_srcSystem() == src[0]]

    candidates = [
        ("GPS_RAW_INT", [(m.lat, m.lon, m.alt) for m in own("GPS_RAW_INT")
                         if m.fix_type >= 2 and (m.lat or m.lon)]),
        ("GLOBAL_POSITION_INT", [(m.lat, m.lon, m.alt) for m in own("GLOBAL_POSITION_INT")
                                 if m.lat or m.lon]),
        ("HIL_STATE_QUATERNION", [(m.lat, m.lon, m.alt) for m in own("HIL_STATE_QUATERNION")
                                  if m.lat or m.lon]),
        ("GPS_GLOBAL_ORIGIN", [(m.latitude, m.longitude, m.altitude)
                               for m in own("GPS_GLOBAL_ORIGIN") if m.latitude or m.longitude]),
        ("HOME_POSITION", [(m.latitude, m.longitude, m.altitude)
                           for m in own("HOME_POSITION") if m.latitude or m.longitude]),
    ]
    for name, rows in candidates:
        if rows:
            lat, lon, alt = np.median(np.array(rows, dtype=float), axis=0)
            return Position(lat * 1e-7, lon * 1e-7, alt * 1e-3, name)
    return None


def _date(messages: dict[str, list], src: tuple) -> tuple[_dt.datetime | None, str]:
    """UTC date: the vehicle's SYSTEM_TIME, else the recorder's clock (arrival stamps)."""
    unix = [m.time_unix_usec for m in messages.get("SYSTEM_TIME", [])
            if m.get_srcSystem() == src[0] and m.time_unix_usec > 0]
    if unix:
        return (_dt.datetime.fromtimestamp(float(np.median(unix)) * 1e-6, _dt.UTC),
                "SYSTEM_TIME")
    stamps = [m._timestamp for rows in messages.values() for m in rows[:1]]
    if stamps and math.isfinite(stamps[0]) and stamps[0] > 0:
        return _dt.datetime.fromtimestamp(float(min(stamps)), _dt.UTC), "tlog arrival time"
    return None, ""


def _velocity_rows(messages: dict[str, list], src: tuple, clock: BoardClock
                   ) -> VelocityRows | None:
    """The preferred velocity source: LOCAL_POSITION_NED, GLOBAL_POSITION_INT, GPS_RAW_INT.

    Each measurement is available at its arrival (board time of the IMU message before
    it) and was valid at its own stamp when that is on the board clock.
    """
    for kind in VELOCITY_MESSAGES:
        rows = [m for m in messages.get(kind, []) if m.get_srcSystem() == src[0]]
        if kind == "LOCAL_POSITION_NED":
            v = _fields(rows, "vx", "vy", "vz") if rows else np.empty((0, 3))
            stamp, scale = "time_boot_ms", 1e-3
        elif kind == "GLOBAL_POSITION_INT":
            rows = [m for m in rows if m.lat or m.lon]  # lat = lon = 0: no position fix
            v = _fields(rows, "vx", "vy", "vz") * 1e-2 if rows else np.empty((0, 3))
            stamp, scale = "time_boot_ms", 1e-3
        else:
            rows = [m for m in rows if m.fix_type >= GPS_FIX_3D and m.vel != UINT16_UNKNOWN
                    and m.cog != UINT16_UNKNOWN]
            speed = _fields(rows, "vel")[:, 0] * 1e-2 if rows else np.empty(0)
            cog = np.radians(_fields(rows, "cog")[:, 0] * 1e-2) if rows else np.empty(0)
            v = np.column_stack([speed * np.cos(cog), speed * np.sin(cog),
                                 np.full(len(rows), np.nan)])
            stamp, scale = "time_usec", 1e-6
        if not rows:
            continue
        arrival = clock.preceding(np.array([m._order for m in rows]))
        own = np.array([getattr(m, stamp) for m in rows], dtype=float) * scale
        valid = np.where(clock.usable(own), own, np.nan)
        return VelocityRows(v, arrival, valid, kind)
    return None
