"""Where does a PX4 SITL tlog's magnetic field point, by source: HIGHRES_IMU (PX4's
calibrated field minus its EKF2's bias estimate) against SCALED_IMU (the raw sensor).

    python benchmarks/px4_mag_source.py FILE.tlog... [--window 4]   # seconds per file

Each reading is turned into the world by the simulator's true attitude
(HIL_STATE_QUATERNION, the latest before it in the file), and the field's azimuth (east
of true north) is averaged per window of arrival time. On SIH the world field is fixed,
so a source whose azimuth moves is being moved by something other than the sensor:
README, "With a real autopilot", and ``imu/px4_mag.py``. Needs a tlog recorded with both
streams (``benchmarks/record_sitl_flights.py`` asks for them).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil

from estimators import quat as Q
from replay.readers.tlog import HIGHRES_MAG_BITS


def world_fields(path: Path, lag_s: float) -> dict[str, np.ndarray]:
    """Per source, rows of (arrival s, north, east, down gauss) for each new reading,
    turned by the truth that arrived ``lag_s`` before it (the reading's age)."""
    conn = mavutil.mavlink_connection(str(path))
    truth_t: list[float] = []
    truth_q: list[list[float]] = []
    readings: dict[str, list] = {"HIGHRES_IMU": [], "SCALED_IMU": []}
    last_raw = None
    while (m := conn.recv_match(type=["HIL_STATE_QUATERNION", "HIGHRES_IMU", "SCALED_IMU"]))\
            is not None:
        kind = m.get_type()
        if kind == "HIL_STATE_QUATERNION":
            truth_t.append(m._timestamp)
            truth_q.append(list(m.attitude_quaternion))
        elif kind == "HIGHRES_IMU":
            if m.fields_updated & HIGHRES_MAG_BITS == HIGHRES_MAG_BITS:
                readings[kind].append((m._timestamp, m.xmag, m.ymag, m.zmag))
        elif (m.xmag, m.ymag, m.zmag) != last_raw:  # SCALED_IMU, mgauss; repeats skipped
            last_raw = (m.xmag, m.ymag, m.zmag)
            readings[kind].append((m._timestamp, m.xmag * 1e-3, m.ymag * 1e-3, m.zmag * 1e-3))
    t_truth, q_truth = np.array(truth_t), np.array(truth_q).reshape(-1, 4)
    out = {}
    for kind, rows in readings.items():
        r = np.array(rows, dtype=float).reshape(-1, 4)
        k = np.searchsorted(t_truth, r[:, 0] - lag_s, side="right") - 1
        r = r[k >= 0]
        out[kind] = np.column_stack([r[:, 0], Q.rotate(q_truth[k[k >= 0]], r[:, 1:])])
    return out


def azimuth_deg(north_east: np.ndarray) -> float:
    mean = north_east.mean(axis=0)
    return math.degrees(math.atan2(mean[1], mean[0]))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("files", nargs="+", type=Path)
    p.add_argument("--window", type=float, default=4.0, help="seconds per mean (4)")
    p.add_argument("--lag", type=float, default=0.03,
                   help="a reading's age [s]: the truth this much earlier turns it (0.03, "
                        "where the turned field is steadiest in these recordings)")
    args = p.parse_args()
    for path in args.files:
        fields = world_fields(path, args.lag)
        if any(len(v) == 0 for v in fields.values()):
            print(f"{path}: needs HIL_STATE_QUATERNION, HIGHRES_IMU and SCALED_IMU")
            continue
        start = min(v[0, 0] for v in fields.values())
        end = max(v[-1, 0] for v in fields.values())
        print(f"{path.name}: field azimuth [deg] per {args.window:g} s")
        for kind, rows in fields.items():
            t = rows[:, 0] - start
            means = [f"{azimuth_deg(rows[(t >= a) & (t < a + args.window), 1:3]):5.1f}"
                     if np.any((t >= a) & (t < a + args.window)) else "   - "
                     for a in np.arange(0.0, end - start, args.window)]
            print(f"  {kind:<11} whole {azimuth_deg(rows[:, 1:3]):5.2f}: {' '.join(means)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
