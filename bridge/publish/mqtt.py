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
import socket
import ssl
import threading
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
#: Longest topic prefix [UTF-8 bytes]. MQTT allows 65535 for a whole topic, but some
#: brokers allow far less (AWS IoT Core: 256 bytes); /<sysid>/<estimator> comes on top.
MAX_PREFIX_BYTES = 200
#: How long the start waits for the broker's name to resolve; a resolver that takes
#: longer is not a typo, the connection attempts then tell.
RESOLVE_TIMEOUT_S = 3.0
URL_USAGE = "use mqtt://host:port or mqtts://host:port (TLS)"


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
        """``mqtt://[user:pass@]host[:port]`` or ``mqtts://...`` (TLS, default port 8883).

        ValueError (the URL shown without its password) for anything that would
        otherwise be replaced or ignored in silence: port 0 (urllib reads it as "no
        port", i.e. 1883), a port out of range, a path or query (the topic prefix is the
        ``mqtt-prefix`` setting, not part of the URL).
        """
        shown = redacted(url)
        try:
            parsed = urlparse(url)
            port = parsed.port
        except ValueError as exc:  # "Port out of range 0-65535", not a number, bad [IPv6]
            what = "the port must be a number in 1..65535" if "Port" in str(exc) else exc
            raise ValueError(f"bad MQTT URL {shown!r}: {what}; {URL_USAGE}") from None
        if parsed.scheme not in ("mqtt", "mqtts") or not parsed.hostname:
            raise ValueError(f"bad MQTT URL {shown!r}; {URL_USAGE}")
        if port == 0:
            raise ValueError(f"bad MQTT URL {shown!r}: port 0 (it would become 1883); the "
                             "port must be in 1..65535")
        if parsed.path not in ("", "/") or parsed.params or parsed.query or parsed.fragment:
            raise ValueError(f"bad MQTT URL {shown!r}: a path or query is not used (the "
                             f"topics' prefix is the mqtt-prefix setting); {URL_USAGE}")
        tls = parsed.scheme == "mqtts"
        settings: dict[str, Any] = {
            "host": parsed.hostname, "port": port or (8883 if tls else 1883), "tls": tls,
            "username": unquote(parsed.username) if parsed.username else None,
            "password": unquote(parsed.password) if parsed.password else None,
        }
        settings.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**settings)

    def tls_context(self) -> ssl.SSLContext | None:
        """The TLS context, or None without TLS. An encrypted key raises
        :class:`EncryptedKeyError` rather than letting OpenSSL prompt on the terminal
        (a service has none, and the prompt would block the event loop)."""
        if not self.tls:
            return None
        ctx = ssl.create_default_context(cafile=self.ca_file)
        if self.cert_file:
            ctx.load_cert_chain(self.cert_file, self.key_file, password=_no_passphrase)
        if self.insecure:
            ctx.check_hostname = False
            ctx.verify_mode = ssl.CERT_NONE
        return ctx


class EncryptedKeyError(ValueError):
    """The client key needs a passphrase, which the bridge has no way to ask for."""


def _no_passphrase() -> str:
    raise EncryptedKeyError("the private key is encrypted; give an unencrypted key "
                            "(readable by the bridge's user only)")


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
            except (aiomqtt.MqttError, OSError, ssl.SSLError, EncryptedKeyError) as exc:
                # (a key file replaced by an encrypted one since the start: reported and
                # retried like a missing one, not the end of the task)
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
                try:
                    await client.publish(item.topic, data, qos=item.qos, retain=item.retain,
                                         timeout=2.0)
                except ValueError as exc:  # paho refuses the topic (a wildcard, empty)
                    # A bug, not a link fault: unhandled, it would end this task and
                    # with it every later message, in silence.
                    log.error("MQTT topic %r refused by the client: %s", item.topic, exc)
                    self.stats.errors += 1
                    if self._queue and self._queue[0] is item:
                        self._queue.popleft()
                    continue
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


def redacted(url: str) -> str:
    """``url`` with its password replaced by ``***``: error messages and logs are read
    by more people than the settings file."""
    try:
        parsed = urlparse(url)
        if parsed.password is None:
            return url
    except ValueError:
        return url.split("@")[-1] if "@" in url else url
    user = parsed.netloc.rpartition("@")[0].partition(":")[0]
    return parsed._replace(netloc=f"{user}:***@{parsed.netloc.rpartition('@')[2]}").geturl()


def check_topic_prefix(prefix: str) -> None:
    """ValueError unless ``prefix`` can start every topic the bridge publishes.

    A topic the broker or client refuses is not a run-time fault to retry: every
    message would be lost (the '#' prefix published nothing and said nothing). Empty
    levels are legal MQTT but a typo in practice (``attitude/`` gives
    ``attitude//1/eskf``, which a subscriber to ``attitude/1/#`` never sees).
    """
    what = f"mqtt-prefix {prefix!r}"
    if not prefix:
        raise ValueError(f"{what}: empty (topics would start with '/'); e.g. 'attitude'")
    for wildcard in ("#", "+"):
        if wildcard in prefix:
            raise ValueError(f"{what}: the MQTT wildcard {wildcard!r} cannot be part of a "
                             "topic one publishes to (brokers and clients refuse it)")
    if "\0" in prefix:
        raise ValueError(f"{what}: NUL is not allowed in an MQTT topic")
    if any(ord(c) < 0x20 or 0x7F <= ord(c) <= 0x9F for c in prefix):
        raise ValueError(f"{what}: control characters do not belong in an MQTT topic")
    if prefix.startswith("$"):
        raise ValueError(f"{what}: topics starting with '$' are the broker's ($SYS); "
                         "clients may not publish there")
    if "" in prefix.split("/"):
        raise ValueError(f"{what}: an empty level (a leading, trailing or doubled '/'); "
                         "e.g. 'fleet/attitude'")
    try:
        size = len(prefix.encode("utf-8"))
    except UnicodeEncodeError:
        raise ValueError(f"{what}: not valid UTF-8 text") from None
    if size > MAX_PREFIX_BYTES:
        raise ValueError(f"{what[:40]}...': {size} bytes long, at most {MAX_PREFIX_BYTES} "
                         "bytes (some brokers limit a whole topic to 256)")


def check_mqtt_settings(cfg: Any) -> None:
    """ValueError naming the bad MQTT setting of a BridgeConfig, before anything starts.

    Everything the publisher would otherwise meet only when connecting — and then
    retry forever with a WARNING, or ignore — is a fault of the input: the URL, the
    broker's name, the TLS files, the topic prefix. Refused too: TLS files without TLS,
    which would connect in plaintext and send the credentials unencrypted (refused
    rather than taken to mean TLS: the user asked for two different things, and only
    they know which one is meant).
    """
    check_topic_prefix(cfg.mqtt_prefix)
    if cfg.mqtt is None:
        return
    if not cfg.mqtt.strip():
        raise ValueError(f"--mqtt {cfg.mqtt!r}: an empty URL (an unset variable?); "
                         f"{URL_USAGE}, or no --mqtt for no MQTT")
    try:
        settings = MqttSettings.from_url(
            cfg.mqtt, username=cfg.mqtt_username, password=cfg.mqtt_password,
            tls=cfg.mqtt_tls or None, ca_file=cfg.mqtt_ca, cert_file=cfg.mqtt_cert,
            key_file=cfg.mqtt_key)
    except ValueError as exc:
        raise ValueError(f"--mqtt: {exc}") from None
    files = [(option, path) for option, path in _tls_files(cfg) if path is not None]
    if files and not settings.tls:
        option, path = files[0]
        raise ValueError(f"{option} {path} given but --mqtt {redacted(cfg.mqtt)} is plaintext "
                         "(credentials would go unencrypted): use mqtts:// or add --mqtt-tls")
    if settings.tls:
        _check_tls_files(cfg.mqtt_ca, cfg.mqtt_cert, cfg.mqtt_key)
    _check_resolves(settings.host, settings.port, redacted(cfg.mqtt))


def orphan_options(cfg: Any) -> list[str]:
    """MQTT credentials and TLS options given without ``--mqtt``: they do nothing, and
    the user who gave them probably expects MQTT (a forgotten or unset ``--mqtt``). Told
    as a warning, not refused: an environment file with the broker's credentials is
    often kept while MQTT is switched off. The rate and prefix have defaults and are
    not looked at."""
    if cfg.mqtt is not None:
        return []
    return [option for option, value in (
        ("--mqtt-username", cfg.mqtt_username), ("--mqtt-password", cfg.mqtt_password),
        ("--mqtt-tls", cfg.mqtt_tls or None), *_tls_files(cfg)) if value is not None]


def _tls_files(cfg: Any) -> tuple[tuple[str, str | None], ...]:
    """(option, path) of the CA, client certificate and key settings."""
    return (("--mqtt-ca", cfg.mqtt_ca), ("--mqtt-cert", cfg.mqtt_cert),
            ("--mqtt-key", cfg.mqtt_key))


def _check_tls_files(ca: str | None, cert: str | None, key: str | None) -> None:
    """ValueError naming the CA, certificate or key file that does not load."""
    if key is not None and cert is None:
        raise ValueError(f"--mqtt-key {key} given without --mqtt-cert: a client key is "
                         "only used with its certificate")
    for option, path in (("--mqtt-ca", ca), ("--mqtt-cert", cert), ("--mqtt-key", key)):
        if path is None:
            continue
        if not path.strip():
            raise ValueError(f"{option} {path!r}: an empty file name (an unset variable?)")
        try:
            with open(path, "rb") as f:
                f.read(1)
        except OSError as exc:
            raise ValueError(f"{option} {path}: cannot read it ({exc.strerror or exc})"
                             ) from None
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    if ca is not None:
        try:
            ctx.load_verify_locations(cafile=ca)
        except (OSError, ValueError) as exc:  # ssl.SSLError is an OSError
            raise ValueError(f"--mqtt-ca {ca}: not a PEM CA bundle ({_ssl_reason(exc)})"
                             ) from None
    if cert is None:
        return
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_verify_locations(cafile=cert)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--mqtt-cert {cert}: no PEM certificate in it "
                         f"({_ssl_reason(exc)})") from None
    key_option = f"--mqtt-key {key}" if key is not None else f"--mqtt-cert {cert}"
    try:
        ctx.load_cert_chain(cert, key, password=_no_passphrase)
    except EncryptedKeyError as exc:
        raise ValueError(f"{key_option}: {exc}") from None
    except (OSError, ValueError) as exc:
        if "KEY_VALUES_MISMATCH" in str(exc):
            raise ValueError(f"{key_option}: not the private key of --mqtt-cert {cert}"
                             ) from None
        if key is None:
            raise ValueError(f"--mqtt-cert {cert}: no private key in it; give it with "
                             f"--mqtt-key ({_ssl_reason(exc)})") from None
        raise ValueError(f"--mqtt-key {key}: no PEM private key in it "
                         f"({_ssl_reason(exc)})") from None


def _ssl_reason(exc: Exception) -> str:
    """OpenSSL's reason without the ``(_ssl.c:NNNN)`` tail, on one line."""
    text = getattr(exc, "strerror", None) if isinstance(exc, OSError) and \
        not isinstance(exc, ssl.SSLError) else None
    text = text or str(exc)
    return " ".join(text.split(" (_ssl.c:")[0].split())


def _check_resolves(host: str, port: int, shown: str) -> None:
    """ValueError if the broker's name does not resolve: at start that is a typo (a
    broker that was reachable and then is not keeps being retried). A temporary
    failure (EAI_AGAIN: no network yet, at boot) or a resolver slower than
    :data:`RESOLVE_TIMEOUT_S` is no proof of a typo: the start goes on, and the
    connection attempts report it."""
    outcome: list[BaseException | None] = []

    def resolve() -> None:
        try:
            socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
            outcome.append(None)
        except OSError as exc:
            outcome.append(exc)

    # A daemon thread: getaddrinfo cannot be interrupted, and a hung one must not keep
    # the process from exiting.
    worker = threading.Thread(target=resolve, name="mqtt-resolve", daemon=True)
    worker.start()
    worker.join(RESOLVE_TIMEOUT_S)
    if not outcome or outcome[0] is None:
        return
    exc = outcome[0]
    if isinstance(exc, socket.gaierror) and exc.errno == socket.EAI_AGAIN:
        return
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    raise ValueError(f"--mqtt {shown}: cannot resolve host {host!r} ({reason})")
