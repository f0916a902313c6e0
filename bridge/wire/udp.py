"""UDP links: ``udpin`` (listen, answer the peers heard) and ``udpout`` (a fixed peer).

A ``udpin`` link answers only peers it has heard speak valid (and, with signing,
verified) MAVLink: one byte from a spoofed address earns nothing. The peer table is
bounded (``max_peers``, silent peers expire after ``peer_timeout_s``); refusals are
counted. An optional ``gate(data)`` sees each datagram before it is parsed, so that a
flood can be refused for the price of a header peek (see :mod:`bridge.wire.admission`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
import sys
import time

from .codec import SigningConfig
from .kernelfilter import KernelFilter, Senders
from .link import (
    BIND_REASONS,
    MAX_DATAGRAMS_PER_WAKEUP,
    PEER_REFRESH_S,
    UDP_RECEIVE_BUFFER,
    Link,
    LinkError,
    LinkOptions,
    LinkUrl,
    MessageHandler,
)
from .mav import MAVLinkMessage

log = logging.getLogger(__name__)

#: Linux's SO_TIMESTAMPNS (asm-generic/socket.h; Python's socket module lacks it): each
#: datagram carries the time the kernel received it, as a struct timespec.
SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@qq")
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size)


class UdpLink(Link):
    """``udpin`` listens and answers the peers it heard valid MAVLink from in the last
    ``peer_timeout_s``; ``udpout`` sends to one fixed address and also reads its replies.

    A plain non-blocking socket read through ``add_reader``: each readiness event drains
    every queued datagram (asyncio's datagram transport reads one per loop iteration,
    which lets a fast sender overflow the socket buffer). One parser serves all peers:
    a datagram holds whole packets, so whatever is left of one is discarded before the
    next is parsed and nothing of one peer's input can merge with another's.
    """

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None,
                 options: LinkOptions | None = None) -> None:
        super().__init__(url, on_message, signing, options)
        self._sock: socket.socket | None = None
        self._peers: dict[tuple, float] = {}  # address -> monotonic time last heard
        self._target: tuple | None = None
        self._peer_list: list[tuple] = []
        self._peers_valid_until = 0.0
        self._filter = KernelFilter()

    def kernel_filter(self, vehicles: Senders | None) -> bool:
        """Refuse, in the kernel, what only these senders may send (None: detach)."""
        if self._sock is None:
            return False
        if vehicles is None:
            self._filter.detach(self._sock)
            return False
        ok = self._filter.attach(self._sock, vehicles)
        if ok:
            log.warning("%s: many datagrams from senders not served (another vehicle "
                        "than --vehicle asks, or a flood): refused in the kernel from now "
                        "on", self.name)
        return ok

    @property
    def connected(self) -> bool:
        if self._sock is None:
            return False
        return self.url.kind == "udpout" or bool(self.peers())

    @property
    def local_port(self) -> int:
        assert self._sock is not None
        return self._sock.getsockname()[1]

    def peers(self) -> list[tuple]:
        """Peers heard from recently (recomputed at most every PEER_REFRESH_S: this is
        on the per-sample output path); expired ones leave the table."""
        now = time.monotonic()
        if now >= self._peers_valid_until:
            timeout = self.options.peer_timeout_s
            expired = [a for a, seen in self._peers.items() if now - seen >= timeout]
            for addr in expired:
                del self._peers[addr]
            self.stats.peers_expired += len(expired)
            self._peer_list = list(self._peers)
            self.stats.peers = len(self._peer_list)
            self._peers_valid_until = now + PEER_REFRESH_S
        return self._peer_list

    async def start(self) -> None:
        """Resolve and bind; LinkError saying why when that is impossible."""
        address = await self._resolve(socket.AF_INET, socket.SOCK_DGRAM)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        with contextlib.suppress(OSError):  # absorb bursts (e.g. a GC pause at 8 kHz)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
        try:
            if self.url.kind == "udpin":
                sock.bind(address)
            else:
                sock.bind(("0.0.0.0", 0))
                self._target = address
        except OSError as exc:
            sock.close()
            reason = BIND_REASONS.get(exc.errno, exc.strerror or str(exc))
            raise LinkError(f"{self.name}: cannot open {address[0]}:{address[1]}: "
                            f"{reason}") from None
        self._stamped = False
        if sys.platform.startswith("linux"):
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
                self._stamped = True
        self._sock = sock
        asyncio.get_running_loop().add_reader(sock.fileno(), self._readable)

    async def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(sock.fileno())
            sock.close()

    def _readable(self) -> None:
        sock = self._sock
        if sock is None:
            return
        gate = self.gate
        stamped = self._stamped
        for _ in range(MAX_DATAGRAMS_PER_WAKEUP):
            try:
                if stamped:
                    data, ancillary, _, addr = sock.recvmsg(65536, _ANCILLARY)
                else:
                    data, addr = sock.recvfrom(65536)
                    ancillary = ()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # e.g. ICMP port unreachable reported on a udpout socket
                self.stats.send_errors += 1
                continue
            if gate is not None and not gate(data):
                self.stats.gate_refused += 1
                continue
            self.waited_s = 0.0
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and \
                        len(value) >= _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack_from(value)
                    waited = time.time() - (sec + nsec * 1e-9)
                    # (a clock stepped meanwhile says nothing about the wait)
                    self.waited_s = waited if 0.0 <= waited < 1.0 else 0.0
            self.last_addr = addr
            self._received(data, datagram=True, addr=addr)
            if self._sock is None:
                return

    def _heard(self, addr: tuple) -> None:
        """A peer spoke valid MAVLink: answer it from now on, if there is room."""
        peers = self._peers
        if addr in peers:
            peers[addr] = time.monotonic()
            return
        if self._target is not None:
            return  # udpout answers its fixed peer only
        now = time.monotonic()
        if len(peers) >= self.options.max_peers:
            stalest = min(peers, key=peers.__getitem__)
            if now - peers[stalest] < self.options.peer_timeout_s:
                self.stats.peers_refused += 1
                return
            del peers[stalest]
            self.stats.peers_expired += 1
        peers[addr] = now
        self._peers_valid_until = 0.0  # a new peer: include it right away

    def send_to(self, msg: MAVLinkMessage, sysid: int, compid: int,
                addr: tuple | None) -> None:
        target = addr if self._target is None else self._target
        if self._sock is None or target is None:
            self.stats.send_dropped += 1
            return
        data = self.codec.pack(msg, sysid, compid)
        if self.tap is not None:
            self.tap(data, False)
        self._sendto(data, target)

    def _sendto(self, data: bytes, addr: tuple) -> None:
        sock = self._sock
        if sock is None:
            return
        try:
            sock.sendto(data, addr)
        except BlockingIOError:
            self.stats.send_dropped += 1
        except OSError as exc:
            self._send_failed(exc, addr)

    def _write(self, data: bytes) -> None:
        targets = [self._target] if self._target is not None else self.peers()
        for addr in targets:
            self._sendto(data, addr)
