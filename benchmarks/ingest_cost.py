"""Per-sample cost of ``bridge.vehicle.ingest.Ingest.handle`` (no sockets, no estimator).

    PYTHONPATH=. python3 benchmarks/ingest_cost.py [--calibration calib.toml]

Decodes a few thousand RAW_IMU / SCALED_IMU / HIGHRES_IMU messages once, then times
``handle`` over them (best of several repeats, to be robust to a shared machine). Used
to check that applying a sensor calibration keeps the per-sample path cheap.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bridge.vehicle.ingest import Ingest
from bridge.wire.mav import mavlink
from imu.boards import gy86

N = 5000
REPEATS = 7


def messages(kind: str) -> list:
    rng = np.random.default_rng(0)
    mav = mavlink.MAVLink(None, 1, 1)
    out = []
    for i in range(N):
        a = rng.integers(-20, 21, 3)
        g = rng.integers(-5, 6, 3)
        t_us = 1_000_000 + i * 1000
        if kind == "RAW_IMU":
            m = mavlink.MAVLink_raw_imu_message(t_us, int(a[0]), int(a[1]), 4096 + int(a[2]),
                                                int(g[0]), int(g[1]), int(g[2]), 300, 10, -500,
                                                0, 2500)
        elif kind == "SCALED_IMU":
            m = mavlink.MAVLink_scaled_imu_message(t_us // 1000, int(a[0]), int(a[1]),
                                                   -1000 + int(a[2]), int(g[0]), int(g[1]),
                                                   int(g[2]), 200, 10, 400, 2500)
        else:
            m = mavlink.MAVLink_highres_imu_message(
                t_us, 0.01 * a[0], 0.01 * a[1], -9.8, 0.001 * g[0], 0.001 * g[1],
                0.001 * g[2], 0.2, 0.01, 0.4, 1013.0, 0.0, 0.0, 25.0, 0x1FF, 0)
        out.append(mavlink.MAVLink(None, 1, 1).parse_buffer(m.pack(mav))[0])
    return out


def time_kind(kind: str, calibration) -> float:
    msgs = messages(kind)
    best = float("inf")
    for _ in range(REPEATS):
        kwargs = {} if calibration is None else {"calibration": calibration}
        ingest = Ingest(gy86(), **kwargs)
        t0 = time.perf_counter()
        for m in msgs:
            ingest.handle(m, 0.0)
        best = min(best, (time.perf_counter() - t0) / len(msgs))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calibration", metavar="FILE", help="calibration TOML to apply")
    args = parser.parse_args()
    calibration = None
    if args.calibration:
        from imu.calibration import SensorCalibration

        calibration = SensorCalibration.load(args.calibration)
    for kind in ("RAW_IMU", "SCALED_IMU", "HIGHRES_IMU"):
        print(f"{kind:12s} {time_kind(kind, calibration) * 1e6:6.2f} µs/sample")


if __name__ == "__main__":
    main()
