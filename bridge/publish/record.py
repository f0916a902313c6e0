"""``run --record session.tlog``: the connection's traffic, in and out, as a tlog.

The format is MAVProxy's / QGroundControl's telemetry log, which pymavlink, the replay
tools here (``attitude-bridge replay session.tlog``) and PlotJuggler read: each
MAVLink frame as it crossed the wire (signature included), preceded by its wall-clock
time as a big-endian 64-bit count of microseconds since 1970. Incoming frames are
stamped when they were read, outgoing ones when they were written, so the log shows
the bridge's latency as well as the vehicle's data; every frame of the connection is
kept, refused ones too (what a forger sent is part of the story).

Writes go through a buffered file (a few system calls per second at kHz rates), flushed
with every status update so that a killed bridge loses at most a second.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import BinaryIO

_STAMP = struct.Struct(">Q")


class TlogRecorder:
    """Appends frames with their arrival (or send) time to a .tlog file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 (closed in close)
        self.frames_in = 0
        self.frames_out = 0
        self.bytes = 0

    def record(self, frame: bytes, incoming: bool) -> None:
        """One MAVLink frame, as read or as written."""
        f = self._file
        if f is None:
            return
        f.write(_STAMP.pack(int(time.time() * 1e6)))
        f.write(frame)
        self.bytes += len(frame) + 8
        if incoming:
            self.frames_in += 1
        else:
            self.frames_out += 1

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        f, self._file = self._file, None
        if f is not None:
            f.close()

    def summary(self) -> str:
        return (f"recorded {self.frames_in} frames in and {self.frames_out} out "
                f"({self.bytes / 1e6:.1f} MB) to {self.path}")
