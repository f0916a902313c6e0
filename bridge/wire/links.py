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

from .codec import SigningConfig
from .link import (
    Link,
    LinkError,
    LinkOptions,
    LinkStats,
    LinkUrl,
    MessageHandler,
    parse_url,
)
from .stream import SerialLink, TcpLink
from .udp import UdpLink

__all__ = ["Link", "LinkError", "LinkOptions", "LinkStats", "LinkUrl", "SerialLink",
           "TcpLink", "UdpLink", "open_link", "parse_url"]


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
