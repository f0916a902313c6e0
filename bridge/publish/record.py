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

import contextlib
import logging
import struct
import time
from pathlib import Path
from typing import BinaryIO

_STAMP = struct.Struct(">Q")
log = logging.getLogger(__name__)


class TlogRecorder:
    """Appends frames with their arrival (or send) time to a .tlog file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 (closed in close)
        self.frames_in = 0
        self.frames_out = 0
        self.bytes = 0
        self.failed: str = ""  # why the recording stopped early ("" while it goes on)

    def record(self, frame: bytes, incoming: bool) -> None:
        """One MAVLink frame, as read or as written."""
        f = self._file
        if f is None:
            return
        try:
            f.write(_STAMP.pack(int(time.time() * 1e6)))
            f.write(frame)
        except OSError as exc:
            self._stop(exc)
            return
        self.bytes += len(frame) + 8
        if incoming:
            self.frames_in += 1
        else:
            self.frames_out += 1

    def _stop(self, exc: OSError) -> None:
        """A write failed (a full disk, a removed drive): the recording stops, once and
        with one warning, and the bridge goes on — its job is the attitude, and a
        traceback per frame would bury everything else in the log."""
        f, self._file = self._file, None
        self.failed = exc.strerror or str(exc)
        log.warning("recording to %s stopped: %s (the bridge goes on without it)",
                    self.path, self.failed)
        if f is not None:
            with contextlib.suppress(OSError):  # the buffered rest cannot be written either
                f.close()

    def flush(self) -> None:
        if self._file is not None:
            try:
                self._file.flush()
            except OSError as exc:
                self._stop(exc)

    def close(self) -> None:
        if self._file is None:
            return
        try:
            self._file.flush()
        except OSError as exc:
            self._stop(exc)
            return
        f, self._file = self._file, None
        f.close()

    def summary(self) -> str:
        stopped = f", stopped early: {self.failed}" if self.failed else ""
        return (f"recorded {self.frames_in} frames in and {self.frames_out} out "
                f"({self.bytes / 1e6:.1f} MB) to {self.path}{stopped}")
