"""PX4 ULog: sensor_combined (FRD, SI), magnetometer (Gauss), attitude references.

Times are the topics' own µs timestamps (``timestamp_sample`` when the topic has it: the
time of the IMU sample an attitude belongs to, which is what lag must be measured from).
``vehicle_attitude_groundtruth`` (SITL) is truth; otherwise ``vehicle_attitude`` (PX4's
EKF, FRD -> NED, true north: PX4 applies its declination) is the autopilot reference.
The magnetometer is ``vehicle_magnetometer``; older logs (PX4 <= 1.9) keep it in
``sensor_combined.magnetometer_ga``; else ``sensor_mag``. Also read: the parameters,
the GPS position and UTC date (for the declination) and the velocity (for aiding).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import mmap
from pathlib import Path

import numpy as np

from ..board import magnitude_warning
from ..dataset import Position, Recording, Reference, ReplayInputError, StateEvent
from ..timebase import sample_and_hold
from ._common import (
    clean_stream,
    make_reference,
    other_autopilot,
    pick_reference,
    require_imu,
    trim_before_first_mag,
)
from .velocity import VelocityRows, place_velocity

US = 1e-6
RELATIVE_INVALID = 2147483647  # sensor_combined *_timestamp_relative: "not updated"
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")
ARMING_STATE_ARMED = 2  # vehicle_status.arming_state (PX4's ARMING_STATE_ARMED)
FILE_HEADER_BYTES = 16  # magic, version, start time
MESSAGE_HEADER_BYTES = 3  # uint16 payload size, uint8 type
MESSAGE_TYPES = frozenset(b"ABCDFILMOPQRS")  # every message type of the ULog format


def read(path: Path, reference: str = "auto") -> Recording:
    from pyulog import ULog  # imported here: only ULog users pay for it

    try:
        # pyulog prints its corruption notices; this reader says them in its notes
        with contextlib.redirect_stdout(io.StringIO()):
            ulog = ULog(str(path))
    except Exception as exc:  # pyulog raises bare Exceptions on corrupt headers
        raise ReplayInputError(f"{path}: not a readable ULog file ({exc})") from exc
    topics = {(d.name, d.multi_id): d.data for d in ulog.data_list}
    cut = _bytes_after_last_message(path)
    damage = f"ULog ends inside a message: last {cut} bytes ignored" if cut else ""
    if not cut and ulog.file_corruption:
        damage = ("ULog damaged inside: pyulog skipped to the next message it could read "
                  "(the samples in between are lost)")

    imu = topics.get(("sensor_combined", 0))
    require_imu(0 if imu is None else len(imu["timestamp"]), path, "ULog topic sensor_combined",
                damage)
    # Subtract a common origin in integers first: PX4 can stamp with epoch µs (~1.7e15),
    # where float64 seconds keep only ~0.2 µs and every dt would carry that jitter.
    origin = int(imu["timestamp"][0])
    t = _seconds(imu["timestamp"], origin)
    gyr = _vec(imu, "gyro_rad[{}]")
    acc = _vec(imu, "accelerometer_m_s2[{}]")
    t, (gyr, acc), cleanup = clean_stream(t, gyr, acc)
    notes = [damage] if damage else []

    mag = None
    mag_topic = _mag_topic(topics)
    if mag_topic is not None:
        name, data, fmt = mag_topic
        tm, (m,), _ = clean_stream(_time(data, origin), _vec(data, fmt))
        mag = sample_and_hold(tm, m, t)
        notes.append(f"magnetometer from {name} ({len(tm)} readings, held between them)")
        first, t, (gyr, acc, mag) = trim_before_first_mag(t, mag, [gyr, acc, mag])
        if first:
            notes.append(f"started at the first {name} sample: {first} IMU samples before it")
    else:
        notes.append("no magnetometer topic (vehicle_magnetometer, sensor_combined."
                     "magnetometer_ga, sensor_mag)")
    require_imu(len(t), path, "sensor_combined", damage)

    found = _references(topics, origin)
    ref, references = pick_reference(found, reference)
    warning = magnitude_warning(acc, "sensor_combined")
    when, when_source = _date(topics)
    events, events_source = _state_events(topics, origin)
    if not events:
        notes.append("no flight state topics (vehicle_status, vehicle_land_detected): "
                     "eskf decides from the data when the vehicle flies")
    return Recording(path=path, format="ulog", t=t, gyr=gyr, acc=acc, mag=mag, world="NED",
                     body="FRD", source="sensor_combined", reference=ref,
                     cleanup=cleanup, notes=tuple(notes), damage=(damage,) if damage else (),
                     warnings=(warning,) if warning else (),
                     params=dict(ulog.initial_parameters), position=_position(topics),
                     when=when, when_source=when_source,
                     velocity=place_velocity(_velocity_rows(topics, origin), t),
                     mav_type=_mav_type(ulog.initial_parameters),
                     mav_type_source="parameter MAV_TYPE" if "MAV_TYPE" in
                     ulog.initial_parameters else "",
                     state_events=events, state_events_source=events_source,
                     references=references, autopilot=other_autopilot(found, ref))


def _bytes_after_last_message(path: Path) -> int:
    """Bytes at the end that do not make a whole message: a log cut while it was being
    written (power lost, copied early). pyulog drops them without a word.

    Walks the messages' 3-byte headers (size, type) from the file header on. A byte
    that is no message type means corruption inside the file, which pyulog skips by
    looking for the next sync; the walk cannot follow it there, so it claims nothing.
    """
    with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        size, pos = len(data), FILE_HEADER_BYTES
        while pos + MESSAGE_HEADER_BYTES <= size:
            if data[pos + 2] not in MESSAGE_TYPES:
                return 0
            end = pos + MESSAGE_HEADER_BYTES + (data[pos] | data[pos + 1] << 8)
            if end > size:
                break
            pos = end
        return max(0, size - pos)


def _state_events(topics: dict, origin: int) -> tuple[tuple[StateEvent, ...], str]:
    """Flight-state reports: ``vehicle_status.arming_state`` and the land detector
    (``vehicle_land_detected``: landed, maybe_landed or ground_contact all mean the
    thrust is not carrying the vehicle, so its in-flight model does not hold)."""
    events: list[StateEvent] = []
    used = []
    status = topics.get(("vehicle_status", 0))
    if status is not None and "arming_state" in status and len(status["timestamp"]):
        used.append("vehicle_status")
        armed = np.asarray(status["arming_state"]) == ARMING_STATE_ARMED
        events += [StateEvent(t, "armed", int(a))
                   for t, a in zip(_seconds(status["timestamp"], origin).tolist(),
                                   armed.tolist(), strict=True)]
    land = topics.get(("vehicle_land_detected", 0))
    if land is not None and "landed" in land and len(land["timestamp"]):
        used.append("vehicle_land_detected")
        down = np.zeros(len(land["timestamp"]), dtype=bool)
        for key in ("landed", "maybe_landed", "ground_contact"):
            if key in land:
                down |= np.asarray(land[key]) != 0
        events += [StateEvent(t, "land_detector", int(d))
                   for t, d in zip(_seconds(land["timestamp"], origin).tolist(),
                                   down.tolist(), strict=True)]
    events.sort(key=lambda e: e.t)
    return tuple(events), " + ".join(used)


def _mav_type(params: dict) -> int | None:
    value = params.get("MAV_TYPE")
    return int(value) if value is not None else None


def _vec(data: dict, fmt: str) -> np.ndarray:
    return np.stack([np.asarray(data[fmt.format(i)], dtype=float) for i in range(3)], axis=1)


def _seconds(stamps: np.ndarray, origin: int) -> np.ndarray:
    return (np.asarray(stamps, dtype=np.int64) - origin) * US


def _time(data: dict, origin: int) -> np.ndarray:
    """``timestamp_sample`` when the topic fills it (SITL groundtruth leaves it 0)."""
    ts = data.get("timestamp_sample")
    if ts is not None and np.all(ts > 0):
        return _seconds(ts, origin)
    return _seconds(data["timestamp"], origin)


def _mag_topic(topics: dict) -> tuple[str, dict, str] | None:
    if ("vehicle_magnetometer", 0) in topics:
        return "vehicle_magnetometer", topics[("vehicle_magnetometer", 0)], "magnetometer_ga[{}]"
    combined = _combined_mag(topics[("sensor_combined", 0)])
    if combined is not None:
        return "sensor_combined.magnetometer_ga", combined, "magnetometer_ga[{}]"
    if ("sensor_mag", 0) in topics:  # raw sensor, axes already rotated to FRD
        return "sensor_mag", topics[("sensor_mag", 0)], "{}"
    return None


def _combined_mag(imu: dict) -> dict | None:
    """The magnetometer rows of an old ``sensor_combined`` (one per new reading).

    Each row repeats the latest reading; ``magnetometer_timestamp_relative`` says when
    it was taken relative to the row (INT32_MAX: none yet), so repeated readings get
    the same time and are dropped as duplicates by the caller's time cleanup.
    """
    if "magnetometer_ga[0]" not in imu:
        return None
    rel = np.asarray(imu.get("magnetometer_timestamp_relative",
                             np.zeros(len(imu["timestamp"]))), dtype=np.int64)
    ok = rel != RELATIVE_INVALID
    values = {f"magnetometer_ga[{i}]": np.asarray(imu[f"magnetometer_ga[{i}]"])[ok]
              for i in range(3)}
    if not ok.any() or not np.any([np.any(v != 0) for v in values.values()]):
        return None
    return {"timestamp": np.asarray(imu["timestamp"], dtype=np.int64)[ok] + rel[ok], **values}


def _references(topics: dict, origin: int) -> dict[str, Reference | None]:
    """Truth from the simulator's groundtruth topic, the autopilot's from its estimate."""
    return {"truth": _topic_reference(topics, "vehicle_attitude_groundtruth", "truth", origin),
            "autopilot": _topic_reference(topics, "vehicle_attitude", "autopilot", origin)}


def _topic_reference(topics: dict, name: str, kind: str, origin: int) -> Reference | None:
    data = topics.get((name, 0))
    if data is None or len(data["timestamp"]) == 0:
        return None
    return make_reference(_time(data, origin), _vec4(data), kind, name)


def _vec4(data: dict) -> np.ndarray:
    return np.stack([np.asarray(data[f"q[{i}]"], dtype=float) for i in range(4)], axis=1)


def _gps(topics: dict) -> dict | None:
    for name in GPS_TOPICS:
        data = topics.get((name, 0))
        if data is not None and len(data["timestamp"]) > 0:
            return data
    return None


def _gps_position(data: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """lat, lon [deg], alt [m] of a GPS topic: ints (1e-7 deg, mm) or, from PX4 1.14
    on, ``latitude_deg`` / ``longitude_deg`` / ``altitude_msl_m``."""
    if "latitude_deg" in data:
        return (np.asarray(data["latitude_deg"], float), np.asarray(data["longitude_deg"], float),
                np.asarray(data["altitude_msl_m"], float))
    return (np.asarray(data["lat"], float) * 1e-7, np.asarray(data["lon"], float) * 1e-7,
            np.asarray(data["alt"], float) * 1e-3)


def _position(topics: dict) -> Position | None:
    gps = _gps(topics)
    if gps is not None:
        lat, lon, alt = _gps_position(gps)
        ok = (np.asarray(gps["fix_type"]) >= 2) & ((lat != 0) | (lon != 0))
        if ok.any():
            return Position(float(np.median(lat[ok])), float(np.median(lon[ok])),
                            float(np.median(alt[ok])), _gps_name(topics))
    glob = topics.get(("vehicle_global_position", 0))
    if glob is not None and len(glob["timestamp"]) > 0:
        lat, lon = np.asarray(glob["lat"], float), np.asarray(glob["lon"], float)
        ok = (lat != 0) | (lon != 0)
        if ok.any():
            return Position(float(np.median(lat[ok])), float(np.median(lon[ok])),
                            float(np.median(np.asarray(glob["alt"], float)[ok])),
                            "vehicle_global_position")
    return None


def _gps_name(topics: dict) -> str:
    return next(n for n in GPS_TOPICS if (n, 0) in topics)


def _date(topics: dict) -> tuple[_dt.datetime | None, str]:
    """UTC date from the GPS's ``time_utc_usec`` (PX4 has no other wall clock)."""
    gps = _gps(topics)
    if gps is not None and "time_utc_usec" in gps:
        utc = np.asarray(gps["time_utc_usec"], dtype=np.int64)
        utc = utc[utc > 0]
        if utc.size:
            return (_dt.datetime.fromtimestamp(int(np.median(utc)) * US, _dt.UTC),
                    f"{_gps_name(topics)}.time_utc_usec")
    return None, ""


def _velocity_rows(topics: dict, origin: int) -> VelocityRows | None:
    """vehicle_local_position (v_xy_valid / v_z_valid), else the GPS's NED velocity.

    Available when published (``timestamp``), valid at ``timestamp_sample`` if filled.
    """
    lp = topics.get(("vehicle_local_position", 0))
    if lp is not None and len(lp["timestamp"]) > 1:
        v = np.column_stack([np.asarray(lp[k], float) for k in ("vx", "vy", "vz")])
        xy = np.asarray(lp.get("v_xy_valid", np.ones(len(v))), bool)
        z = np.asarray(lp.get("v_z_valid", np.ones(len(v))), bool)
        v[~xy, :2] = np.nan
        v[~z, 2] = np.nan
        if np.isfinite(v[:, :2]).any():  # vertical alone: a GPS velocity is worth more
            return VelocityRows(v, _seconds(lp["timestamp"], origin), _time(lp, origin),
                                "vehicle_local_position", after_arrival=False)
    gps = _gps(topics)
    if gps is not None and len(gps["timestamp"]) > 1 and "vel_n_m_s" in gps:
        v = np.column_stack([np.asarray(gps[k], float)
                             for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")])
        ok = (np.asarray(gps["vel_ned_valid"], bool) & (np.asarray(gps["fix_type"]) >= 3))
        v[~ok] = np.nan
        if np.isfinite(v[:, :2]).any():
            return VelocityRows(v, _seconds(gps["timestamp"], origin), _time(gps, origin),
                                _gps_name(topics), after_arrival=False)
    return None
