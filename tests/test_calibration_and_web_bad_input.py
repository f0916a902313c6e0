"""Bad input to the calibration loader and to the web view (``--web``).

A calibration file with text for numbers, or with nothing in it, is refused with one
line naming what is wrong; a web request that is malformed is answered 4xx (never 500
with a traceback in the log), and one that is never finished is closed after
:data:`REQUEST_TIMEOUT_S`, while an opened WebSocket stays open.
"""

from __future__ import annotations

import select
import socket
import subprocess
import sys
import time

import pytest
from web_bridge import WebBridge

from bridge.publish.web import MAX_CONNECTIONS, REQUEST_TIMEOUT_S
from imu.calibration import SensorCalibration

# --- calibration files -----------------------------------------------------------------


@pytest.mark.parametrize("text, message", [
    ('[gyro]\noffset = ["0.5", 0, 0]\n',
     r"gyro\.offset must be 3 numbers, got \['0\.5', 0, 0\]"),
    ('[accel]\nmatrix = [["1", 0, 0], [0, "1.0", 0], [0, 0, "1"]]\n',
     r"accel\.matrix must be a 3x3 array of numbers, got \[\['1', 0, 0\]"),
    ('[mag]\noffset = [0, 0, "nan"]\n', r"mag\.offset must be 3 numbers"),
    ('[gyro]\noffset = [0, 0, {a = 1}]\n', r"gyro\.offset must be 3 numbers"),
])
def test_text_for_a_number_is_refused_naming_the_key(tmp_path, text, message):
    path = tmp_path / "strings.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        SensorCalibration.load(path)
    assert str(info.value).startswith(f"{path}: ")
    # The constructor refuses them too (numpy would read "0.5" as 0.5).
    with pytest.raises(ValueError, match="gyro_offset must be 3 numbers"):
        SensorCalibration(gyro_offset=["0.5", 0, 0])


@pytest.mark.parametrize("text", ["", "\n# only a comment\n", "[meta]\nnote = 'x'\n"])
def test_a_file_with_no_sensor_table_is_refused(tmp_path, text):
    path = tmp_path / "empty.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        SensorCalibration.load(path)
    assert str(info.value) == f"{path}: no [gyro], [accel] or [mag] table"


@pytest.mark.parametrize("text, table, keys", [
    ("[gyro]\n", "gyro", "matrix and/or offset"),
    ("[accel]\noffset = [0.1, 0, 0]\n[mag]\n", "mag", "matrix and/or offset"),
])
def test_an_empty_sensor_table_is_refused(tmp_path, text, table, keys):
    """A file cut after a table's header applied nothing for that sensor, unsaid."""
    path = tmp_path / "cut.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        SensorCalibration.load(path)
    assert str(info.value) == (f"{path}: [{table}] is empty; give {keys}, or leave the "
                               f"table out")


def test_run_refuses_them_in_one_line_with_exit_2(tmp_path):
    strings = tmp_path / "s.toml"
    strings.write_text('[gyro]\noffset = ["0.5", 0, 0]\n'
                       'matrix = [["1",0,0],[0,"1.0",0],[0,0,"1"]]\n')
    empty = tmp_path / "e.toml"
    empty.write_text("")
    for path, said in ((strings, "gyro.offset must be 3 numbers, got ['0.5', 0, 0]"),
                       (empty, "no [gyro], [accel] or [mag] table")):
        out = subprocess.run([sys.executable, "-m", "bridge.app.cli", "run", "--calibration",
                              str(path), "--duration", "2"], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 2, out.stderr
        assert out.stderr.strip().splitlines() == [
            f"attitude-bridge run: error: {path}: {said}"]


# --- the web view -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    b = WebBridge.serving(tmp_path_factory.mktemp("web_bad_input"), "-e", "mahony",
                          env={"ATTITUDE_BRIDGE_DEBUG": "1"})
    try:
        yield b
    finally:
        code = b.stop()
        assert code == 0, b.log()
        assert "Traceback" not in b.log(), b.log()


def _status_line(sock: socket.socket) -> int:
    head = b""
    while b"\r\n" not in head:
        got = sock.recv(1)
        assert got, f"closed without an answer after {head!r}"
        head += got
    return int(head.split()[1])


def _request(bridge: WebBridge, text: str) -> int:
    with bridge.connect() as sock:
        sock.sendall(text.encode())
        return _status_line(sock)


def _closed_within(sock: socket.socket, seconds: float) -> float | None:
    """Seconds until the server closes ``sock`` (None: still open after ``seconds``)."""
    t0 = time.monotonic()
    sock.settimeout(seconds)
    try:
        while True:
            got = sock.recv(4096)
            if not got:
                return time.monotonic() - t0
    except TimeoutError:
        return None
    except ConnectionResetError:
        return time.monotonic() - t0


def _upgrade(bridge: WebBridge, key: str) -> str:
    origin = f"http://{bridge.host}:{bridge.port}"
    return (f"GET /ws HTTP/1.1\r\nHost: {bridge.host}:{bridge.port}\r\n"
            "Upgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            f"Origin: {origin}\r\n\r\n")


@pytest.mark.parametrize("path", ["/view/view.js%00.html", "/view/%00", "/bokeh/a%00b.js"])
def test_a_nul_byte_in_a_path_is_400_not_500(bridge, path):
    code = _request(bridge, f"GET {path} HTTP/1.1\r\nHost: {bridge.host}\r\n"
                            "Connection: close\r\n\r\n")
    assert code in (400, 404), code
    assert "Traceback" not in bridge.log() and "null byte" not in bridge.log(), bridge.log()


@pytest.mark.parametrize("key", ["!!notb64", "dGhlIHNhbXBsZQ==", "dGhlIHNhbXBsZSBub25jZQ",
                                 "dGhlIHNhbXBsZSBub25jZSEh"])
def test_a_websocket_key_not_base64_of_16_bytes_is_400(bridge, key):
    assert _request(bridge, _upgrade(bridge, key)) == 400
    # (the good key of RFC 6455's example opens)
    assert _request(bridge, _upgrade(bridge, "dGhlIHNhbXBsZSBub25jZQ==")) == 101


def test_half_sent_requests_are_closed_but_websockets_are_not(bridge):
    limit = REQUEST_TIMEOUT_S + 3.0
    one_byte = bridge.connect()
    trickle = bridge.connect()
    viewer = bridge.connect()
    try:
        viewer.sendall(_upgrade(bridge, "dGhlIHNhbXBsZSBub25jZQ==").encode())
        assert _status_line(viewer) == 101
        one_byte.sendall(b"G")
        trickle.sendall(f"GET / HTTP/1.1\r\nHost: {bridge.host}\r\n".encode())
        t0 = time.monotonic()
        trickle_closed = None
        while time.monotonic() - t0 < limit:  # a header line a second: still cut
            try:
                trickle.sendall(b"X-Slow: 1\r\n")
            except (BrokenPipeError, ConnectionResetError):
                trickle_closed = time.monotonic() - t0
                break
            if _closed_within(trickle, 1.0) is not None:
                trickle_closed = time.monotonic() - t0
                break
        assert trickle_closed is not None, "a trickled request was never timed out"
        waited = _closed_within(one_byte, max(0.1, limit - (time.monotonic() - t0)))
        assert waited is not None, "a one-byte request was never timed out"
        # The WebSocket opened before both still gets frames after the timeout.
        viewer.settimeout(5)
        viewer.setblocking(False)
        try:
            while viewer.recv(65536):
                pass
        except BlockingIOError:
            pass
        viewer.settimeout(5)
        assert viewer.recv(65536), "the WebSocket was closed"
    finally:
        for s in (one_byte, trickle, viewer):
            s.close()


def test_connections_beyond_the_cap_are_closed_at_once(bridge):
    socks = [bridge.connect() for _ in range(MAX_CONNECTIONS + 5)]
    try:
        time.sleep(1.0)  # (well within REQUEST_TIMEOUT_S: only the cap closes them)
        readable, _, _ = select.select(socks, [], [], 0)
        closed = [s for s in readable if _closed_within(s, 0.01) is not None]
        assert len(closed) == 5, len(closed)  # the extra ones, none of the rest
    finally:
        for s in socks:
            s.close()
    time.sleep(0.5)  # the server sees them go; then a page loads again
    assert _request(bridge, f"GET / HTTP/1.1\r\nHost: {bridge.host}\r\n"
                            "Connection: close\r\n\r\n") == 200
