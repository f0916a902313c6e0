"""asyncio MAVLink links: UDP in/out, TCP client, serial — bytes only, never blocking.

Every link parses what it receives with its own :class:`MavCodec` and hands each valid
message to ``on_message(msg, link)``; ``send(msg, sysid, compid)`` packs and writes
without waiting (a slow or absent peer costs a counted drop, never a stalled loop).
TCP and serial links reconnect by themselves with exponential backoff.

URLs follow pymavlink: ``udpin:HOST:PORT`` (listen; reply to whoever sent to us),
``udpout:HOST:PORT`` (send to a fixed peer; ``udp:`` is an alias of ``udpin:``),
``tcp:HOST:PORT`` (client), and serial as ``serial:/dev/ttyUSB0:921600`` or just
``/dev/ttyUSB0[:BAUD]`` / ``COM3[:BAUD]``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

from .codec import MavCodec, SigningConfig
from .mav import MAVLinkMessage

log = logging.getLogger(__name__)

#: A UDP peer that has sent nothing for this long no longer receives our output.
PEER_TIMEOUT_S = 10.0
PEER_REFRESH_S = 0.5
#: Outgoing bytes allowed to queue on a stream link before new messages are dropped.
MAX_WRITE_BUFFER = 256 * 1024
BACKOFF_START_S = 0.25
UDP_RECEIVE_BUFFER = 4 * 1024 * 1024
MAX_DATAGRAMS_PER_WAKEUP = 512  # then let other callbacks run
BACKOFF_MAX_S = 5.0

MessageHandler = Callable[[MAVLinkMessage, "Link"], None]


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


class Link:
    """Base class: codec, stats, and the message callback; subclasses move bytes."""

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None) -> None:
        self.url = url
        self.on_message = on_message
        self.signing = signing
        self.codec = MavCodec(signing)
        self.stats = LinkStats()
        self.last_receive = 0.0  # time.monotonic() of the last valid message

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
        self._write(self.codec.pack(msg, sysid, compid))

    def send_many(self, msgs: tuple[MAVLinkMessage, ...], sysid: int, compid: int) -> None:
        """Several messages in one write (one UDP datagram: fewer system calls)."""
        if not self.connected:
            self.stats.send_dropped += len(msgs)
            return
        self._write(b"".join(self.codec.pack(m, sysid, compid) for m in msgs))

    def _write(self, data: bytes) -> None:
        raise NotImplementedError

    def _received(self, data: bytes, codec: MavCodec | None = None,
                  datagram: bool = False) -> None:
        msgs = (codec or self.codec).parse(data, datagram)
        if not msgs:
            return
        self.last_receive = time.monotonic()
        if self.on_message is None:
            return
        for msg in msgs:
            try:
                self.on_message(msg, self)
            except Exception:  # one bad message must not kill the link
                log.exception("%s: handling %s failed", self.name, msg.get_type())


class UdpLink(Link):
    """``udpin`` listens and answers every peer heard from in the last PEER_TIMEOUT_S;
    ``udpout`` sends to one fixed address and also reads its replies.

    A plain non-blocking socket read through ``add_reader``: each readiness event drains
    every queued datagram (asyncio's datagram transport reads one per loop iteration,
    which lets a fast sender overflow the socket buffer).
    """

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None) -> None:
        super().__init__(url, on_message, signing)
        self._sock: socket.socket | None = None
        # Per-peer parsers: a corrupt datagram's leftovers must not merge with another
        # peer's next packet. The send side keeps the link codec's packers.
        self._peers: dict[tuple, tuple[MavCodec, float]] = {}
        self._target: tuple | None = None
        self._peer_list: list[tuple] = []
        self._peers_valid_until = 0.0

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
        on the per-sample output path)."""
        now = time.monotonic()
        if now >= self._peers_valid_until:
            self._peer_list = [a for a, (_, seen) in self._peers.items()
                               if now - seen < PEER_TIMEOUT_S]
            self._peers_valid_until = now + PEER_REFRESH_S
        return self._peer_list

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        infos = await loop.getaddrinfo(self.url.host, self.url.port, family=socket.AF_INET,
                                       type=socket.SOCK_DGRAM)
        address = infos[0][4][:2]
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        with contextlib.suppress(OSError):  # absorb bursts (e.g. a GC pause at 8 kHz)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
        if self.url.kind == "udpin":
            sock.bind(address)
        else:
            sock.bind(("0.0.0.0", 0))
            self._target = address
        self._sock = sock
        loop.add_reader(sock.fileno(), self._readable)

    async def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(sock.fileno())
            sock.close()

    def _readable(self) -> None:
        for _ in range(MAX_DATAGRAMS_PER_WAKEUP):
            sock = self._sock
            if sock is None:
                return
            try:
                data, addr = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # e.g. ICMP port unreachable reported on a udpout socket
                self.stats.send_errors += 1
                continue
            self._datagram(data, addr)

    def _datagram(self, data: bytes, addr: tuple) -> None:
        entry = self._peers.get(addr)
        if entry is None:
            self._peers_valid_until = 0.0  # a new peer: include it right away
            codec = MavCodec(self.signing)
            codec.stats = self.codec.stats  # one set of counters per link
        else:
            codec = entry[0]
        self._peers[addr] = (codec, time.monotonic())
        self._received(data, codec, datagram=True)

    def _write(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            return
        targets = [self._target] if self._target is not None else self.peers()
        for addr in targets:
            try:
                sock.sendto(data, addr)
            except BlockingIOError:
                self.stats.send_dropped += 1
            except OSError:
                self.stats.send_errors += 1


class _StreamLink(Link):
    """Shared reconnect-with-backoff loop of byte-stream links (TCP, serial)."""

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None) -> None:
        super().__init__(url, on_message, signing)
        self._task: asyncio.Task | None = None
        self._closing = False

    async def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name=f"link {self.name}")

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
            try:
                await self._session()
                backoff = BACKOFF_START_S  # it was up: retry promptly
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                log.warning("%s: %s; retrying in %.1f s", self.name, exc, backoff)
            self._disconnect()
            if self._closing:
                break
            self.stats.reconnects += 1
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, BACKOFF_MAX_S)

    async def _session(self) -> None:
        """Connect, then read until the connection ends."""
        raise NotImplementedError

    def _disconnect(self) -> None:
        raise NotImplementedError


class TcpLink(_StreamLink):
    """TCP client (e.g. SITL on tcp:127.0.0.1:5760)."""

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None) -> None:
        super().__init__(url, on_message, signing)
        self._writer: asyncio.StreamWriter | None = None

    @property
    def connected(self) -> bool:
        return self._writer is not None and not self._writer.is_closing()

    async def _session(self) -> None:
        reader, self._writer = await asyncio.open_connection(self.url.host, self.url.port)
        log.info("%s: connected", self.name)
        self.codec.reset_parser()  # drop a partial frame left by the old connection
        while True:
            data = await reader.read(65536)
            if not data:
                raise ConnectionError("connection closed by peer")
            self._received(data)

    def _disconnect(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _write(self, data: bytes) -> None:
        writer = self._writer
        if writer is None:
            return
        if writer.transport.get_write_buffer_size() > MAX_WRITE_BUFFER:
            self.stats.send_dropped += 1
            return
        writer.write(data)


class SerialLink(_StreamLink):
    """A serial port via pyserial in non-blocking mode, read through ``add_reader``."""

    def __init__(self, url: LinkUrl, on_message: MessageHandler | None = None,
                 signing: SigningConfig | None = None) -> None:
        super().__init__(url, on_message, signing)
        self._port = None
        self._lost: asyncio.Future | None = None
        self._pending = bytearray()  # output the port could not take yet

    @property
    def connected(self) -> bool:
        return self._port is not None

    async def _session(self) -> None:
        import serial  # pyserial; imported here so UDP-only use does not need it

        loop = asyncio.get_running_loop()
        port = serial.Serial(self.url.device, self.url.baud, timeout=0, write_timeout=0)
        self._port = port
        self._lost = loop.create_future()
        loop.add_reader(port.fileno(), self._readable)
        log.info("%s: open", self.name)
        await self._lost

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
              signing: SigningConfig | None = None) -> Link:
    """A not-yet-started link for ``url``."""
    parsed = parse_url(url) if isinstance(url, str) else url
    if parsed.kind in ("udpin", "udpout"):
        return UdpLink(parsed, on_message, signing)
    if parsed.kind == "tcp":
        return TcpLink(parsed, on_message, signing)
    return SerialLink(parsed, on_message, signing)
