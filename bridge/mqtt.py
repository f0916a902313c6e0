"""MQTT publishing that can never hold up the MAVLink path.

Producers call :meth:`MqttPublisher.publish`, which only appends to a bounded queue
(dropping — and counting — the oldest entry when full) and returns. One task drains the
queue to the broker, serialising JSON there, and reconnects with exponential backoff
when the broker is slow or gone. Uses aiomqtt 2.x.
"""

from __future__ import annotations

import asyncio
import json
import logging
import ssl
from collections import deque
from dataclasses import dataclass
from typing import Any
from urllib.parse import unquote, urlparse

import aiomqtt

log = logging.getLogger(__name__)

BACKOFF_START_S = 0.25
BACKOFF_MAX_S = 5.0


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


class MqttPublisher:
    """Bounded, drop-oldest queue in front of a self-reconnecting aiomqtt client."""

    def __init__(self, settings: MqttSettings) -> None:
        self.settings = settings
        self.stats = MqttStats()
        self._queue: deque[tuple[str, Any]] = deque(maxlen=settings.queue_size)
        self._wake = asyncio.Event()
        # aiomqtt logs every connection failure at WARNING on the "mqtt" logger; we
        # log reconnects ourselves, once, so keep its logger to errors only.
        self._client_log = logging.getLogger("mqtt")
        self._client_log.setLevel(logging.ERROR)

    def topic(self, *parts: object) -> str:
        return "/".join([self.settings.topic_prefix, *map(str, parts)])

    def publish(self, topic: str, payload: Any) -> None:
        """Queue a JSON-serialisable payload; never waits, drops the oldest if full."""
        if len(self._queue) == self._queue.maxlen:
            self.stats.dropped += 1
        self._queue.append((topic, payload))
        self.stats.queued += 1
        self._wake.set()

    async def run(self) -> None:
        """Connect, drain, reconnect forever (until cancelled)."""
        s = self.settings
        backoff = BACKOFF_START_S
        was_connected = False
        while True:
            try:
                async with aiomqtt.Client(
                        s.host, s.port, username=s.username, password=s.password,
                        identifier=s.client_id, tls_context=s.tls_context(),
                        logger=self._client_log, timeout=3.0, keepalive=5) as client:
                    self.stats.connects += 1
                    self.stats.connected = True
                    log.info("MQTT connected to %s:%d", s.host, s.port)
                    backoff = BACKOFF_START_S
                    was_connected = True
                    await self._drain(client)
            except asyncio.CancelledError:
                self.stats.connected = False
                raise
            except (aiomqtt.MqttError, OSError, ssl.SSLError) as exc:
                self.stats.errors += 1
                if was_connected:
                    log.warning("MQTT connection lost (%s); reconnecting", exc)
                    was_connected = False
                else:
                    log.debug("MQTT connect failed (%s); retry in %.2f s", exc, backoff)
            self.stats.connected = False
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, BACKOFF_MAX_S)

    async def _drain(self, client: aiomqtt.Client) -> None:
        while True:
            while self._queue:
                item = self._queue[0]
                try:
                    data = json.dumps(item[1], separators=(",", ":"), allow_nan=False,
                                      default=_jsonable)
                except (TypeError, ValueError) as exc:  # a producer bug, not a link fault
                    log.error("MQTT payload for %s not serialisable: %s", item[0], exc)
                    self.stats.errors += 1
                    self._queue.popleft()
                    continue
                await client.publish(item[0], data, qos=0, timeout=2.0)
                # Only now is it gone: a failed publish is retried after reconnecting.
                # (If the queue overflowed meanwhile, `item` was already discarded.)
                if self._queue and self._queue[0] is item:
                    self._queue.popleft()
                self.stats.published += 1
            self._wake.clear()
            await self._wake.wait()


def _jsonable(value: Any) -> Any:
    """numpy scalars/arrays -> Python; NaN is not valid JSON, so callers send null."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
