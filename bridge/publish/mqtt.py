"""MQTT publishing that can never hold up the MAVLink path.

Producers call :meth:`MqttPublisher.publish`, which only appends to a bounded queue
(dropping — and counting — the oldest entry when full) and returns. One task drains the
queue to the broker, serialising JSON there, and reconnects with exponential backoff
when the broker is slow or gone. Uses aiomqtt 2.x.

A broker that cannot be reached is a WARNING at the first failed attempt and again at
most every :data:`WARN_EVERY_S` while it lasts (the operator must hear of it; the log
must not fill with it). Retained messages (:meth:`MqttPublisher.set_retained`, e.g. a
vehicle's ``online`` state) are sent again after every reconnect, because a last will
may have replaced them while the connection was down.
"""

from __future__ import annotations

import asyncio
import json
import logging
import ssl
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, NamedTuple
from urllib.parse import unquote, urlparse

import aiomqtt

log = logging.getLogger(__name__)

BACKOFF_START_S = 0.25
BACKOFF_MAX_S = 5.0
WARN_EVERY_S = 30.0  # an unreachable broker is reported again at most this often


class Outgoing(NamedTuple):
    topic: str
    payload: Any  # JSON-serialisable, or a str sent as it is
    retain: bool = False
    qos: int = 0


@dataclass(frozen=True)
class MqttSettings:
    """Broker address, credentials and TLS (``mqtts://`` or ``tls=True`` enables TLS)."""

    host: str
    port: int = 1883
    username: str | None = None
    password: str | None = None
    tls: bool = False
    ca_file: str | None = None  # CA bundle to trust (default: the system's)
    cert_file: str | None = None  # client certificate for mutual TLS
    key_file: str | None = None
    insecure: bool = False  # skip hostname verification (testing only)
    client_id: str | None = None
    topic_prefix: str = "attitude"
    queue_size: int = 1000

    @classmethod
    def from_url(cls, url: str, **overrides: Any) -> MqttSettings:
        """``mqtt://[user:pass@]host[:port]`` or ``mqtts://...`` (TLS, default port 8883)."""
        parsed = urlparse(url)
        if parsed.scheme not in ("mqtt", "mqtts") or not parsed.hostname:
            raise ValueError(f"bad MQTT URL {url!r}; use mqtt://host:port or mqtts://host:port")
        tls = parsed.scheme == "mqtts"
        settings: dict[str, Any] = {
            "host": parsed.hostname, "port": parsed.port or (8883 if tls else 1883), "tls": tls,
            "username": unquote(parsed.username) if parsed.username else None,
            "password": unquote(parsed.password) if parsed.password else None,
        }
        settings.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**settings)

    def tls_context(self) -> ssl.SSLContext | None:
        if not self.tls:
            return None
        ctx = ssl.create_default_context(cafile=self.ca_file)
        if self.cert_file:
            ctx.load_cert_chain(self.cert_file, self.key_file)
        if self.insecure:
            ctx.check_hostname = False
            ctx.verify_mode = ssl.CERT_NONE
        return ctx


@dataclass
class MqttStats:
    queued: int = 0
    published: int = 0
    dropped: int = 0  # oldest entries discarded because the queue was full
    connects: int = 0
    errors: int = 0
    connected: bool = False
    last_error: str = ""  # why the last connection attempt failed or ended
    stopped: bool = False  # closed by us (the summary then says what it was, not "down")


class MqttPublisher:
    """Bounded, drop-oldest queue in front of a self-reconnecting aiomqtt client.

    ``will``: published by the broker if this client vanishes without saying goodbye
    (process killed, network gone). ``quiet``: connection trouble at DEBUG only (a
    helper connection whose main one already reports it).
    """

    def __init__(self, settings: MqttSettings, will: Outgoing | None = None,
                 quiet: bool = False) -> None:
        self.settings = settings
        self.stats = MqttStats()
        self.will = will
        self.quiet = quiet
        self._queue: deque[Outgoing] = deque(maxlen=settings.queue_size)
        self._retained: dict[str, Outgoing] = {}
        self._wake = asyncio.Event()
        self._idle = asyncio.Event()  # set while connected with nothing left to send
        # aiomqtt logs every connection failure at WARNING on the "mqtt" logger; we
        # report them ourselves (rate-limited), so keep its logger to errors only.
        self._client_log = logging.getLogger("mqtt")
        self._client_log.setLevel(logging.ERROR)

    def topic(self, *parts: object) -> str:
        return "/".join([self.settings.topic_prefix, *map(str, parts)])

    def publish(self, topic: str, payload: Any, retain: bool = False, qos: int = 0) -> None:
        """Queue a payload (JSON-serialisable, or a str sent as is); never waits, drops
        the oldest if full."""
        if len(self._queue) == self._queue.maxlen:
            self.stats.dropped += 1
        self._queue.append(Outgoing(topic, payload, retain, qos))
        self.stats.queued += 1
        self._idle.clear()
        self._wake.set()

    def set_retained(self, topic: str, payload: Any) -> None:
        """Publish a retained state now and again after every reconnect."""
        item = Outgoing(topic, payload, True, 1)
        if self._retained.get(topic) == item:
            return
        self._retained[topic] = item
        self.publish(*item)

    async def flush(self, timeout: float) -> bool:
        """Wait until everything queued is sent (True) or ``timeout`` passes (False)."""
        if not self.stats.connected:
            return not self._queue
        try:
            await asyncio.wait_for(self._idle.wait(), timeout)
        except TimeoutError:
            return False
        return True

    async def run(self) -> None:
        """Connect, drain, reconnect forever (until cancelled)."""
        s = self.settings
        backoff = BACKOFF_START_S
        was_connected = False
        failures = 0
        warned = -WARN_EVERY_S
        will = None
        if self.will is not None:
            will = aiomqtt.Will(self.will.topic, _encode(self.will.payload),
                                qos=self.will.qos, retain=self.will.retain)
        while True:
            try:
                async with aiomqtt.Client(
                        s.host, s.port, username=s.username, password=s.password,
                        identifier=s.client_id, tls_context=s.tls_context(), will=will,
                        logger=self._client_log, timeout=3.0, keepalive=5) as client:
                    self.stats.connects += 1
                    self.stats.connected = True
                    if failures and not self.quiet:
                        log.warning("MQTT broker %s:%d reached after %d failed attempt(s)",
                                    s.host, s.port, failures)
                    else:
                        log.info("MQTT connected to %s:%d", s.host, s.port)
                    backoff = BACKOFF_START_S
                    was_connected = True
                    failures = 0
                    for item in self._retained.values():
                        await client.publish(item.topic, _encode(item.payload), qos=item.qos,
                                             retain=True, timeout=2.0)
                    await self._drain(client)
            except asyncio.CancelledError:
                self.stats.connected = False
                raise
            except (aiomqtt.MqttError, OSError, ssl.SSLError) as exc:
                self.stats.errors += 1
                self.stats.last_error = str(exc) or type(exc).__name__
                level = logging.DEBUG if self.quiet else logging.WARNING
                if was_connected:
                    log.log(level, "MQTT connection to %s:%d lost (%s); reconnecting",
                            s.host, s.port, self.stats.last_error)
                    was_connected = False
                    warned = time.monotonic()
                else:
                    failures += 1
                    now = time.monotonic()
                    if now - warned >= WARN_EVERY_S:
                        warned = now
                        log.log(level, "MQTT broker %s:%d unreachable (%s), attempt %d; "
                                "retrying every %g s at most, messages queued (the oldest "
                                "dropped beyond %d)", s.host, s.port, self.stats.last_error,
                                failures, BACKOFF_MAX_S, s.queue_size)
                    else:
                        log.debug("MQTT connect failed (%s); retry in %.2f s",
                                  self.stats.last_error, backoff)
            self.stats.connected = False
            self._idle.clear()
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, BACKOFF_MAX_S)

    async def _drain(self, client: aiomqtt.Client) -> None:
        while True:
            while self._queue:
                item = self._queue[0]
                try:
                    data = _encode(item.payload)
                except (TypeError, ValueError) as exc:  # a producer bug, not a link fault
                    log.error("MQTT payload for %s not serialisable: %s", item.topic, exc)
                    self.stats.errors += 1
                    self._queue.popleft()
                    continue
                await client.publish(item.topic, data, qos=item.qos, retain=item.retain,
                                     timeout=2.0)
                # Only now is it gone: a failed publish is retried after reconnecting.
                # (If the queue overflowed meanwhile, `item` was already discarded.)
                if self._queue and self._queue[0] is item:
                    self._queue.popleft()
                self.stats.published += 1
            self._wake.clear()
            self._idle.set()
            await self._wake.wait()


def _encode(payload: Any) -> str:
    """A str as it is, anything else as compact JSON (NaN refused: callers send null)."""
    if isinstance(payload, str):
        return payload
    return json.dumps(payload, separators=(",", ":"), allow_nan=False, default=_jsonable)


def _jsonable(value: Any) -> Any:
    """numpy scalars/arrays -> Python; NaN is not valid JSON, so callers send null."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
