"""A real MAVLink receiver for the HIL tests: a loopback UDP socket read from asyncio,
each datagram parsed on its own by pymavlink and classified (valid, corrupt, truncated)."""

from __future__ import annotations

import asyncio
import os
import socket
import struct
import time
from dataclasses import dataclass, field

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink

MAVLINK2_MAGIC = 0xFD
#: Linux: the kernel stamps each datagram with when it reached the socket (struct
#: timespec in the ancillary data), which the stdlib names on some versions only.
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("qq")


@dataclass
class Received:
    time_s: float  # arrival (perf_counter)
    seq: int
    data: bytes
    msg: object  # pymavlink message
    #: when the datagram reached the socket (kernel stamp, CLOCK_REALTIME): the sender's
    #: pace, whenever this process got round to reading it (None: not stamped)
    kernel_s: float | None = None


@dataclass
class Receiver:
    """Collects every datagram arriving on a loopback port."""

    sock: socket.socket
    valid: list[Received] = field(default_factory=list)
    corrupt: int = 0
    truncated: int = 0
    datagrams: int = 0
    peer: tuple | None = None  # where the stream comes from (replies go there)

    @classmethod
    def open(cls) -> Receiver:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        return cls(sock)

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        loop.add_reader(self.sock.fileno(), self.drain)

    def detach(self, loop: asyncio.AbstractEventLoop) -> None:
        loop.remove_reader(self.sock.fileno())
        self.drain()
        self.sock.close()

    def drain(self) -> None:
        """Read everything waiting (asyncio reader callback, or call directly)."""
        while True:
            try:
                data, stamp = self._receive()
            except (BlockingIOError, InterruptedError):
                return
            self.handle(data, time.perf_counter(), stamp)

    def _receive(self) -> tuple[bytes, float | None]:
        """One datagram and the kernel's stamp of its arrival (None if there is none)."""
        data, ancillary, _flags, self.peer = self.sock.recvmsg(65535, 64)
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and \
                    len(payload) >= _TIMESPEC.size:
                sec, nsec = _TIMESPEC.unpack_from(payload)
                return data, sec + nsec * 1e-9
        return data, None

    def handle(self, data: bytes, now: float, kernel_s: float | None = None) -> None:
        self.datagrams += 1
        if len(data) < 12 or data[0] != MAVLINK2_MAGIC:
            self.truncated += 1
            return
        expected = 10 + data[1] + 2 + (13 if data[2] & 0x01 else 0)
        if len(data) < expected:
            self.truncated += 1
            return
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        msgs = parser.parse_buffer(data) or []
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.corrupt += 1
            else:
                self.valid.append(Received(now, msg.get_seq(), data, msg, kernel_s))

    def send(self, msg, sysid: int = 255, compid: int = 190) -> None:
        """Send a pymavlink message to the stream's source (as a ground station)."""
        mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.sock.sendto(msg.pack(mav), self.peer)

    def of_type(self, kind: str) -> list:
        return [r.msg for r in self.valid if r.msg.get_type() == kind]

    def blocking_collect(self, seconds_idle: float, limit_s: float) -> None:
        """Read until no datagram came for ``seconds_idle`` (for a subprocess sender)."""
        self.sock.setblocking(True)
        self.sock.settimeout(seconds_idle)
        end = time.monotonic() + limit_s
        while time.monotonic() < end:
            try:
                data, stamp = self._receive()
            except TimeoutError:
                if self.datagrams:
                    return
                continue
            self.handle(data, time.perf_counter(), stamp)


def unwrap_seq(seqs: list[int]) -> list[int]:
    """8-bit MAVLink sequence numbers as a running count (steps of |d| < 128)."""
    out: list[int] = []
    for s in seqs:
        if not out:
            out.append(s)
            continue
        d = (s - out[-1]) % 256
        out.append(out[-1] + (d - 256 if d >= 128 else d))
    return out
