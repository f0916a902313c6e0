"""The live web view (``--web``) in a real browser: Debian's headless Chromium driven by
Playwright, against the bridge as a user starts it (``attitude-bridge run --web``, the
built-in emulator as the source), over real sockets.

The page must load without console errors, update at the view's frame rate, show the
numbers of the bridge's own status report, and leave nothing behind when the browser
closes; the server must stay read-only, same-origin, bounded (viewers, a slow viewer's
frames) and say clearly when its port is taken.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import time
from urllib.error import HTTPError
from urllib.request import Request, urlopen

import pytest
from web_bridge import WebBridge

from bridge.publish.web import FRAME_HZ, MAX_VIEWERS, parse_web

pytestmark = pytest.mark.xdist_group("web")

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
#: As the machine's notes say: without the background-networking flags Chromium tries
#: Google's hosts at every start, which a closed network refuses.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    b = WebBridge.serving(tmp_path_factory.mktemp("web"), "-e", "eskf", "-e", "mahony")
    try:
        b.wait_for(lambda st: st["vehicles"].get("1", {}).get("compare", {}).get("truth"),
                   60, "comparison with the emulator's truth")
        yield b
    finally:
        code = b.stop()
        assert code == 0, b.log()


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


_OPEN: list = []  # closed after each test, whatever it asserted


@pytest.fixture(autouse=True)
def _close_pages():
    yield
    while _OPEN:
        _OPEN.pop().close()


def open_page(browser, url: str):
    """A page in a context of its own, with every console error and page error kept."""
    context = browser.new_context(viewport={"width": 1200, "height": 1400})
    _OPEN.append(context)
    page = context.new_page()
    page.problems = []
    page.on("console", lambda m: page.problems.append(f"{m.type}: {m.text}")
            if m.type in ("error", "warning") else None)
    page.on("pageerror", lambda e: page.problems.append(f"pageerror: {e}"))
    page.goto(url)
    return context, page


def shown(page, sysid: int, field: str) -> str:
    return page.inner_text(f'section[data-sysid="{sysid}"] [data-field="{field}"]')


def test_page_shows_every_estimator_and_reference_live(bridge, browser):
    url = bridge.web["url"]
    assert url.startswith("http://127.0.0.1:")  # nobody else's business by default
    context, page = open_page(browser, url)
    # the vehicle's section and its plots appear (how fast is a benchmark's question,
    # benchmarks/web_load.py: this one times nothing)
    page.wait_for_selector('section[data-sysid="1"] canvas', timeout=30000)
    # one indicator per estimator, the autopilot's own and the truth; the primary marked
    names = page.eval_on_selector_all('section[data-sysid="1"] .indicator',
                                      "els => els.map(e => e.dataset.series)")
    assert names == ["eskf", "mahony", "vehicle", "truth"]
    assert page.get_attribute('.indicator[data-series="eskf"]', "class") == "indicator primary"
    # it updates at the frame rate, and the plots fill (BokehJS drew them)
    web0, t0 = bridge.web, time.monotonic()
    frames0 = page.evaluate("window.attitudeView.frames")
    angles0 = page.inner_text('.indicator[data-series="eskf"] .angles')
    time.sleep(6.0)
    web1, t1 = bridge.web, time.monotonic()
    frames1 = page.evaluate("window.attitudeView.frames")
    # The bridge makes FRAME_HZ >= 10 frames a second (the status file is a second old
    # at most at either end), and every one of them either reached this page (the only
    # viewer) or was dropped because the page was still busy with the one before (a
    # loaded machine): none is lost or queued.
    made = web1["frames"] - web0["frames"]
    assert FRAME_HZ >= 10.0 and made >= FRAME_HZ * (t1 - t0 - 2.0)
    dropped = web1["frames_dropped"] - web0["frames_dropped"]
    assert abs((frames1 - frames0) + dropped - made) <= 2 * FRAME_HZ, (frames1 - frames0,
                                                                      dropped, made)
    assert frames1 - frames0 >= 2.0 * (t1 - t0)  # and it does update
    # the view's time on the bridge's loop is accounted (benchmarks/web_latency.py reads it)
    assert web1["work_ms"] > web0["work_ms"] > 0.0
    assert page.inner_text('.indicator[data-series="eskf"] .angles') != angles0
    points = page.evaluate("Object.values(window.attitudeView.vehicles['1'].sources)"
                           ".map(s => s.data.t.length)")
    assert min(points) > 30, points
    assert page.locator("section[data-sysid='1'] .bk-Canvas, section[data-sysid='1'] "
                        "canvas").count() > 4
    assert page.evaluate("window.attitudeView.errors") == []
    assert page.problems == []
    context.close()
    bridge.wait_for(lambda st: st["connection"]["web"]["viewers"] == 0, 5, "the page gone")


def test_page_agrees_with_the_status_report(bridge, browser):
    context, page = open_page(browser, bridge.web["url"])
    # (how soon the page shows is the first test's to hold; here it is what it shows)
    page.wait_for_selector('section[data-sysid="1"] table.errors td', timeout=10000)
    # The page and the status file come from the same report (once a second): read both
    # until they are of the same second.
    for _ in range(30):
        st = bridge.status()["vehicles"]["1"]
        row = page.eval_on_selector_all(
            'section[data-sysid="1"] tr[data-row="eskf"] td', "tds => tds.map(t => t.innerText)")
        truth = st["compare"]["truth"]["eskf"]
        imu = st["imu_stream"]
        if row[1:3] == [f"{truth['total_deg']:.2f}", f"{truth['inclination_deg']:.2f}"]:
            break
        time.sleep(0.2)
    else:
        raise AssertionError(f"page {row} never matched the status {truth}")
    assert shown(page, 1, "imu").startswith(f"RAW_IMU {imu['achieved_hz']:.0f} Hz")
    dec = st["declination"]
    assert shown(page, 1, "declination").startswith(f"{dec['deg']:.2f}° ({dec['source']}")
    fs = st["flight_state"]
    assert shown(page, 1, "flight").startswith(f"{fs['state']} ({fs['source']}")
    # the estimate shown is the bridge's: within a few degrees of the truth shown beside it
    att = page.evaluate("window.attitudeView.last.vehicles['1'].series")
    assert abs(att["eskf"][1] - att["truth"][1]) < 5 and abs(att["eskf"][2] - att["truth"][2]) < 5
    assert page.problems == []
    context.close()


def test_the_live_part_does_not_wait_for_the_plots(bridge, browser):
    """BokehJS (the plots) loads beside the live part: with BokehJS refused, the
    indicators, facts and error table still show and update, and the page says why
    there are no plots."""
    context = browser.new_context(viewport={"width": 1200, "height": 1400})
    _OPEN.append(context)
    page = context.new_page()
    page.route("**/bokeh/**", lambda route: route.abort())
    page.goto(bridge.web["url"])
    page.wait_for_selector('section[data-sysid="1"] table.errors td', timeout=10000)
    # drawn again and again (the angles themselves may hold still for a while)
    drawn0 = page.evaluate("window.attitudeView.drawn")
    time.sleep(1.0)
    assert page.evaluate("window.attitudeView.drawn") >= drawn0 + 3
    assert page.inner_text('.indicator[data-series="eskf"] .angles') != "–"
    assert shown(page, 1, "imu").startswith("RAW_IMU")
    assert page.locator("section[data-sysid='1'] .bk-Canvas").count() == 0
    errors = page.evaluate("window.attitudeView.errors")
    assert len(errors) == 1 and "bokeh" in errors[0] and "did not load" in errors[0], errors
    context.close()


def test_five_viewers_then_none_left_behind(bridge, browser):
    pages = []
    try:
        for _ in range(5):
            pages.append(open_page(browser, bridge.web["url"]))
        for _, page in pages:
            page.wait_for_selector('section[data-sysid="1"] canvas', timeout=5000)
        bridge.wait_for(lambda st: st["connection"]["web"]["viewers"] == 5, 5, "5 viewers")
        for _, page in pages:
            assert page.problems == []
    finally:
        for context, _ in pages:
            context.close()
    st = bridge.wait_for(lambda st: st["connection"]["web"]["viewers"] == 0, 5,
                         "every viewer gone")
    assert st["vehicles"]["1"]["online"]  # the bridge went on estimating meanwhile


def test_server_is_read_only_and_same_origin(bridge):
    url = bridge.web["url"]
    for method, path, code in (("POST", "", 405), ("PUT", "ws", 405), ("DELETE", "", 405),
                               ("GET", "status", 404), ("GET", "../etc/passwd", 404),
                               ("GET", "view/../web.py", 403)):
        with pytest.raises(HTTPError) as err:
            urlopen(Request(url + path, method=method, data=b"" if method != "GET" else None),
                    timeout=5)
        assert err.value.code in (code, 404), (method, path, err.value.code)
    host, port = url.removeprefix("http://").rstrip("/").split(":")
    # a page of another origin may not open the frame stream
    assert _handshake(host, int(port), origin="http://evil.example")[0] == 403


def test_a_slow_viewer_loses_frames_not_memory(bridge):
    """A viewer that never reads: its frames are dropped while its last one is in flight;
    the bridge goes on; when it goes, it is forgotten."""
    host, port = bridge.web["url"].removeprefix("http://").rstrip("/").split(":")
    before = bridge.web
    code, sock = _handshake(host, int(port), origin=f"http://{host}:{port}", rcvbuf=4096)
    assert code == 101
    samples0 = bridge.status()["vehicles"]["1"]["samples"]
    # (its buffers, 64 KB on our side, fill at 10 frames of ~1.5 KB a second)
    st = bridge.wait_for(lambda s: s["connection"]["web"]["frames_dropped"]
                         > before["frames_dropped"] + 10, 45, "frames dropped")
    assert st["connection"]["web"]["viewers"] >= 1
    assert st["vehicles"]["1"]["samples"] > samples0 + 250  # estimating meanwhile
    sock.close()
    bridge.wait_for(lambda s: s["connection"]["web"]["viewers"] == 0, 20, "the slow viewer gone")


def test_at_most_max_viewers(bridge):
    host, port = bridge.web["url"].removeprefix("http://").rstrip("/").split(":")
    socks = []
    try:
        for _ in range(MAX_VIEWERS):
            code, s = _handshake(host, int(port), origin=f"http://{host}:{port}")
            assert code == 101
            socks.append(s)
        bridge.wait_for(lambda st: st["connection"]["web"]["viewers"] == MAX_VIEWERS, 5,
                        f"{MAX_VIEWERS} viewers")
        refused0 = bridge.web["viewers_refused"]
        code, extra = _handshake(host, int(port), origin=f"http://{host}:{port}")
        socks.append(extra)
        bridge.wait_for(lambda st: st["connection"]["web"]["viewers_refused"] == refused0 + 1,
                        5, "the viewer beyond the limit refused")
    finally:
        for s in socks:
            s.close()
    bridge.wait_for(lambda st: st["connection"]["web"]["viewers"] == 0, 20, "viewers gone")


def test_port_in_use_is_one_line_and_exit_2(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = subprocess.run([sys.executable, "-m", "bridge.app.cli", "run", "--web",
                              str(port), "--duration", "5"], capture_output=True, text=True,
                             timeout=60)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert lines[-1] == (f"attitude-bridge run: error: --web 127.0.0.1:{port}: address already in "
                         "use (another program, or another bridge, is listening on that port)")
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize("text, expected", [("8080", ("127.0.0.1", 8080)),
                                            ("0.0.0.0:8080", ("0.0.0.0", 8080)),
                                            ("[::1]:9000", ("::1", 9000)),
                                            ("localhost:0", ("localhost", 0))])
def test_web_address(text, expected):
    assert parse_web(text) == expected


@pytest.mark.parametrize("text", ["", "web", "8080x", "host:", "1:70000", "-1"])
def test_bad_web_address_is_a_clear_error(text):
    with pytest.raises(ValueError, match="expected PORT or HOST:PORT"):
        parse_web(text)


def _handshake(host: str, port: int, origin: str, rcvbuf: int | None = None
               ) -> tuple[int, socket.socket]:
    """A WebSocket opening handshake by hand (RFC 6455), to be a client that never reads
    or one of another origin; (HTTP status, the socket)."""
    sock = socket.socket()
    if rcvbuf is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(5)
    sock.connect((host, port))
    sock.sendall((f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                  "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                  f"Sec-WebSocket-Version: 13\r\nOrigin: {origin}\r\n\r\n").encode())
    head = b""
    while b"\r\n" not in head:
        head += sock.recv(1)
    return int(head.split()[1]), sock
