"""asyncio MAVLink links: UDP in/out, TCP client, serial — bytes only, never blocking.

Every link parses what it receives with its own :class:`MavCodec` and hands each valid
message to ``on_message(msg, link)`` (``link.last_addr`` says who sent it);
``send(msg, sysid, compid)`` packs and writes without waiting (a slow or absent peer
costs a counted drop, never a stalled loop). TCP and serial links reconnect by
themselves with exponential backoff, reset after a session that delivered messages,
and give up on a connection that delivers no valid message for ``idle_timeout_s``
(a peer that went silent, or stopped reading and let our output back up). What no
retry can fix fails at start instead (:class:`LinkError`): a host name that does not
resolve, a serial device that does not exist. A peer that refuses (an autopilot still
booting) is retried; each reason is logged once at WARNING, its repeats at DEBUG.

A UDP ``udpin`` link answers only peers it has heard speak valid (and, with signing,
verified) MAVLink: one byte from a spoofed address earns nothing. The peer table is
bounded (``max_peers``, silent peers expire after ``peer_timeout_s``); refusals are
counted. An optional ``gate(data)`` sees each datagram before it is parsed, so that a
flood can be refused for the price of a header peek (see :mod:`bridge.wire.admission`).

URLs follow pymavlink: ``udpin:HOST:PORT`` (listen; reply to whoever sent to us),
``udpout:HOST:PORT`` (send to a fixed peer; ``udp:`` is an alias of ``udpin:``),
``tcp:HOST:PORT`` (client), and serial as ``serial:/dev/ttyUSB0:921600`` or just
``/dev/ttyUSB0[:BAUD]`` / ``COM3[:BAUD]``.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

from .codec import MavCodec, SigningConfig
from .kernelfilter import KernelFilter, Senders
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
#: Sees each UDP datagram before parsing; False refuses it (the gate counts why).
Gate = Callable[[bytes], bool]


class LinkError(OSError):
    """A link that cannot be opened at all (a host that does not resolve, a port in use,
    an address not on this machine, a serial device that does not exist): a setting to
    fix, reported as one line."""


#: What a failed bind means, in words a user can act on.
_BIND_REASONS = {
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
            return LinkUrl(kind=kind, host=host or "0.0.0.0", port=int(port))
    else:
        device = text[len("serial:"):] if text.startswith("serial:") else text
        if device.startswith("/dev/") or device.upper().startswith("COM") or \
                text.startswith("serial:"):
            name, sep, baud = device.rpartition(":")
            if sep and baud.isdigit():
                return LinkUrl(kind="serial", device=name, baud=int(baud))
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
        self.last_addr: tuple | None = None  # sender of the message being handled
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
            except Exception:  # one bad message must not kill the link
                log.exception("%s: handling %s failed", self.name, msg.get_type())

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
            log.warning("%s: flood of refused datagrams; kernel filter on", self.name)
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
            reason = _BIND_REASONS.get(exc.errno, exc.strerror or str(exc))
            raise LinkError(f"{self.name}: cannot open {address[0]}:{address[1]}: "
                            f"{reason}") from None
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
        recv = sock.recvfrom
        for _ in range(MAX_DATAGRAMS_PER_WAKEUP):
            try:
                data, addr = recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # e.g. ICMP port unreachable reported on a udpout socket
                self.stats.send_errors += 1
                continue
            if gate is not None and not gate(data):
                self.stats.gate_refused += 1
                continue
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
        except OSError:
            self.stats.send_errors += 1

    def _write(self, data: bytes) -> None:
        targets = [self._target] if self._target is not None else self.peers()
        for addr in targets:
            self._sendto(data, addr)


class _StreamLink(Link):
    """Shared reconnect-with-backoff loop of byte-stream links (TCP, serial).

    A session ends when the transport fails or when it has delivered no valid message
    for ``idle_timeout_s`` (the peer went silent mid-frame, or stopped reading so that
    our output backs up and nothing comes back either). The backoff starts over after
    a session that delivered messages.
    """

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None,
                 options: LinkOptions | None = None) -> None:
        super().__init__(url, on_message, signing, options)
        self._task: asyncio.Task | None = None
        self._closing = False
        self._session_start = 0.0
        self._last_warned: str | None = None  # failure already told at WARNING

    async def start(self) -> None:
        """Check what can be wrong for good (LinkError), then connect in the background:
        a peer that is not up yet is retried with backoff."""
        await self._check()
        self._task = asyncio.create_task(self._run(), name=f"link {self.name}")

    async def _check(self) -> None:
        """Raise LinkError for a setting that no retry can fix."""

    def _describe_failure(self, exc: Exception) -> str:
        """Why a connection attempt or session ended, in words a user can act on."""
        return str(exc) or type(exc).__name__

    def _report_failure(self, reason: str, backoff: float) -> None:
        """WARNING once per reason, DEBUG for its repeats until a session works again.

        An autopilot that is still booting refuses every attempt for a while: one line
        says so (and that we keep trying); a warning per attempt would bury the rest.
        """
        if reason == self._last_warned:
            log.debug("%s: %s; retrying in %g s", self.name, reason, backoff)
            return
        self._last_warned = reason
        log.warning("%s: %s; retrying in %g s, then with backoff up to %g s (repeats "
                    "are logged at DEBUG)", self.name, reason, backoff, BACKOFF_MAX_S)

    async def close(self) -> None:
        self._closing = True
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self._disconnect()

    async def _run(self) -> None:
        backoff = BACKOFF_START_S
        while not self._closing:
            self._session_start = time.monotonic()
            try:
                await self._session()
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                self._report_failure(self._describe_failure(exc), backoff)
            if self.last_receive > self._session_start:
                backoff = BACKOFF_START_S  # it worked: retry promptly
                self._last_warned = None  # and say so again if it fails again
            self._disconnect()
            if self._closing:
                break
            self.stats.reconnects += 1
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, BACKOFF_MAX_S)

    def _idle(self) -> bool:
        """No valid message for idle_timeout_s in this session."""
        since = max(self.last_receive, self._session_start)
        if time.monotonic() - since < self.options.idle_timeout_s:
            return False
        self.stats.idle_timeouts += 1
        return True

    @property
    def _watch_period(self) -> float:
        return max(0.05, self.options.idle_timeout_s / 4.0)

    async def _session(self) -> None:
        """Connect, then read until the connection ends or goes idle."""
        raise NotImplementedError

    def _disconnect(self) -> None:
        raise NotImplementedError


class TcpLink(_StreamLink):
    """TCP client (e.g. SITL on tcp:127.0.0.1:5760), with TCP keep-alive."""

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None,
                 options: LinkOptions | None = None) -> None:
        super().__init__(url, on_message, signing, options)
        self._writer: asyncio.StreamWriter | None = None
        self._blocked_since: float | None = None  # our output backed up since then

    @property
    def connected(self) -> bool:
        return self._writer is not None and not self._writer.is_closing()

    async def _check(self) -> None:
        await self._resolve(socket.AF_UNSPEC, socket.SOCK_STREAM)

    def _describe_failure(self, exc: Exception) -> str:
        peer = f"{self.url.host}:{self.url.port}"
        if isinstance(exc, ConnectionRefusedError):
            return f"connection refused by {peer}"
        if isinstance(exc, TimeoutError):
            return f"no answer from {peer}"
        return super()._describe_failure(exc)

    async def _session(self) -> None:
        reader, self._writer = await asyncio.wait_for(
            asyncio.open_connection(self.url.host, self.url.port),
            max(1.0, self.options.idle_timeout_s))
        sock = self._writer.get_extra_info("socket")
        _keepalive(sock, self.options.idle_timeout_s)
        with contextlib.suppress(OSError, AttributeError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, MAX_WRITE_BUFFER)
        log.info("%s: connected", self.name)
        self.codec.reset_parser()  # drop a partial frame left by the old connection
        while True:
            try:
                data = await asyncio.wait_for(reader.read(65536), self._watch_period)
            except TimeoutError:
                data = None
            if data is not None and not data:
                raise ConnectionError("connection closed by peer")
            if data:
                self._received(data)
            if self._idle():
                raise ConnectionError(
                    f"no valid message for {self.options.idle_timeout_s:g} s")
            blocked = self._blocked_since
            if blocked is not None and \
                    time.monotonic() - blocked >= self.options.idle_timeout_s:
                self.stats.write_stalls += 1
                raise ConnectionError(f"peer has not read our output for "
                                      f"{self.options.idle_timeout_s:g} s")

    def _disconnect(self) -> None:
        self._blocked_since = None
        if self._writer is not None:
            self._writer.transport.abort()  # a peer that stopped reading: do not wait
            self._writer = None

    def _write(self, data: bytes) -> None:
        writer = self._writer
        if writer is None:
            return
        if writer.transport.get_write_buffer_size() > MAX_WRITE_BUFFER:
            self.stats.send_dropped += 1
            if self._blocked_since is None:
                self._blocked_since = time.monotonic()
            return
        self._blocked_since = None
        writer.write(data)


def _keepalive(sock: socket.socket | None, idle_s: float) -> None:
    """Let the kernel probe a connection whose peer vanished without a FIN."""
    if sock is None:
        return
    with contextlib.suppress(OSError, AttributeError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        secs = max(1, int(idle_s))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE, secs)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL, secs)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, 3)


class SerialLink(_StreamLink):
    """A serial port via pyserial in non-blocking mode, read through ``add_reader``."""

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None,
                 options: LinkOptions | None = None) -> None:
        super().__init__(url, on_message, signing, options)
        self._port = None
        self._lost: asyncio.Future | None = None
        self._pending = bytearray()  # output the port could not take yet

    @property
    def connected(self) -> bool:
        return self._port is not None

    async def _check(self) -> None:
        """A device path that does not exist at start is a typo (a device unplugged
        later is retried). Names that are not paths (COM3) are left to the driver."""
        device = self.url.device
        if "/" in device and not os.path.exists(device):
            raise LinkError(f"{self.name}: no such serial device {device!r}")

    async def _session(self) -> None:
        import serial  # pyserial; imported here so UDP-only use does not need it

        loop = asyncio.get_running_loop()
        port = serial.Serial(self.url.device, self.url.baud, timeout=0, write_timeout=0)
        self._port = port
        self._lost = loop.create_future()
        loop.add_reader(port.fileno(), self._readable)
        log.info("%s: open", self.name)
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._lost), self._watch_period)
            if self._idle():
                raise ConnectionError(
                    f"no valid message for {self.options.idle_timeout_s:g} s")

    def _readable(self) -> None:
        port = self._port
        if port is None:
            return
        try:
            data = port.read(max(1, port.in_waiting))
        except Exception as exc:  # device unplugged
            self._fail(exc)
            return
        if data:
            self._received(data)

    def _fail(self, exc: Exception) -> None:
        if self._lost is not None and not self._lost.done():
            self._lost.set_exception(ConnectionError(f"serial port lost: {exc}"))

    def _disconnect(self) -> None:
        port, self._port = self._port, None
        self._pending.clear()
        if port is None:
            return
        with contextlib.suppress(Exception):
            asyncio.get_running_loop().remove_reader(port.fileno())
            asyncio.get_running_loop().remove_writer(port.fileno())
        with contextlib.suppress(Exception):
            port.close()

    def _write(self, data: bytes) -> None:
        """Write without blocking: what the port cannot take now waits in a bounded
        buffer flushed when the fd is writable; beyond that, messages are dropped.

        (os.write on the O_NONBLOCK fd, not pyserial's write: with write_timeout=0 that
        spins forever once the driver's buffer is full.)
        """
        port = self._port
        if port is None:
            return
        if self._pending:
            if len(self._pending) + len(data) > MAX_WRITE_BUFFER:
                self.stats.send_dropped += 1
            else:
                self._pending += data
            return
        try:
            written = os.write(port.fileno(), data)
        except BlockingIOError:
            written = 0
        except OSError as exc:
            self.stats.send_errors += 1
            self._fail(exc)
            return
        if written < len(data):
            self._pending += data[written:]
            asyncio.get_running_loop().add_writer(port.fileno(), self._flush)

    def _flush(self) -> None:
        port = self._port
        if port is None:
            return
        try:
            written = os.write(port.fileno(), self._pending)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(exc)
            return
        del self._pending[:written]
        if not self._pending:
            asyncio.get_running_loop().remove_writer(port.fileno())


def open_link(url: str | LinkUrl, on_message: MessageHandler | None = None,
              signing: SigningConfig | None = None,
              options: LinkOptions | None = None) -> Link:
    """A not-yet-started link for ``url``."""
    parsed = parse_url(url) if isinstance(url, str) else url
    if parsed.kind in ("udpin", "udpout"):
        return UdpLink(parsed, on_message, signing, options)
    if parsed.kind == "tcp":
        return TcpLink(parsed, on_message, signing, options)
    return SerialLink(parsed, on_message, signing, options)
