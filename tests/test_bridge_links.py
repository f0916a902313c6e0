"""TCP and serial links with real peers, and the `run` command as a real process."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np
import pytest
from bridge_support import (
    UdpListener,
    async_test,
    euler_q,
    free_udp_port,
    raw_imu,
    running_bridge,
    wait_until,
)

from bridge.wire.links import TcpLink, parse_url
from bridge.wire.mav import mavlink

REPO = Path(__file__).resolve().parents[1]


def imu_bytes(mav: mavlink.MAVLink, q, n: int, t0_us: int) -> bytes:
    out = bytearray()
    for i in range(n):
        out += raw_imu(t0_us + 2000 * i, q).pack(mav)
        mav.seq = (mav.seq + 1) % 256
    return bytes(out)


def parse_all(data: bytes) -> list:
    parser = mavlink.MAVLink(None, 255, 0)
    parser.robust_parsing = True
    return [m for m in parser.parse_buffer(data) or [] if
            not isinstance(m, mavlink.MAVLink_bad_data)]


@async_test
async def test_tcp_link_streams_and_reconnects_after_the_peer_drops():
    q0 = euler_q(5.0, 10.0, -30.0)
    received: list[bytes] = []
    sessions = []
    finished = []  # sessions whose replies have all been read

    loop = asyncio.get_running_loop()
    booted = loop.time() - 1.0

    async def vehicle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A TCP 'autopilot' whose board clock runs in real time: 200 IMU samples at
        500 Hz, read the replies, then hang up."""
        sessions.append(len(sessions))
        mav = mavlink.MAVLink(None, 1, 1)
        for _ in range(8):
            writer.write(imu_bytes(mav, q0, 25, int((loop.time() - booted) * 1e6)))
            await writer.drain()
            await asyncio.sleep(0.05)
        with contextlib.suppress(TimeoutError):
            while data := await asyncio.wait_for(reader.read(65536), 0.4):
                received.append(data)
        writer.close()
        finished.append(len(finished))

    server = await asyncio.start_server(vehicle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with running_bridge(connect=f"tcp:127.0.0.1:{port}", out_rate=0.0) as bridge:
        # wait for what is asserted on: two whole sessions, their replies read
        ok = await wait_until(lambda: len(finished) >= 2 and
                              sum(s.accepted for s in bridge.ingest.sources.values()) >= 400,
                              timeout=10.0)
        reconnects = bridge.link.stats.reconnects
    server.close()
    assert ok
    assert reconnects >= 1
    msgs = parse_all(b"".join(received))
    aq = [m for m in msgs if m.get_type() == "ATTITUDE_QUATERNION"]
    assert len(aq) >= 300 and {m.get_srcComponent() for m in aq} == {191}
    last = np.array([aq[-1].q1, aq[-1].q2, aq[-1].q3, aq[-1].q4])
    assert abs(np.dot(last, q0)) > np.cos(np.radians(1.0) / 2)


@async_test
async def test_serial_link_over_a_pseudo_terminal():
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    q0 = euler_q(-15.0, 5.0, 100.0)
    out = bytearray()

    def readable() -> None:  # the vehicle side reads the bridge's replies as they come
        with contextlib.suppress(BlockingIOError):
            out.extend(os.read(master, 65536))

    def replies() -> int:
        return sum(m.get_type() == "ATTITUDE_QUATERNION" for m in parse_all(bytes(out)))

    os.set_blocking(master, False)
    loop = asyncio.get_running_loop()
    loop.add_reader(master, readable)
    try:
        async with running_bridge(connect=f"serial:{path}:921600", out_rate=0.0) as bridge:
            await asyncio.sleep(0.3)  # the link opens the port in its own task
            mav = mavlink.MAVLink(None, 1, 1)
            data = imu_bytes(mav, q0, 300, 5_000_000)
            for i in range(0, len(data), 512):
                os.write(master, data[i:i + 512])
                await asyncio.sleep(0.002)
            ok = await wait_until(
                lambda: sum(s.accepted for s in bridge.ingest.sources.values()) >= 300)
            await wait_until(lambda: replies() >= 300)
    finally:
        loop.remove_reader(master)
        os.close(master)
        os.close(slave)
    assert ok
    aq = [m for m in parse_all(bytes(out)) if m.get_type() == "ATTITUDE_QUATERNION"]
    assert len(aq) == 300  # every sample answered (out_rate 0), nothing lost on the tty
    last = np.array([aq[-1].q1, aq[-1].q2, aq[-1].q3, aq[-1].q4])
    assert abs(np.dot(last, q0)) > np.cos(np.radians(1.0) / 2)


@async_test
async def test_run_command_serves_and_stops_on_sigint():
    listener = UdpListener()
    out_port = await listener.start()
    in_port = free_udp_port()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.app.cli", "run", "--connect", f"udpin:127.0.0.1:{in_port}",
         "--out", f"udpout:127.0.0.1:{out_port}", "--estimator", "quaternion"],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # Up once its HEARTBEAT arrives; then it must answer IMU input with attitude.
        assert await wait_until(lambda: listener.of_type("HEARTBEAT"), timeout=60.0)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.sendto(imu_bytes(mavlink.MAVLink(None, 3, 1), euler_q(0, 0, 0), 1, 1000),
                    ("127.0.0.1", in_port))
        for i in range(1, 50):
            sock.sendto(raw_imu(1000 + 2000 * i, euler_q(0, 0, 0)).pack(
                mavlink.MAVLink(None, 3, 1)), ("127.0.0.1", in_port))
        sock.close()
        assert await wait_until(lambda: listener.of_type("ATTITUDE_QUATERNION", 3), 10.0)
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        out, err = proc.communicate(timeout=10.0)
        stopped_after = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        listener.close()
    assert proc.returncode == 0, err
    assert "attitude-bridge summary" in out and "vehicle 3" in out
    assert stopped_after < 5.0  # generous under CI load; the benchmark note gives the time


@pytest.mark.parametrize(("url", "why"), [
    ("tcp:nonexistent.invalid:5760", "cannot resolve host 'nonexistent.invalid'"),
    ("/dev/ttyDOESNOTEXIST:921600", "no such serial device '/dev/ttyDOESNOTEXIST'"),
    # not a terminal: pyserial said "Inappropriate ioctl" and it was retried for ever
    ("/dev/zero:57600", "'/dev/zero' is not a serial device"),
    ("/dev/null", "'/dev/null' is not a serial device"),
    ("/dev/zero:0", "baud rate 0 is not one a port runs at"),
    ("/dev/zero:abc", "bad baud rate 'abc'"),  # was "no such serial device"
])
def test_run_refuses_a_link_that_cannot_exist_at_start(url, why):
    """A host name that does not resolve or a serial device that is not there is a typo:
    one line and exit 2 at once, not retries for ever (here: until --duration ends)."""
    out = subprocess.run(
        [sys.executable, "-m", "bridge.app.cli", "run", "--connect", url, "--estimator",
         "quaternion", "--duration", "2"],
        cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr
    assert out.stderr.startswith("attitude-bridge run: error: ") and why in out.stderr


@async_test
async def test_refused_tcp_port_is_retried_and_told_once(caplog):
    """An autopilot that is still starting refuses: one WARNING says so, the link keeps
    trying with backoff, and connects once the port listens."""
    with socket.socket() as autopilot:
        autopilot.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
        port = autopilot.getsockname()[1]
        link = TcpLink(parse_url(f"tcp:127.0.0.1:{port}"))
        with caplog.at_level(logging.WARNING, logger="bridge.wire"):
            await link.start()
            try:
                retried = await wait_until(lambda: link.stats.reconnects >= 3)
                autopilot.listen()
                connected = await wait_until(lambda: link.connected)
            finally:
                await link.close()
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert retried and connected
    assert len(warnings) == 1, warnings
    assert warnings[0].startswith(f"tcp:127.0.0.1:{port}: connection refused by "
                                  f"127.0.0.1:{port}; retrying")


@async_test
async def test_a_handler_that_fails_on_every_message_is_counted_not_a_traceback_flood(caplog):
    """A message whose handling raises (a bug) is counted in the link's status; the
    traceback is logged once per kind of failure, then a counted warning now and then —
    not one traceback per sample with a summary that says nothing was dropped."""
    from bridge.wire.udp import UdpLink

    def broken(msg, link) -> None:
        raise ZeroDivisionError("division by zero")

    port = free_udp_port()
    link = UdpLink(parse_url(f"udpin:127.0.0.1:{port}"), on_message=broken)
    with caplog.at_level(logging.WARNING, logger="bridge.wire"):
        await link.start()
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
                mav = mavlink.MAVLink(None, 1, 1)
                for k in range(150):
                    sender.sendto(imu_bytes(mav, euler_q(0, 0, 0), 1, 1000 + 2000 * k),
                                  ("127.0.0.1", port))
                    await asyncio.sleep(0)
            counted = await wait_until(lambda: link.stats.handler_failures == 150)
        finally:
            await link.close()
    assert counted, link.stats
    tracebacks = [r for r in caplog.records if r.exc_info]
    warnings = [r.getMessage() for r in caplog.records
                if r.levelno == logging.WARNING and "failed" in r.getMessage()]
    assert len(tracebacks) == 1
    assert warnings == [f"udpin:127.0.0.1:{port}: handling RAW_IMU has failed {n} times "
                        f"(ZeroDivisionError: division by zero)" for n in (10, 100)]


def test_an_output_the_os_refuses_is_told_once_and_counted():
    """`--out udpout:255.255.255.255:14550` (broadcast without SO_BROADCAST): every send
    failed with EACCES, nothing was logged and the status said 0 send errors."""
    out = subprocess.run([sys.executable, "-m", "bridge.app.cli", "run", "--duration", "2",
                          "-q", "--out", "udpout:255.255.255.255:9"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    text = out.stdout + out.stderr
    assert out.returncode == 0, text[-2000:]
    assert text.count("udpout:255.255.255.255:9: cannot send to 255.255.255.255:9: "
                      "Permission denied") == 1
    assert " output udpout:255.255.255.255:9: {'send_errors': " in text
