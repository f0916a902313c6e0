"""Achieved send rate and timing jitter of the HIL emulator in real time.

Runs `attitude-bridge hil` as a separate process (as a user would) at each rate and
receives on a loopback UDP socket in this process, then reports, for RAW_IMU:
achieved rate, inter-arrival jitter and lateness against the ideal schedule.

    PYTHONPATH=. python3 benchmarks/hil_rate.py [--rates 1000 8000] [--duration 10]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RAW_IMU_ID = 27


def measure(rate: float, duration: float, profile: str) -> dict[str, float]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(1.0)
    port = sock.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.app.cli", "hil", "--target", f"udp:127.0.0.1:{port}",
         "--rate", str(rate), "--duration", str(duration), "--profile", profile],
        env=dict(os.environ, PYTHONPATH=str(REPO)), stderr=subprocess.DEVNULL)
    arrivals, seen_any = [], False
    deadline = time.monotonic() + duration + 30.0
    while time.monotonic() < deadline:
        try:
            data = sock.recv(65535)
        except TimeoutError:
            if seen_any:
                break
            continue
        seen_any = True
        # MAVLink 2: message id is bytes 7..9 (little-endian)
        if data[0] == 0xFD and int.from_bytes(data[7:10], "little") == RAW_IMU_ID:
            arrivals.append(time.perf_counter())
    proc.wait(timeout=30)
    sock.close()
    t = np.array(arrivals)
    n = len(t)
    gaps = np.diff(t)
    ideal = t[0] + np.arange(n) / rate
    late = (t - ideal) - np.min(t - ideal)  # lateness relative to the earliest packet
    return {
        "rate_hz": rate, "received": n, "expected": round(rate * duration),
        "achieved_hz": (n - 1) / (t[-1] - t[0]),
        "gap_mean_us": gaps.mean() * 1e6, "gap_std_us": gaps.std() * 1e6,
        "gap_p99_us": np.percentile(gaps, 99) * 1e6, "gap_max_ms": gaps.max() * 1e3,
        "late_p50_ms": np.percentile(late, 50) * 1e3, "late_p99_ms": np.percentile(late, 99) * 1e3,
        "late_max_ms": late.max() * 1e3,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[1000.0, 8000.0])
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--profile", default="flight")
    args = parser.parse_args()
    print(f"{'rate':>6} {'recv/exp':>13} {'achieved':>9} {'gap std':>8} {'gap p99':>8} "
          f"{'gap max':>8} {'late p50':>8} {'late p99':>8} {'late max':>8}")
    for rate in args.rates:
        r = measure(rate, args.duration, args.profile)
        print(f"{r['rate_hz']:6.0f} {r['received']:6d}/{r['expected']:<6d} "
              f"{r['achieved_hz']:9.1f} {r['gap_std_us']:6.0f}us {r['gap_p99_us']:6.0f}us "
              f"{r['gap_max_ms']:6.1f}ms {r['late_p50_ms']:6.2f}ms {r['late_p99_ms']:6.2f}ms "
              f"{r['late_max_ms']:6.1f}ms")


if __name__ == "__main__":
    main()
