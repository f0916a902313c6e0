"""The bridge service: links in, ingest, estimators, MAVLink and MQTT out, comparison.

Everything runs in one asyncio loop. The per-sample path (packet -> ingest -> all
estimators -> decimated MAVLink output) is synchronous inside the datagram callback,
so nothing queues between reading an IMU packet and sending its attitude. MQTT only
ever gets a non-blocking enqueue; comparison, status and the live table run in a 1 Hz
task off the sample path.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imu.boards import board_profile
from imu.rotations import rotation_matrix

from .codec import SigningConfig, load_signing_key
from .compare import References, compare_all
from .config import BridgeConfig
from .ingest import DROP_CAUSES, FLAG_CAUSES, IMU_MESSAGE_IDS, IMU_MESSAGE_NAMES, Ingest
from .links import Link, UdpLink, open_link, parse_url
from .mav import MAVLinkMessage, mavlink
from .mqtt import MqttPublisher, MqttSettings
from .output import AttitudeOutput, euler_zyx
from .pipeline import Estimate, Pipeline
from .sequence import SequenceTracker

log = logging.getLogger(__name__)

ID_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
ID_HIL_STATE_QUATERNION = mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION
ID_ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
ID_ATTITUDE_QUATERNION = mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
ID_COMMAND_ACK = mavlink.MAVLINK_MSG_ID_COMMAND_ACK

#: Ask again for the IMU stream after this long without samples, backing off to the max.
STREAM_SILENCE_S = 2.0
STREAM_RETRY_MAX_S = 30.0

#: Starts an emulator sending to the given UDP port; returns its awaitable run.
EmulatorStarter = Callable[[int], Awaitable[Any]]


@dataclass
class Vehicle:
    """What the bridge knows about one system id on the connection."""

    sysid: int
    autopilot_compid: int | None = None
    heartbeats: int = 0
    last_imu: float = 0.0  # monotonic time of the last accepted IMU sample
    stream_requests: int = 0
    next_request: float = 0.0
    request_backoff: float = STREAM_SILENCE_S
    command_acks: int = 0
    refs: References = field(default_factory=References)
    sequences: dict[int, SequenceTracker] = field(default_factory=dict)
    next_mqtt_t: dict[Any, float] = field(default_factory=dict)
    samples_at_last_status: int = 0


class BridgeService:
    """One bridge: ``await BridgeService(cfg).run(stop_event)`` returns the final status."""

    def __init__(self, cfg: BridgeConfig, emulator: EmulatorStarter | None = None) -> None:
        cfg.validate()
        self.cfg = cfg
        self.signing = None
        if cfg.signing_key:
            self.signing = SigningConfig(load_signing_key(cfg.signing_key),
                                         allow_unsigned=cfg.allow_unsigned)
        self.emulator = emulator
        connect = cfg.connect or "udpin:127.0.0.1:0"
        self.link: Link = open_link(parse_url(connect), self._on_message, self.signing)
        self.outs: list[Link] = [open_link(u, self._on_out_message, self.signing)
                                 for u in cfg.outs]
        self.ingest = Ingest(board_profile(cfg.board), rotation_matrix(cfg.rotation),
                             cfg.jump_s, cfg.reorder_s, cfg.sensor_calibration())
        self.pipeline = Pipeline(cfg.estimator_specs, cfg.imu_rate, cfg.window_s + 2.0,
                                 cfg.declination_deg or 0.0)
        self.output = AttitudeOutput([self.link, *self.outs], cfg.component_id, cfg.out_rate)
        self.mqtt: MqttPublisher | None = None
        if cfg.mqtt:
            self.mqtt = MqttPublisher(MqttSettings.from_url(
                cfg.mqtt, username=cfg.mqtt_username, password=cfg.mqtt_password,
                tls=cfg.mqtt_tls or None, ca_file=cfg.mqtt_ca, cert_file=cfg.mqtt_cert,
                key_file=cfg.mqtt_key, topic_prefix=cfg.mqtt_prefix))
        self.vehicles: dict[int, Vehicle] = {}
        self.started = time.monotonic()
        self.last_status: dict[int, dict[str, Any]] = {}
        self.on_status: Callable[[BridgeService], None] | None = None
        self.ready = asyncio.Event()
        self.imu_msg_id = IMU_MESSAGE_NAMES[cfg.imu_message]
        self._mqtt_period = 1.0 / cfg.mqtt_rate if cfg.mqtt_rate > 0 else 0.0
        self._last_status_wall = time.monotonic()

    # --- lifecycle ---------------------------------------------------------------------
    @property
    def port(self) -> int:
        """Local UDP port of the connection (useful with udpin:...:0)."""
        assert isinstance(self.link, UdpLink)
        return self.link.local_port

    async def run(self, stop: asyncio.Event | None = None) -> dict[int, dict[str, Any]]:
        """Run until ``stop`` is set or ``cfg.duration`` elapses; return the final status."""
        stop = stop or asyncio.Event()
        tasks: list[asyncio.Task] = []
        await self.link.start()
        for out in self.outs:
            await out.start()
        self.started = time.monotonic()
        if self.mqtt is not None:
            tasks.append(asyncio.create_task(self.mqtt.run(), name="mqtt"))
        tasks.append(asyncio.create_task(self._heartbeat_loop(), name="heartbeat"))
        tasks.append(asyncio.create_task(self._status_loop(), name="status"))
        if self.emulator is not None:
            tasks.append(asyncio.create_task(self._run_emulator(stop), name="emulator"))
        self.ready.set()
        try:
            if self.cfg.duration is not None:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), self.cfg.duration)
            else:
                await stop.wait()
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            self.publish_status()
            await self.link.close()
            for out in self.outs:
                await out.close()
        return self.last_status

    async def _run_emulator(self, stop: asyncio.Event) -> None:
        assert self.emulator is not None
        try:
            await self.emulator(self.port)
        except Exception:
            log.exception("built-in emulator failed")
        # A finite emulator run ends the demo shortly after, once the output is flushed.
        if self.cfg.duration is None:
            await asyncio.sleep(0.2)
            stop.set()

    async def _heartbeat_loop(self) -> None:
        while True:
            sysids = sorted(self.vehicles) or [self.cfg.system_id]
            self.output.send_heartbeat(sysids)
            await asyncio.sleep(1.0)

    async def _status_loop(self) -> None:
        while True:
            await asyncio.sleep(self.cfg.status_period_s)
            try:
                self._request_streams()
                self.publish_status()
            except Exception:
                log.exception("status update failed")

    # --- input -------------------------------------------------------------------------
    def _on_out_message(self, msg: MAVLinkMessage, link: Link) -> None:
        """Output links only deliver; what their peers say (heartbeats) is ignored."""

    def _vehicle(self, sysid: int) -> Vehicle:
        v = self.vehicles.get(sysid)
        if v is None:
            v = self.vehicles[sysid] = Vehicle(sysid)
            log.info("vehicle %d seen", sysid)
        return v

    def _on_message(self, msg: MAVLinkMessage, link: Link) -> None:
        arrival = time.perf_counter()
        header = msg.get_header()
        sysid, compid = header.srcSystem, header.srcComponent
        if compid == self.cfg.component_id:
            return  # our own output echoed back, or a peer bridge: not vehicle data
        msg_id = header.msgId
        vehicle = self._vehicle(sysid)
        tracker = vehicle.sequences.get(compid)
        if tracker is None:
            tracker = vehicle.sequences[compid] = SequenceTracker()
        tracker.observe(header.seq)
        if msg_id in IMU_MESSAGE_IDS:
            sample = self.ingest.handle(msg, arrival)
            if sample is None:
                return
            vehicle.last_imu = time.monotonic()
            vehicle.request_backoff = STREAM_SILENCE_S
            est = self.pipeline.process(sample)
            self.output.offer(est)
            if self.mqtt is not None:
                self._maybe_publish_estimates(vehicle, est)
        elif msg_id == ID_HEARTBEAT:
            vehicle.heartbeats += 1
            if msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and \
                    vehicle.autopilot_compid is None:
                vehicle.autopilot_compid = compid
                self._request_stream(vehicle)
        elif msg_id == ID_HIL_STATE_QUATERNION:
            vehicle.refs.add_truth(msg.time_usec * 1e-6, np.array(msg.attitude_quaternion))
        elif msg_id == ID_ATTITUDE_QUATERNION:
            vehicle.refs.add_vehicle_quaternion(
                msg.time_boot_ms * 1e-3, np.array([msg.q1, msg.q2, msg.q3, msg.q4]))
        elif msg_id == ID_ATTITUDE:
            vehicle.refs.add_vehicle_euler(msg.time_boot_ms * 1e-3, msg.roll, msg.pitch,
                                           msg.yaw)
        elif msg_id == ID_COMMAND_ACK:
            vehicle.command_acks += 1

    # --- IMU stream requests -------------------------------------------------------------
    def _request_stream(self, vehicle: Vehicle) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL for the configured IMU message and rate."""
        cmd = mavlink.MAVLink_command_long_message(
            vehicle.sysid, vehicle.autopilot_compid or 1,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            float(self.imu_msg_id), 1e6 / self.cfg.imu_rate, 0, 0, 0, 0, 0)
        self.link.send(cmd, vehicle.sysid, self.cfg.component_id)
        vehicle.stream_requests += 1
        vehicle.next_request = time.monotonic() + vehicle.request_backoff
        log.info("asked vehicle %d for %s at %g Hz", vehicle.sysid, self.cfg.imu_message,
                 self.cfg.imu_rate)

    def _request_streams(self) -> None:
        now = time.monotonic()
        for vehicle in self.vehicles.values():
            if vehicle.autopilot_compid is None or now < vehicle.next_request:
                continue
            if now - vehicle.last_imu > STREAM_SILENCE_S:
                self._request_stream(vehicle)
                vehicle.request_backoff = min(2.0 * vehicle.request_backoff,
                                              STREAM_RETRY_MAX_S)

    # --- MQTT ----------------------------------------------------------------------------
    def _maybe_publish_estimates(self, vehicle: Vehicle, est: Estimate) -> None:
        assert self.mqtt is not None
        due = vehicle.next_mqtt_t.get(est.key)
        if due is not None and due - 2.0 > est.t:
            due = None  # timeline restarted
        if due is not None and est.t < due:
            return
        vehicle.next_mqtt_t[est.key] = est.t + self._mqtt_period
        src = self.pipeline.sources[est.key]
        for label, estimator in zip(src.labels, src.estimators, strict=True):
            st = estimator.status
            q = st.q
            roll, pitch, yaw = euler_zyx(q)
            self.mqtt.publish(self.mqtt.topic(est.key.sysid, label), {
                "sysid": est.key.sysid, "compid": est.key.compid, "imu": est.key.imu,
                "estimator": label, "primary": label == self.pipeline.primary_label,
                "time_s": est.t, "time_boot_ms": est.time_boot_ms,
                "q": _finite_list(q),
                "euler_deg": {"roll": _finite(math.degrees(roll)),
                              "pitch": _finite(math.degrees(pitch)),
                              "yaw": _finite(math.degrees(yaw))},
                "bias_rad_s": _finite_list(st.bias),
                "flags": {"initialising": st.initialising, "acc_rejected": st.acc_rejected,
                          "mag_rejected": st.mag_rejected},
            })

    # --- status --------------------------------------------------------------------------
    def vehicle_status(self, vehicle: Vehicle, elapsed: float) -> dict[str, Any]:
        """Rates, drops by cause, latency and the live comparison of one vehicle."""
        sources = {k: s for k, s in self.ingest.sources.items() if k.sysid == vehicle.sysid}
        samples = sum(s.accepted for s in sources.values())
        rate = (samples - vehicle.samples_at_last_status) / elapsed if elapsed > 0 else 0.0
        vehicle.samples_at_last_status = samples
        drops = dict.fromkeys(DROP_CAUSES, 0)
        flags = dict.fromkeys(FLAG_CAUSES, 0)
        for s in sources.values():
            for cause in DROP_CAUSES:
                drops[cause] += s.counts[cause]
            for cause in FLAG_CAUSES:
                flags[cause] += s.counts[cause]
        link = {"lost": sum(t.lost for t in vehicle.sequences.values()),
                "late": sum(t.late for t in vehicle.sequences.values()),
                "repeated": sum(t.duplicate for t in vehicle.sequences.values())}
        compare: dict[str, Any] = {}
        counters: dict[str, Any] = {}
        t_last = None
        for key, src in self.pipeline.sources.items():
            if key.sysid != vehicle.sysid:
                continue
            if src.last_sample is not None:
                t_last = src.last_sample.t
            for label, est in zip(src.labels, src.estimators, strict=True):
                counters[label] = est.counters.__dict__
            for ref, by_label in compare_all(src.history, vehicle.refs,
                                             self.cfg.window_s).items():
                compare.setdefault(ref, {}).update(
                    {label: c.to_dict() for label, c in by_label.items()})
            break  # the first IMU of the vehicle is the one compared
        status = {
            "sysid": vehicle.sysid, "time_s": t_last, "samples": samples,
            "input_rate_hz": round(rate, 1), "sources": [list(k) for k in sources],
            "drops": drops, "flags": flags, "link": link,
            "sent": self.output.sent.get(vehicle.sysid, 0),
            "latency_ms": self.output.latency_percentiles_ms(),
            "estimator_counters": counters, "compare": compare,
            "stream_requests": vehicle.stream_requests,
        }
        return status

    def link_status(self) -> dict[str, Any]:
        c = self.link.codec.stats
        s = {"bytes_in": c.bytes_in, "messages_in": c.messages_in, "bad_crc": c.bad_crc,
             "bad_frame": c.bad_frame, "unsigned_rejected": c.unsigned_rejected,
             "unknown_message": c.unknown_message, "truncated": c.truncated,
             "send_dropped": self.link.stats.send_dropped,
             "send_errors": self.link.stats.send_errors,
             "reconnects": self.link.stats.reconnects}
        if self.mqtt is not None:
            m = self.mqtt.stats
            s["mqtt"] = {"connected": m.connected, "published": m.published,
                         "dropped": m.dropped, "connects": m.connects}
        return s

    def publish_status(self) -> None:
        now = time.monotonic()
        elapsed = now - self._last_status_wall
        self._last_status_wall = now
        link = self.link_status()
        for vehicle in list(self.vehicles.values()):
            status = self.vehicle_status(vehicle, elapsed)
            status["connection"] = link
            self.last_status[vehicle.sysid] = status
            if self.mqtt is not None:
                self.mqtt.publish(self.mqtt.topic(vehicle.sysid, "status"), status)
        if self.on_status is not None:
            self.on_status(self)


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _finite_list(v: np.ndarray) -> list[float | None]:
    return [_finite(float(x)) for x in v]
