"""A flood of valid RAW_IMU frames from another vehicle (sysid 77, source 127.0.0.9), paced
at a given rate, in a process of its own so that it competes with the bridge for the CPU
as a real attacker would. Used by `bridge_attack.py flood` and the flood-fairness test.

    python benchmarks/flood_sender.py PORT SECONDS RATE    # prints how many it sent
"""

from __future__ import annotations

import os
import socket
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink

SOURCE_ADDRESS = "127.0.0.9"
SYSID = 77


def frames(count: int = 256) -> list[bytes]:
    """``count`` consecutive frames (sequence numbers and stamps advance)."""
    mav = mavlink.MAVLink(None, SYSID, 1)
    out = []
    for i in range(count):
        out.append(mavlink.MAVLink_raw_imu_message(i * 1000, 0, 0, -4096, 0, 0, 0, 100, 0,
                                                   300, 0, 0).pack(mav))
        mav.seq = (mav.seq + 1) % 256
    return out


def flood(port: int, seconds: float, rate: float) -> int:
    """Send to 127.0.0.1:``port`` at ``rate`` frames/s for ``seconds``; frames the kernel
    refuses (buffer full) count as sent. Returns the number sent."""
    pkts = frames()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((SOURCE_ADDRESS, 0))
        dst = ("127.0.0.1", port)
        start = time.perf_counter()
        sent = 0
        while (now := time.perf_counter() - start) < seconds:
            while sent < int(now * rate):
                try:  # noqa: SIM105 (a hot loop: suppress() costs a context manager per frame)
                    s.sendto(pkts[sent & 255], dst)
                except OSError:
                    pass
                sent += 1
            time.sleep(0.0003)
    return sent


if __name__ == "__main__":
    print(flood(int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])))
