"""The link every transport shares: URL parsing, options, counters, parse-and-deliver.

A link parses what it receives with its own :class:`~bridge.wire.codec.MavCodec` and
hands each valid message to ``on_message(msg, link)``; ``send`` packs and writes without
waiting. The transports (:mod:`bridge.wire.udp`, :mod:`bridge.wire.stream`) only move
bytes; :mod:`bridge.wire.links` picks one for a URL.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

from .codec import MavCodec, SigningConfig
from .mav import MAVLinkMessage

log = logging.getLogger(__name__)

#: A UDP peer that has sent nothing for this long no longer receives our output.
PEER_TIMEOUT_S = 10.0
PEER_REFRESH_S = 0.5
MAX_PEERS = 32
#: A stream link that delivers no valid message for this long is reconnected.
IDLE_TIMEOUT_S = 5.0
#: Outgoing bytes allowed to queue on a stream link before new messages are dropped (and
#: the kernel's send buffer of a TCP link): queued attitudes only grow stale.
MAX_WRITE_BUFFER = 64 * 1024
BACKOFF_START_S = 0.25
UDP_RECEIVE_BUFFER = 4 * 1024 * 1024
MAX_DATAGRAMS_PER_WAKEUP = 512  # then let other callbacks run
BACKOFF_MAX_S = 5.0

MessageHandler = Callable[[MAVLinkMessage, "Link"], None]
#: Sees every frame read (True) or written (False), e.g. to record the session.
Tap = Callable[[bytes, bool], None]
#: Kinds of handler failure (message type, exception) whose traceback is logged; a
#: sender that makes new kinds without end cannot flood the log with them.
_FAILURE_KINDS_LOGGED = 20
#: Sees each UDP datagram before parsing; False refuses it (the gate counts why).
Gate = Callable[[bytes], bool]


class LinkError(OSError):
    """A link that cannot be opened at all (a host that does not resolve, a port in use,
    an address not on this machine, a serial device that does not exist): a setting to
    fix, reported as one line."""


#: What a failed bind means, in words a user can act on.
BIND_REASONS = {
    errno.EADDRINUSE: "address already in use (another program, or another bridge, is "
                      "listening on that port)",
    errno.EADDRNOTAVAIL: "that address is not on this machine (use 0.0.0.0 to listen on "
                         "all of its addresses)",
    errno.EACCES: "permission denied (ports below 1024 need privileges)",
}


@dataclass(frozen=True)
class LinkOptions:
    """Bounds and timeouts of a link (see the module docstring)."""

    max_peers: int = MAX_PEERS
    peer_timeout_s: float = PEER_TIMEOUT_S
    idle_timeout_s: float = IDLE_TIMEOUT_S


@dataclass(frozen=True)
class LinkUrl:
    """A parsed connection URL."""

    kind: str  # "udpin", "udpout", "tcp" or "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 57600

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind}:{self.host}:{self.port}"


#: Baud rates a serial port runs at (termios knows 50 to a few Mbaud; USB CDC takes any).
MIN_BAUD, MAX_BAUD = 50, 20_000_000


def parse_url(url: str) -> LinkUrl:
    """Parse a pymavlink-style URL; ValueError saying what is accepted otherwise."""
    text = url.strip()
    for prefix in ("udpin:", "udpout:", "udp:", "tcp:"):
        if text.startswith(prefix):
            rest = text[len(prefix):].lstrip("/")
            host, sep, port = rest.rpartition(":")
            kind = "udpin" if prefix == "udp:" else prefix[:-1]
            lowest = 0 if kind == "udpin" else 1  # udpin:HOST:0 picks a free port
            if not sep or not port.isdigit() or not lowest <= int(port) < 65536:
                break
            if host.startswith("[") and host.endswith("]"):  # an IPv6 literal, as in URLs
                host = host[1:-1]
                if kind != "tcp":
                    raise ValueError(f"bad connection URL {url!r}: UDP links are IPv4 only "
                                     f"(e.g. udpin:0.0.0.0:14550); tcp: takes IPv6")
            return LinkUrl(kind=kind, host=host or "0.0.0.0", port=int(port))
    else:
        device = text[len("serial:"):] if text.startswith("serial:") else text
        if device.startswith("/dev/") or device.upper().startswith("COM") or \
                text.startswith("serial:"):
            name, sep, baud = device.rpartition(":")
            if sep and baud.isdigit():
                if not MIN_BAUD <= int(baud) <= MAX_BAUD:
                    raise ValueError(f"serial {name}: baud rate {baud} is not one a port "
                                     f"runs at ({MIN_BAUD}..{MAX_BAUD})")
                return LinkUrl(kind="serial", device=name, baud=int(baud))
            if sep and name and os.path.exists(name):
                raise ValueError(f"serial {name}: bad baud rate {baud!r}; e.g. "
                                 f"{name}:921600")
            return LinkUrl(kind="serial", device=device)
    raise ValueError(f"bad connection URL {url!r}; use udpin:HOST:PORT, udpout:HOST:PORT, "
                     f"tcp:HOST:PORT or a serial device like /dev/ttyUSB0:921600")


@dataclass
class LinkStats:
    """Transport-level counters (the codec counts message-level problems)."""

    send_dropped: int = 0  # messages dropped because the peer was slow or absent
    send_errors: int = 0  # OS errors while sending (e.g. ICMP port unreachable)
    reconnects: int = 0
    idle_timeouts: int = 0  # stream connections given up for delivering nothing
    write_stalls: int = 0  # stream connections given up because the peer stopped reading
    gate_refused: int = 0  # datagrams refused before parsing (see the gate's counts)
    peers: int = 0  # UDP peers currently answered
    peers_refused: int = 0  # new peers not answered because the table was full
    peers_expired: int = 0  # peers dropped after peer_timeout_s of silence
    handler_failures: int = 0  # messages whose handling raised (a bug: logged, counted)


class Link:
    """Base class: codec, stats, and the message callback; subclasses move bytes."""

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None,
                 options: LinkOptions | None = None) -> None:
        self.url = url
        self.on_message = on_message
        self.signing = signing
        self.options = options or LinkOptions()
        self.codec = MavCodec(signing)
        self.stats = LinkStats()
        self.last_receive = 0.0  # time.monotonic() of the last valid message
        self._failure_kinds: dict[tuple[str, str], int] = {}  # (message, exception) -> n
        self._send_errnos: set[int] = set()  # kinds of send error already told
        self.last_addr: tuple | None = None  # sender of the message being handled
        #: How long the datagram being handled waited in the kernel before it was read
        #: (UDP, from its kernel receive time; 0 where there is none): what a busy event
        #: loop costs a sample, counted in its latency.
        self.waited_s = 0.0
        self.gate: Gate | None = None
        self.tap: Tap | None = None

    @property
    def name(self) -> str:
        return str(self.url)

    async def start(self) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    @property
    def connected(self) -> bool:
        raise NotImplementedError

    def send(self, msg: MAVLinkMessage, sysid: int, compid: int) -> None:
        """Pack and write ``msg`` as (sysid, compid); never waits."""
        if not self.connected:
            self.stats.send_dropped += 1
            return
        data = self.codec.pack(msg, sysid, compid)
        if self.tap is not None:
            self.tap(data, False)
        self._write(data)

    def send_many(self, msgs: tuple[MAVLinkMessage, ...], sysid: int, compid: int) -> None:
        """Several messages in one write (one UDP datagram: fewer system calls)."""
        if not self.connected:
            self.stats.send_dropped += len(msgs)
            return
        frames = [self.codec.pack(m, sysid, compid) for m in msgs]
        if self.tap is not None:
            for frame in frames:
                self.tap(frame, False)
        self._write(b"".join(frames))

    def _write(self, data: bytes) -> None:
        raise NotImplementedError

    def send_to(self, msg: MAVLinkMessage, sysid: int, compid: int,
                addr: tuple | None) -> None:
        """Like :meth:`send`, to one peer only where the transport has several."""
        self.send(msg, sysid, compid)

    def _received(self, data: bytes, datagram: bool = False,
                  addr: tuple | None = None) -> None:
        """Parse and deliver (a UDP sender of valid messages becomes a peer first, so
        that the output they cause reaches it too)."""
        msgs = self.codec.parse(data, datagram)
        if not msgs:
            return
        self.last_receive = time.monotonic()
        if addr is not None:
            self._heard(addr)
        if self.tap is not None:
            for msg in msgs:
                self.tap(msg.get_msgbuf(), True)
        if self.on_message is None:
            return
        for msg in msgs:
            try:
                self.on_message(msg, self)
            except Exception as exc:  # one bad message must not kill the link
                self._handler_failed(msg.get_type(), exc)

    def _send_failed(self, exc: OSError, addr: tuple | None = None) -> None:
        """Count a send the OS refused; say so once per kind of error (a broadcast
        address without permission, no route): an output that never leaves this machine
        must not look like one that works."""
        self.stats.send_errors += 1
        key = exc.errno or 0
        if key not in self._send_errnos:
            self._send_errnos.add(key)
            where = f" to {addr[0]}:{addr[1]}" if addr else ""
            log.warning("%s: cannot send%s: %s (counted as send_errors)", self.name, where,
                        exc.strerror or exc)

    def _handler_failed(self, msg_type: str, exc: Exception) -> None:
        """Count a message whose handling raised; the traceback once per kind of failure
        and then a counted warning now and then, so that a failure on every sample is
        a line a minute rather than a traceback per message."""
        self.stats.handler_failures += 1
        kind = (msg_type, type(exc).__name__)
        seen = self._failure_kinds.get(kind, 0) + 1
        self._failure_kinds[kind] = seen
        if seen == 1 and len(self._failure_kinds) <= _FAILURE_KINDS_LOGGED:
            log.error("%s: handling %s failed (a bug; later failures of this kind are "
                      "counted)", self.name, msg_type, exc_info=exc)
        elif seen in (10, 100) or seen % 10_000 == 0:
            log.warning("%s: handling %s has failed %d times (%s: %s)", self.name, msg_type,
                        seen, type(exc).__name__, exc)

    def _heard(self, addr: tuple) -> None:
        """A peer at ``addr`` spoke valid MAVLink (datagram links only)."""

    async def _resolve(self, family: int, kind: int) -> tuple[str, int]:
        """The URL's first address; LinkError when the host name does not resolve.

        A name that does not resolve at start is a typo, not a peer that is still
        booting: retrying would hide it forever.
        """
        try:
            infos = await asyncio.get_running_loop().getaddrinfo(
                self.url.host, self.url.port, family=family, type=kind)
        except OSError as exc:  # socket.gaierror
            raise LinkError(f"{self.name}: cannot resolve host {self.url.host!r} "
                            f"({exc.strerror or exc})") from None
        return infos[0][4][:2]
