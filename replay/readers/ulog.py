"""PX4 ULog: sensor_combined (FRD, SI), vehicle_magnetometer (Gauss), attitude references.

Times are the topics' own µs timestamps (``timestamp_sample`` when the topic has it: the
time of the IMU sample an attitude belongs to, which is what lag must be measured from).
``vehicle_attitude_groundtruth`` (SITL) is truth; otherwise ``vehicle_attitude`` (PX4's
EKF, FRD -> NED) is the autopilot reference.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..dataset import Recording, Reference, ReplayInputError
from ..timebase import sample_and_hold
from ._common import clean_stream, make_reference, require_imu, trim_before_first_mag

US = 1e-6


def read(path: Path, reference: str = "auto") -> Recording:
    from pyulog import ULog  # imported here: only ULog users pay for it

    try:
        ulog = ULog(str(path))
    except Exception as exc:  # pyulog raises bare Exceptions on corrupt headers
        raise ReplayInputError(f"{path}: not a readable ULog file ({exc})") from exc
    topics = {(d.name, d.multi_id): d.data for d in ulog.data_list}

    imu = topics.get(("sensor_combined", 0))
    if imu is None or len(imu["timestamp"]) < 2:
        raise ReplayInputError(f"{path}: no IMU samples found (ULog topic sensor_combined)")
    # Subtract a common origin in integers first: PX4 can stamp with epoch µs (~1.7e15),
    # where float64 seconds keep only ~0.2 µs and every dt would carry that jitter.
    origin = int(imu["timestamp"][0])
    t = _seconds(imu["timestamp"], origin)
    gyr = _vec(imu, "gyro_rad[{}]")
    acc = _vec(imu, "accelerometer_m_s2[{}]")
    t, (gyr, acc), cleanup = clean_stream(t, gyr, acc)
    notes = []

    mag = None
    mag_topic = _mag_topic(topics)
    if mag_topic is not None:
        name, data, fmt = mag_topic
        tm, (m,), _ = clean_stream(_time(data, origin), _vec(data, fmt))
        mag = sample_and_hold(tm, m, t)
        first, t, (gyr, acc, mag) = trim_before_first_mag(t, mag, [gyr, acc, mag])
        if first:
            notes.append(f"started at the first {name} sample: {first} IMU samples before it")
    require_imu(len(t), path, "sensor_combined")

    ref = _reference(topics, reference, origin)
    return Recording(path=path, format="ulog", t=t, gyr=gyr, acc=acc, mag=mag, world="NED",
                     body="FRD", source="sensor_combined", reference=ref,
                     cleanup=cleanup, notes=tuple(notes))


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
    if ("sensor_mag", 0) in topics:  # older logs: raw sensor, axes already rotated to FRD
        return "sensor_mag", topics[("sensor_mag", 0)], "{}"
    return None


def _reference(topics: dict, reference: str, origin: int) -> Reference | None:
    order = {"auto": ("vehicle_attitude_groundtruth", "vehicle_attitude"),
             "truth": ("vehicle_attitude_groundtruth",),
             "autopilot": ("vehicle_attitude",)}[reference]
    for name in order:
        data = topics.get((name, 0))
        if data is not None and len(data["timestamp"]) > 0:
            kind = "truth" if name.endswith("groundtruth") else "autopilot"
            return make_reference(_time(data, origin), _vec4(data), kind, name)
    return None


def _vec4(data: dict) -> np.ndarray:
    return np.stack([np.asarray(data[f"q[{i}]"], dtype=float) for i in range(4)], axis=1)
