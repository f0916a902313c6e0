"""MQTT output against a real mosquitto broker started by the test on a free port."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import subprocess
import time
from pathlib import Path

import aiomqtt
import numpy as np
import pytest
from bridge_support import (
    MavSender,
    UdpListener,
    async_test,
    euler_q,
    running_bridge,
    send_rotating,
    wait_until,
)

MOSQUITTO = "/usr/sbin/mosquitto"


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Broker:
    """A mosquitto process on 127.0.0.1:port with a minimal config; restartable."""

    def __init__(self, tmp: Path) -> None:
        self.port = free_tcp_port()
        self.conf = tmp / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\n"
                             "persistence false\nlog_dest none\n")
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError), socket.create_connection(
                    ("127.0.0.1", self.port), timeout=0.2):
                return
            time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(5)
            self.proc = None


@pytest.fixture
def broker(tmp_path):
    b = Broker(tmp_path)
    b.start()
    yield b
    b.stop()


class Subscriber:
    """Collects JSON messages under attitude/#, reconnecting on its own."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.messages: list[tuple[float, str, dict]] = []
        self.task: asyncio.Task | None = None

    async def _run(self) -> None:
        while True:
            try:
                async with aiomqtt.Client("127.0.0.1", self.port) as client:
                    await client.subscribe("attitude/#")
                    async for msg in client.messages:
                        self.messages.append((time.monotonic(), str(msg.topic),
                                              json.loads(msg.payload)))
            except aiomqtt.MqttError:
                await asyncio.sleep(0.2)

    def start(self) -> None:
        self.task = asyncio.create_task(self._run())

    async def stop(self) -> None:
        self.task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.task

    def topics(self, since: float = 0.0) -> set[str]:
        return {t for when, t, _ in self.messages if when >= since}


@async_test
async def test_topics_json_and_broker_outage(broker):
    sub = Subscriber(broker.port)
    sub.start()
    listener = UdpListener()
    out_port = await listener.start()
    q0 = euler_q(10.0, -5.0, 60.0)
    async with running_bridge(estimators=["eskf", "quaternion"], out_rate=50.0,
                              outs=[f"udpout:127.0.0.1:{out_port}"],
                              mqtt=f"mqtt://127.0.0.1:{broker.port}", mqtt_rate=10.0) as bridge:
        vehicle = MavSender(bridge.port)
        await vehicle.start()
        stream = asyncio.create_task(send_rotating(vehicle, q0, np.radians([0, 0, 20.0]), 11.0))
        expected = {"attitude/1/eskf", "attitude/1/quaternion", "attitude/1/status"}
        assert await wait_until(lambda: expected <= sub.topics(), timeout=5.0), sub.topics()
        # The broker goes away for 3 s.
        broker.stop()
        outage = (time.perf_counter(), None)
        await asyncio.sleep(3.0)
        outage = (outage[0], time.perf_counter())
        broker.start()
        restarted = time.monotonic()
        resumed = await wait_until(lambda: expected <= sub.topics(since=restarted), 7.0)
        await stream
        mqtt_stats = bridge.mqtt.stats
    await sub.stop()
    assert resumed, "MQTT did not resume after the broker came back"
    assert mqtt_stats.connects >= 2
    # MAVLink output never stalled while the broker was down: 50 Hz throughout.
    arrivals = np.array([t for t, m in listener.messages
                         if m.get_type() == "ATTITUDE_QUATERNION"])
    during = arrivals[(arrivals >= outage[0]) & (arrivals <= outage[1])]
    assert len(during) >= 0.9 * 3.0 * 50
    assert len(arrivals) > 0.9 * 11.0 * 50
    assert np.max(np.diff(arrivals)) < 0.25
    # Content of the per-estimator topic and of the status topic.
    est = [p for _, t, p in sub.messages if t == "attitude/1/eskf"][-1]
    assert set(est) >= {"time_s", "time_boot_ms", "q", "euler_deg", "bias_rad_s", "flags"}
    assert est["primary"] is True and est["estimator"] == "eskf"
    assert abs(np.linalg.norm(est["q"]) - 1.0) < 1e-6
    assert set(est["euler_deg"]) == {"roll", "pitch", "yaw"}
    status = [p for _, t, p in sub.messages if t == "attitude/1/status"][-1]
    assert status["input_rate_hz"] > 100
    assert set(status["drops"]) >= {"duplicate", "reordered", "jump", "backwards"}
    assert set(status["latency_ms"]) >= {"p50", "p99"}
    assert status["connection"]["mqtt"]["connected"] is True
    assert status["link"]["lost"] == 0
    listener.close()
    vehicle.close()
