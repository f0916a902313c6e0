"""The live web view: a page per bridge, fed snapshots over a WebSocket (``--web``).

Served by Tornado (the asyncio web server Bokeh is built on, already installed with the
report extra) on the bridge's own event loop; the page draws with BokehJS, served from
the installed ``bokeh`` package, so the view works with no internet (a companion
computer in a field has none). Why not a Bokeh server document per browser: its
per-session diffs run Python per browser per frame and queue without bound behind a
slow browser; here one JSON text per frame is made once and handed to every browser.

It never slows the MAVLink path:

* the view reads snapshots (:mod:`bridge.publish.snapshot`) taken by a timer at
  :data:`FRAME_HZ`, never anything per sample;
* each browser has at most one frame in flight: when its previous frame has not been
  written out yet (a slow browser or link), the new one is dropped and counted;
* memory is bounded: :data:`MAX_VIEWERS` browsers at most, the history a new browser
  gets is the last ``window_s`` of frames, incoming messages are ignored and limited
  in size.

Safe by default: binds 127.0.0.1 unless told otherwise, read-only (GET pages and a
WebSocket that only sends; no control of any kind), same-origin WebSockets only.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import json
import logging
import socket
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from importlib import resources
from typing import Any

import tornado.web
import tornado.websocket
from bokeh import __version__ as bokeh_version
from bokeh.util.paths import bokehjs_path
from tornado.httpserver import HTTPServer
from tornado.iostream import IOStream
from tornado.netutil import bind_sockets

from ..wire.link import BIND_REASONS

log = logging.getLogger(__name__)

#: Frames per second to every browser (the page updates at this rate).
FRAME_HZ = 10.0
#: Browsers served at once; more are refused (closed with a reason).
MAX_VIEWERS = 16
#: Seconds of frames a browser gets when it opens (its plots start full).
HISTORY_S = 30.0
#: The page sends nothing we act on; anything bigger than this closes its socket.
MAX_INCOMING_BYTES = 1024
#: Kernel send buffer of a viewer's connection: what a browser that stops reading can
#: hold of the bridge's memory, beside the one frame in flight (no autotuning to MBs).
VIEWER_SEND_BUFFER = 64 * 1024
#: Seconds a connection may take to send a request's headers, counted from when it
#: opens (or from the previous response, for a kept-alive one; Tornado's
#: ``idle_connection_timeout`` is this header timeout), and to send a body. A browser
#: sends its headers in one packet at once; 5 s leaves room for a couple of TCP
#: retransmissions on a lossy field Wi-Fi link (1 s + 2 s), yet a half-sent request
#: (slowloris: one byte, or a header line every few seconds) holds its socket and
#: memory no longer. An idle kept-alive connection is closed too: the browser reopens
#: it without a word. An opened WebSocket is no longer an HTTP request: not affected.
REQUEST_TIMEOUT_S = 5.0
#: HTTP connections (pages, scripts, WebSocket handshakes in progress) served at once;
#: more are closed at once. A browser opens about 6 per page, so this serves all
#: MAX_VIEWERS browsers loading at the same time, while a flood of sockets cannot take
#: the bridge's file descriptors (the MAVLink link needs its own). Opened WebSockets do
#: not count (MAX_VIEWERS bounds them).
MAX_CONNECTIONS = 128
#: Largest request body: the view accepts none (GET only), so any body is refused.
MAX_BODY_BYTES = 64 * 1024


class WebViewError(OSError):
    """The view cannot be served (the port is in use, the address is not ours): a
    setting to fix, reported as one line."""


def parse_web(text: str) -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (``[v6]:PORT``) -> (host, port); 127.0.0.1 by default."""
    host, sep, port = str(text).strip().rpartition(":")
    if not sep:
        host = "127.0.0.1"
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--web {text}: expected PORT or HOST:PORT (e.g. 8080, "
                         f"0.0.0.0:8080)")
    return host, int(port)


@dataclass
class WebStats:
    viewers: int = 0
    viewers_total: int = 0
    viewers_refused: int = 0
    frames: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0  # a browser still busy with the previous frame
    incoming_ignored: int = 0
    tick_ms_max: float = 0.0  # the longest snapshot + JSON: the event loop is busy that
    tick_ms_mean: float = 0.0  # long, an IMU packet arriving meanwhile waits
    work_ms: float = 0.0  # all of the view's time on the event loop (frames and sends):
    # what it takes from the MAVLink path, whatever else the machine is doing


class WebView:
    """Serves the page and pushes one frame per tick to every browser that is ready."""

    def __init__(self, host: str, port: int, take_snapshot: Callable[[], dict[str, Any]],
                 window_s: float = HISTORY_S) -> None:
        self.host = host
        self.port = port
        self.take_snapshot = take_snapshot
        self.stats = WebStats()
        self.viewers: set[_ViewSocket] = set()
        self.history: deque[str] = deque(maxlen=max(1, int(window_s * FRAME_HZ)))
        self.window_s = window_s
        self._server: HTTPServer | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self) -> None:
        """Bind and listen (WebViewError when the address cannot be had)."""
        try:
            sockets = bind_sockets(self.port, self.host)
        except OSError as exc:
            reason = BIND_REASONS.get(exc.errno, exc.strerror or str(exc))
            raise WebViewError(f"--web {self.host}:{self.port}: {reason}") from None
        except (UnicodeError, ValueError) as exc:  # a host name that is no host name
            raise WebViewError(f"--web {self.host}:{self.port}: {exc}") from None
        self.port = sockets[0].getsockname()[1]
        static = resources.files("bridge.publish") / "webview"
        app = tornado.web.Application([
            (r"/", _PageHandler, {"page": (static / "index.html").read_bytes()}),
            (r"/ws", _ViewSocket, {"view": self}),
            (r"/view/(.*)", _StaticHandler, {"path": str(static)}),
            (r"/bokeh/(.*)", _StaticHandler, {"path": str(bokehjs_path() / "js")}),
        ], websocket_max_message_size=MAX_INCOMING_BYTES, websocket_ping_interval=5.0,
            websocket_ping_timeout=5.0, log_function=_quiet_access_log)
        self._server = _BoundedHTTPServer(app, idle_connection_timeout=REQUEST_TIMEOUT_S,
                                          body_timeout=REQUEST_TIMEOUT_S,
                                          max_body_size=MAX_BODY_BYTES)
        self._server.add_sockets(sockets)
        log.info("web view at %s (read-only; %d Hz)", self.url, FRAME_HZ)

    def tick(self) -> None:
        """Take a snapshot and hand it to every browser that has written out the last.

        Each browser's send is a callback of its own on the event loop, so that an IMU
        packet arriving meanwhile waits for one send at most, not for all of them."""
        t0 = time.perf_counter()
        frame = {"type": "frame", "time_unix": round(time.time(), 3),
                 **self.take_snapshot()}
        text = json.dumps(frame, separators=(",", ":"), allow_nan=False)
        self.history.append(text)
        self.stats.frames += 1
        loop = asyncio.get_running_loop()
        for viewer in list(self.viewers):
            loop.call_soon(self._send, viewer, text)
        ms = (time.perf_counter() - t0) * 1e3
        st = self.stats
        st.tick_ms_max = max(st.tick_ms_max, round(ms, 3))
        st.tick_ms_mean = round(ms if st.frames == 1 else 0.95 * st.tick_ms_mean + 0.05 * ms, 3)
        st.work_ms = round(st.work_ms + ms, 3)

    def _send(self, viewer: _ViewSocket, text: str) -> None:
        t0 = time.perf_counter()
        if viewer.send(text):
            self.stats.frames_sent += 1
        else:
            self.stats.frames_dropped += 1
        self.stats.work_ms = round(self.stats.work_ms + (time.perf_counter() - t0) * 1e3, 3)

    def hello(self) -> str:
        """What a browser is told first: the settings of the view and its history."""
        head = json.dumps({"type": "hello", "frame_hz": FRAME_HZ,
                           "window_s": self.window_s, "bokeh": bokeh_version})
        return f'{head[:-1]},"history":[{",".join(self.history)}]}}'  # frames as they are

    def status(self) -> dict[str, Any]:
        return {"url": self.url, **asdict(self.stats)}

    def close(self) -> None:
        if self._server is not None:
            self._server.stop()
        for viewer in list(self.viewers):
            viewer.close(1001, "bridge stopping")


class _BoundedHTTPServer(HTTPServer):
    """At most :data:`MAX_CONNECTIONS` HTTP connections at once; more are closed."""

    def handle_stream(self, stream: IOStream, address: tuple) -> None:
        # Tornado keeps its open HTTP connections in _connections (a WebSocket leaves
        # it when it takes its stream over).
        if len(getattr(self, "_connections", ())) >= MAX_CONNECTIONS:
            stream.close()
            return
        super().handle_stream(stream, address)


class _StaticHandler(tornado.web.StaticFileHandler):
    """Tornado's static files, with a path holding a NUL byte refused (400): the file
    system calls raise ValueError on it, which would be an HTTP 500 and a traceback."""

    def parse_url_path(self, url_path: str) -> str:
        if "\x00" in url_path:
            raise tornado.web.HTTPError(400)
        return super().parse_url_path(url_path)


def _valid_websocket_key(key: str) -> bool:
    """RFC 6455 4.2.1: the key is the base64 of 16 bytes."""
    try:
        return len(base64.b64decode(key.strip(), validate=True)) == 16
    except (binascii.Error, ValueError):
        return False


def _quiet_access_log(handler: tornado.web.RequestHandler) -> None:
    """Page loads at DEBUG: a service log is no access log."""
    log.debug("%d %s %s", handler.get_status(), handler.request.method,
              handler.request.uri)


def _consume(future: Any) -> None:
    """A write that failed because the browser went away: on_close says so."""
    if not future.cancelled():
        future.exception()


class _PageHandler(tornado.web.RequestHandler):
    def initialize(self, page: bytes) -> None:
        self.page = page

    def get(self) -> None:
        self.set_header("Content-Type", "text/html; charset=utf-8")
        self.set_header("Cache-Control", "no-store")
        self.set_header("X-Content-Type-Options", "nosniff")
        self.write(self.page)


class _ViewSocket(tornado.websocket.WebSocketHandler):
    """One browser: frames out, nothing in (same origin only: Tornado's default)."""

    def initialize(self, view: WebView) -> None:
        self.view = view
        self._pending = None

    async def get(self, *args: Any, **kwargs: Any) -> None:
        key = self.request.headers.get("Sec-WebSocket-Key")
        if key is not None and not _valid_websocket_key(key):
            # Tornado checks the key is there, not what it is.
            self.set_status(400)
            self.finish("Sec-WebSocket-Key must be the base64 of 16 bytes")
            return
        await super().get(*args, **kwargs)

    def open(self) -> None:
        view = self.view
        if len(view.viewers) >= MAX_VIEWERS:
            view.stats.viewers_refused += 1
            self.close(1013, f"at most {MAX_VIEWERS} viewers")
            return
        stream = self.ws_connection.stream if self.ws_connection is not None else None
        if stream is not None and stream.socket is not None:
            stream.socket.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, VIEWER_SEND_BUFFER)
        view.viewers.add(self)
        view.stats.viewers = len(view.viewers)
        view.stats.viewers_total += 1
        self.send(view.hello())

    def send(self, text: str) -> bool:
        """Write ``text`` unless the previous frame is still on its way (False: dropped)."""
        if self._pending is not None and not self._pending.done():
            return False
        try:
            self._pending = self.write_message(text)
        except tornado.websocket.WebSocketClosedError:
            self._forget()
            return False
        self._pending.add_done_callback(_consume)
        return True

    def on_message(self, message: str | bytes) -> None:
        self.view.stats.incoming_ignored += 1  # read-only: the page has nothing to say

    def on_close(self) -> None:
        self._forget()

    def _forget(self) -> None:
        self.view.viewers.discard(self)
        self.view.stats.viewers = len(self.view.viewers)
