"""MQTT output against a real mosquitto broker started by the test on a free port."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
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
    free_udp_port,
    running_bridge,
    send_rotating,
    wait_until,
)

from bridge.app.table import summary
from bridge.estimate.pipeline import Pipeline
from bridge.publish.estimates import EstimatePublisher
from bridge.publish.mqtt import MqttPublisher, MqttSettings
from bridge.vehicle.imu_sample import ImuSample, SourceKey
from estimators.spec import EstimatorSpec

#: mostly waits on real time: spread among computing tests (conftest)
pytestmark = pytest.mark.realtime

REPO = Path(__file__).resolve().parents[1]

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
    """Collects messages under attitude/# (JSON decoded, plain text as it is),
    reconnecting on its own; ``retained`` holds the retained ones."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.messages: list[tuple[float, str, dict | str]] = []
        self.retained: list[tuple[str, str]] = []
        self.task: asyncio.Task | None = None

    async def _run(self) -> None:
        while True:
            try:
                async with aiomqtt.Client("127.0.0.1", self.port) as client:
                    await client.subscribe("attitude/#", qos=1)
                    async for msg in client.messages:
                        text = msg.payload.decode()
                        try:
                            payload = json.loads(text)
                        except ValueError:
                            payload = text
                        self.messages.append((time.monotonic(), str(msg.topic), payload))
                        if msg.retain:
                            self.retained.append((str(msg.topic), text))
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

    def last(self, topic: str) -> dict | str | None:
        found = [p for _, t, p in self.messages if t == topic]
        return found[-1] if found else None


@async_test
async def test_topics_json_and_broker_outage(broker):
    sub = Subscriber(broker.port)
    sub.start()
    listener = UdpListener()
    out_port = await listener.start()
    q0 = euler_q(10.0, -5.0, 60.0)
    sent: dict[int, float] = {}
    async with running_bridge(estimators=["eskf", "quaternion", "quaternion:exact=false"],
                              out_rate=50.0, outs=[f"udpout:127.0.0.1:{out_port}"],
                              mqtt=f"mqtt://127.0.0.1:{broker.port}", mqtt_rate=10.0) as bridge:
        vehicle = MavSender(bridge.port)
        await vehicle.start()
        stream = asyncio.create_task(send_rotating(vehicle, q0, np.radians([0, 0, 20.0]), 11.0,
                                                   sent=sent))
        # One topic per estimator, named after it (a second instance gets -2; its
        # parameters are in the payload), the status, and the retained online state.
        expected = {"attitude/1/eskf", "attitude/1/quaternion", "attitude/1/quaternion-2",
                    "attitude/1/status"}
        assert await wait_until(lambda: expected | {"attitude/1/online"} <= sub.topics(),
                                timeout=5.0), sub.topics()
        # The broker goes away for 3 s. (Stopped and started from a thread: waiting on
        # the process here would stall this event loop, which the bridge shares, and
        # the latency below would measure the test, not the bridge.)
        await asyncio.to_thread(broker.stop)
        outage = (time.perf_counter(), None)
        await asyncio.sleep(3.0)
        outage = (outage[0], time.perf_counter())
        await asyncio.to_thread(broker.start)
        restarted = time.monotonic()
        resumed = await wait_until(lambda: expected <= sub.topics(since=restarted), 7.0)
        await stream
        stream_done = time.monotonic()
        mqtt_stats = bridge.mqtt.stats
    await asyncio.sleep(0.3)
    await sub.stop()
    assert resumed, "MQTT did not resume after the broker came back"
    assert mqtt_stats.connects >= 2
    # MAVLink output never waited on MQTT: every sample sent while the broker was down
    # got its 50 Hz output, each within a few ms of the sample. (Judged per sample: how
    # fast this test's own sender manages to send on a loaded machine is not the
    # bridge's output rate.)
    outs = [(t, m.time_boot_ms * 1000) for t, m in listener.messages
            if m.get_type() == "ATTITUDE_QUATERNION"]
    latency = np.array([t - sent[stamp] for t, stamp in outs])
    during = sorted(stamp for _, stamp in outs if outage[0] <= sent[stamp] <= outage[1])
    sent_during = [stamp for stamp, when in sent.items() if outage[0] <= when <= outage[1]]
    span_s = (max(sent_during) - min(sent_during)) * 1e-6
    assert len(during) >= span_s * 50 - 2, (len(during), span_s)
    assert np.max(np.diff(during)) <= 22_000  # no output skipped (20 ms of board time)
    assert np.percentile(latency, 99) < 0.05 and latency.max() < 0.25, latency.max()
    assert len(outs) > 0.9 * 11.0 * 50
    # Content of the per-estimator topic: frame and convention named, wall-clock time.
    est = sub.last("attitude/1/eskf")
    assert set(est) >= {"time_unix", "time_s", "time_boot_ms", "q", "euler_deg",
                        "gyro_bias_dps", "flags", "params", "source"}
    assert (est["frame"], est["body_frame"], est["q_order"]) == ("NED", "FRD", "wxyz")
    assert abs(est["time_unix"] - time.time()) < 30.0
    assert est["primary"] is True and est["estimator"] == "eskf"
    assert est["source"] == {"sysid": 1, "compid": 1, "message": "RAW_IMU", "imu": 0}
    assert abs(np.linalg.norm(est["q"]) - 1.0) < 1e-6
    assert set(est["euler_deg"]) == {"roll", "pitch", "yaw"}
    second = sub.last("attitude/1/quaternion-2")
    assert second["params"] == {"exact": False} and second["primary"] is False
    # the last status written while the emulator was still streaming (one written after
    # it stopped counts the samples of a shorter stretch)
    status = [p for when, t, p in sub.messages
              if t == "attitude/1/status" and when <= stream_done][-1]
    assert status["input_rate_hz"] > 100 and status["online"] is True
    assert status["sources"] == [est["source"]] and status["primary"] == est["source"]
    assert set(status["drops"]) >= {"duplicate", "reordered", "jump", "backwards"}
    assert set(status["latency_ms"]) >= {"p50", "p99"}
    assert status["connection"]["mqtt"]["connected"] is True
    assert status["link"]["lost"] == 0
    # A clean stop: the last status went out, the vehicle is offline (retained), and
    # the summary tells what the session did, not that MQTT is down.
    states = [p for _, t, p in sub.messages if t == "attitude/1/online"]
    assert states[0] == "online" and states[-1] == "offline", states
    text = summary(bridge)
    assert "mqtt ok" in text and "DOWN" not in text
    listener.close()
    vehicle.close()


@async_test
async def test_unreachable_broker_is_a_warning_at_start_and_not_every_attempt(caplog):
    port = free_tcp_port()  # nothing listens there
    caplog.set_level(logging.DEBUG, logger="bridge.publish.mqtt")
    async with running_bridge(estimators=["quaternion"], mqtt=f"mqtt://127.0.0.1:{port}"
                              ) as bridge:
        await asyncio.sleep(3.0)  # several attempts (backoff from 0.25 s)
        attempts = bridge.mqtt.stats.errors
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING
                and "unreachable" in r.getMessage()]
    assert attempts >= 3
    assert len(warnings) == 1 and f"127.0.0.1:{port}" in warnings[0].getMessage()
    assert "DOWN" not in summary(bridge) and "mqtt never connected" in summary(bridge)


@async_test
async def test_last_will_says_offline_when_the_bridge_dies(broker):
    """The bridge as a user runs it (a process), killed with SIGKILL: the broker
    publishes the vehicle's last will, retained, for anyone who subscribes later."""
    sub = Subscriber(broker.port)
    sub.start()
    port = free_udp_port()
    env = {**os.environ, "PYTHONPATH": str(REPO),
           "ATTITUDE_BRIDGE_MQTT": f"mqtt://127.0.0.1:{broker.port}"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.app.cli", "run", "--connect", f"udpin:127.0.0.1:{port}",
         "--estimator", "quaternion", "-q"], cwd=REPO, env=env,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        vehicle = MavSender(port)
        await vehicle.start()
        stream = asyncio.create_task(send_rotating(vehicle, euler_q(0, 0, 0),
                                                   np.radians([0, 0, 10.0]), 30.0))
        online = await wait_until(lambda: sub.last("attitude/1/online") == "online", 60.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait(5)
        offline = await wait_until(lambda: sub.last("attitude/1/online") == "offline", 5.0)
        stream.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await stream
        # A newcomer gets the retained state: offline.
        late = Subscriber(broker.port)
        late.start()
        retained = await wait_until(lambda: late.last("attitude/1/online") is not None, 5.0)
        await late.stop()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        await sub.stop()
    assert online, proc.stderr.read() if proc.stderr else ""
    assert offline
    assert retained and late.last("attitude/1/online") == "offline"
    vehicle.close()


def _offer_stream(publisher: EstimatePublisher, pipeline: Pipeline, last: dict,
                  times: np.ndarray) -> list[float]:
    """Feed board times through the pipeline and ``offer``; the board times published."""
    key = SourceKey(1, 1, 27, 0)
    sent = []
    for t in times:
        sample = ImuSample(key, float(t), round(t * 1e3), None, np.zeros(3),
                           np.array([0.0, 0.0, -9.80665]), None, time.perf_counter())
        before = publisher.mqtt.stats.queued
        publisher.offer(pipeline.process(sample), last)
        if publisher.mqtt.stats.queued > before:
            sent.append(float(t))
    return sent


@pytest.mark.parametrize("rate_hz", [0.05, 0.25, 0.4, 1.0, 10.0, 50.0])
def test_estimate_rate_is_honoured_at_any_rate_and_after_a_restart(rate_hz):
    """``--mqtt-rate 0.25`` used to publish every sample (a due time more than 2 s ahead
    was taken for a restarted timeline). Any rate is honoured; a board clock that goes
    back (a reboot) starts the count again at once."""
    pipeline = Pipeline([EstimatorSpec.parse("quaternion")], rate_hz=250.0)
    publisher = EstimatePublisher(MqttPublisher(MqttSettings("127.0.0.1")), pipeline,
                                  rate_hz)
    last: dict = {}
    span = max(40.0, 8.0 / rate_hz)
    times = 5.0 + np.arange(round(span * 250)) / 250.0  # 250 Hz of board time
    sent = _offer_stream(publisher, pipeline, last, times)
    expected = span * rate_hz
    assert expected - 1 <= len(sent) <= expected + 1, (len(sent), expected)
    assert np.all(np.diff(sent) >= 1.0 / rate_hz - 1e-6)
    # The vehicle rebooted: board time starts again near 0; published at once, then
    # at the rate again.
    again = _offer_stream(publisher, pipeline, last, 0.5 + np.arange(round(2.5 / rate_hz
                                                                          * 250)) / 250.0)
    assert again[0] == 0.5 and 2 <= len(again) <= 4, again[:5]
    assert np.all(np.diff(again) >= 1.0 / rate_hz - 1e-6)


@async_test
async def test_low_mqtt_rate_end_to_end(broker):
    """The finding as met: 0.25 Hz through a real broker gives about one message per
    estimator per 4 s of data, not one per sample."""
    sub = Subscriber(broker.port)
    sub.start()
    async with running_bridge(estimators=["quaternion"], mqtt_rate=0.25,
                              mqtt=f"mqtt://127.0.0.1:{broker.port}") as bridge:
        vehicle = MavSender(bridge.port)
        await vehicle.start()
        await send_rotating(vehicle, euler_q(0, 0, 0), np.radians([0, 0, 10.0]), 6.0)
        await wait_until(lambda: "attitude/1/status" in sub.topics(), timeout=5.0)
        await asyncio.sleep(0.5)
    await sub.stop()
    vehicle.close()
    count = sum(1 for _, t, _ in sub.messages if t == "attitude/1/quaternion")
    assert 1 <= count <= 2, count


@async_test
async def test_a_topic_the_client_refuses_is_logged_and_the_rest_still_goes_out(broker,
                                                                              caplog):
    """paho refuses some topics with ValueError (a wildcard, an empty topic): that used
    to end the publisher's task in silence, nothing more was published or counted."""
    caplog.set_level(logging.ERROR, logger="bridge.publish.mqtt")
    sub = Subscriber(broker.port)
    sub.start()
    publisher = MqttPublisher(MqttSettings("127.0.0.1", broker.port))
    task = asyncio.create_task(publisher.run())
    try:
        assert await wait_until(lambda: publisher.stats.connected, 5.0)
        await asyncio.sleep(0.3)  # the subscriber is in too
        publisher.publish("attitude/#", {"x": 1})
        publisher.publish("attitude/1/fine", {"x": 2})
        assert await wait_until(lambda: sub.last("attitude/1/fine") is not None, 5.0)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        await sub.stop()
    assert publisher.stats.errors >= 1 and publisher.stats.published == 1
    assert any("attitude/#" in r.getMessage() for r in caplog.records
               if r.levelno == logging.ERROR)
