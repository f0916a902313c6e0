"""Byte-stream links: TCP client and serial port, reconnecting by themselves.

They reconnect with exponential backoff, reset after a session that delivered messages,
and give up on a connection that delivers no valid message for ``idle_timeout_s`` (a
peer that went silent, or stopped reading and let our output back up). A peer that
refuses (an autopilot still booting) is retried; each reason is logged once at WARNING,
its repeats at DEBUG. Output that cannot be written at once queues up to
``MAX_WRITE_BUFFER`` bytes, then new messages are dropped and counted: queued attitudes
only grow stale.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time

from .codec import SigningConfig
from .link import (
    BACKOFF_MAX_S,
    BACKOFF_START_S,
    MAX_WRITE_BUFFER,
    Link,
    LinkError,
    LinkOptions,
    LinkUrl,
    MessageHandler,
)

log = logging.getLogger(__name__)


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


def _is_terminal(device: str) -> bool:
    """Whether ``device`` is a terminal (a serial port is one; /dev/zero, /dev/null and
    files are not, and pyserial would fail on them for ever with 'Inappropriate ioctl').
    Opened without becoming the controlling terminal and without waiting for carrier;
    a device that cannot be opened now (busy, no permission) is left to the retries."""
    try:
        fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError:
        return True
    try:
        return os.isatty(fd)
    finally:
        os.close(fd)


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
        if "/" in device and not _is_terminal(device):
            raise LinkError(f"{self.name}: {device!r} is not a serial device (not a "
                            f"terminal: a file, /dev/null or the like)")

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
