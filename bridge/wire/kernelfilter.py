"""A socket filter (classic BPF) that refuses a flood inside the kernel.

Refusing a datagram in Python costs a system call and a few microseconds; at 100 k
datagrams/s on a small computer that is most of a core, and once the bridge falls
behind, the kernel drops from the full socket buffer blindly — the vehicle's packets as
much as the flood's. A filter attached with SO_ATTACH_FILTER runs before the datagram
is queued: the flood never reaches the buffer.

The program keeps what the admission gate would let through anyway: MAVLink 1/2 frames
from an admitted sender (the vehicle's system id and, once known, its autopilot's
component id), and HEARTBEATs from anyone (how a ground station
announces itself). Of everything else it passes a random 1/``SAMPLE`` to user space,
cut to ``MARK_LEN`` bytes (a filter's return value is how much of the datagram to keep),
where the gate counts it (times ``SAMPLE``, as an estimate) — the refusals stay visible
without their cost, and are told apart from datagrams queued before the filter went
on. Offsets count from the UDP header (8 bytes) in front of the payload; a datagram too
short for a load is dropped by the kernel, which is what we want.

Linux only; elsewhere :func:`attach` reports False and the gate works alone.
"""

from __future__ import annotations

import contextlib
import ctypes
import socket
import struct
from collections.abc import Mapping

SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)
SO_DETACH_FILTER = getattr(socket, "SO_DETACH_FILTER", 27)
SAMPLE = 64  # one refused datagram in SAMPLE reaches user space to be counted
MARK_LEN = 3  # ... cut to this length (no MAVLink frame is that short)

# Classic BPF opcodes (linux/filter.h).
_LD_B_ABS, _LD_W_ABS = 0x30, 0x20
_JEQ_K, _AND_K, _RET_K, _JA = 0x15, 0x54, 0x06, 0x05
_RANDOM = (-0x1000 + 56) & 0xFFFFFFFF  # SKF_AD_OFF + SKF_AD_RANDOM
_UDP = 8  # the payload starts after the UDP header
_ACCEPT = 0x40000  # bytes of the datagram to keep (all of it)


#: Admitted senders: system id -> the component ids that may send everything (None: any).
Senders = Mapping[int, "frozenset[int] | None"]


def program(vehicles: Senders) -> list[tuple[int, int, int, int]]:
    """The filter's instructions (code, jt, jf, k) for the admitted senders."""
    code: list[tuple[str, int, str | None, str | None, int | str]] = []

    def op(label: str, opcode: int, k: int | str = 0, jt: str | None = None,
           jf: str | None = None) -> None:
        code.append((label, opcode, jt, jf, k))

    op("", _LD_B_ABS, _UDP)  # magic
    op("", _JEQ_K, 0xFD, "v2", None)
    op("", _JEQ_K, 0xFE, "v1", "sample")
    for version, sys_at, comp_at, msg_bytes in (("v2", 5, 6, (7, 8, 9)), ("v1", 3, 4, (5,))):
        op(version, _LD_B_ABS, _UDP + sys_at)
        for sysid in sorted(vehicles):
            op("", _JEQ_K, sysid, f"{version}_{sysid}", None)
        op("", _JA, f"{version}_hb")
        for sysid, comps in sorted(vehicles.items()):
            if comps is None:
                op(f"{version}_{sysid}", _RET_K, _ACCEPT)
                continue
            op(f"{version}_{sysid}", _LD_B_ABS, _UDP + comp_at)
            for compid in sorted(comps):
                op("", _JEQ_K, compid, "accept", None)
            op("", _JA, f"{version}_hb")
        # Anyone's HEARTBEAT (message id 0, three bytes in MAVLink 2).
        for i, at in enumerate(msg_bytes):
            op(f"{version}_hb" if i == 0 else "", _LD_B_ABS, _UDP + at)
            last = i == len(msg_bytes) - 1
            op("", _JEQ_K, 0, "accept" if last else None, "sample")
    op("sample", _LD_W_ABS, _RANDOM)
    op("", _AND_K, SAMPLE - 1)
    op("", _JEQ_K, 0, "mark", "drop")
    op("mark", _RET_K, _UDP + MARK_LEN)  # counted from the UDP header
    op("accept", _RET_K, _ACCEPT)
    op("drop", _RET_K, 0)
    where = {label: i for i, (label, *_rest) in enumerate(code) if label}
    out = []
    for i, (_label, opcode, jt, jf, k) in enumerate(code):
        t = where[jt] - i - 1 if jt else 0
        f = where[jf] - i - 1 if jf else 0
        kk = where[k] - i - 1 if isinstance(k, str) else k
        if max(t, f) > 255:
            raise ValueError("too many admitted senders for one socket filter")
        out.append((opcode, t, f, kk))
    return out


class KernelFilter:
    """Attaches/detaches the program on one socket (keeps its memory alive meanwhile)."""

    def __init__(self) -> None:
        self._buf: ctypes.Array | None = None
        self.attached = False

    def attach(self, sock: socket.socket, vehicles: Senders) -> bool:
        insns = program(vehicles)
        buf = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *i) for i in insns))
        fprog = struct.pack("HL", len(insns), ctypes.addressof(buf))
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
        except OSError:
            return False
        self._buf = buf
        self.attached = True
        return True

    def detach(self, sock: socket.socket) -> None:
        if self.attached:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
        self.attached = False
        self._buf = None
