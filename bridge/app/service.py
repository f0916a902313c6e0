"""The bridge service: links in, ingest, estimators, MAVLink and MQTT out, comparison.

Everything runs in one asyncio loop. The per-sample path (packet -> ingest -> all
estimators -> decimated MAVLink output, :mod:`bridge.app.samples`) is synchronous inside
the datagram callback, so nothing queues between reading an IMU packet and sending its
attitude. MQTT only ever gets a non-blocking enqueue; stream requests, eviction, the
stream watch, status and the live table run in a task off the sample path.

The service only builds the parts and runs their loops; each part owns its state:

* :class:`~bridge.app.registry.VehicleRegistry` — who is served (admission, eviction);
* :class:`~bridge.app.routing.MessageRouter` — every parsed message to its part;
* :class:`~bridge.app.samples.SampleFlow` — an IMU message to an attitude on the wire;
* :class:`~bridge.app.requests.StreamRequester` — what is asked of the autopilot;
* :class:`~bridge.app.watch.StreamWatch` — a stream settled, lost, back;
* :class:`~bridge.app.status.StatusReporter` — the report (MQTT, status file, table);
* :class:`~bridge.publish.presence.MqttPresence` and
  :class:`~bridge.publish.estimates.EstimatePublisher` — MQTT.

Hostile input is refused as early as it can be and counted where it was refused: the
UDP gate (:mod:`bridge.wire.admission`) before parsing, the codec (CRC, signing), the
registry and router (unserved system ids, non-primary IMUs, references from other
senders), ingest (clock, plausibility). Per-vehicle state exists only for served
vehicles and is dropped after ``evict_after_s`` of silence.

The service talks without the live table: what it learns and what goes wrong is logged
(INFO: a vehicle served, its autopilot and the IMU stream negotiated, a link regained;
WARNING: a gap or reboot restarting the estimate, a vehicle gone silent, a stream
refused or below its rate, an unreachable MQTT broker).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

from imu.boards import board_profile
from imu.rotations import rotation_matrix

from ..estimate.pipeline import Pipeline
from ..publish.estimates import EstimatePublisher
from ..publish.mqtt import MqttPublisher, MqttSettings, orphan_options
from ..publish.output import AttitudeOutput
from ..publish.presence import MqttPresence
from ..publish.record import TlogRecorder
from ..vehicle.ingest import Ingest, Limits
from ..vehicle.negotiate import parse_forced
from ..vehicle.vehicle import CONFIGURED, Vehicle
from ..wire.admission import Admission
from ..wire.codec import SigningConfig, load_signing_key
from ..wire.links import Link, LinkOptions, UdpLink, open_link, parse_url
from ..wire.mav import MAVLinkMessage
from .config import BridgeConfig
from .lateness import LatenessWatch
from .registry import VehicleRegistry
from .requests import StreamRequester
from .routing import MessageRouter
from .samples import SampleFlow
from .status import StatusReporter
from .warmup import Progress, interruptible, warm_up_all
from .watch import StreamWatch

log = logging.getLogger(__name__)

#: Starts an emulator sending to the given UDP port; returns its awaitable run.
EmulatorStarter = Callable[[int], Awaitable[Any]]
#: At stop, MQTT gets this long to deliver the last status and the offline states.
MQTT_FLUSH_S = 1.0


class BridgeService:
    """One bridge: ``await BridgeService(cfg).run(stop_event)`` returns the final status."""

    def __init__(self, cfg: BridgeConfig, emulator: EmulatorStarter | None = None) -> None:
        cfg.validate()
        self.cfg = cfg
        self.emulator = emulator
        signing = None
        if cfg.signing_key:
            signing = SigningConfig(load_signing_key(cfg.signing_key),
                                    allow_unsigned=cfg.allow_unsigned)
        options = LinkOptions(max_peers=cfg.max_peers, peer_timeout_s=cfg.peer_timeout_s,
                              idle_timeout_s=cfg.idle_timeout_s)
        self.link: Link = open_link(parse_url(cfg.connect or "udpin:127.0.0.1:0"),
                                    self._on_message, signing, options)
        # The built-in emulator is trusted and may run faster than real time (--fast).
        self.admission = Admission(None if emulator is not None else cfg.max_source_rate)
        self.link.gate = self.admission
        if isinstance(self.link, UdpLink):
            self.admission.on_flood = self.link.kernel_filter
        # output links only deliver; what their peers say (heartbeats) is ignored
        self.outs: list[Link] = [open_link(u, None, signing, options) for u in cfg.outs]
        for out in self.outs:
            out.gate = Admission(cfg.max_source_rate)
        self.ingest = Ingest(board_profile(cfg.board or "gy86"), rotation_matrix(cfg.rotation),
                             cfg.jump_s, cfg.reorder_s, cfg.sensor_calibration(),
                             Limits(cfg.gyro_range_dps, cfg.accel_range_g,
                                    cfg.mag_range_gauss),
                             cfg.clock_resync_s, cfg.reinit_gap_s)
        self.pipeline = Pipeline(cfg.estimator_specs, cfg.imu_rate, cfg.window_s + 2.0,
                                 cfg.declination_deg or 0.0, cfg.reinit_settle_s)
        self.output = AttitudeOutput([self.link, *self.outs], cfg.component_id, cfg.out_rate)
        self.mqtt: MqttPublisher | None = None
        self.presence: MqttPresence | None = None
        estimates = None
        if cfg.mqtt:
            self.mqtt = MqttPublisher(MqttSettings.from_url(
                cfg.mqtt, username=cfg.mqtt_username, password=cfg.mqtt_password,
                tls=cfg.mqtt_tls or None, ca_file=cfg.mqtt_ca, cert_file=cfg.mqtt_cert,
                key_file=cfg.mqtt_key, topic_prefix=cfg.mqtt_prefix))
            self.presence = MqttPresence(self.mqtt)
            estimates = EstimatePublisher(self.mqtt, self.pipeline, cfg.mqtt_rate)
        elif orphans := orphan_options(cfg):
            log.warning("%s given without --mqtt: ignored, nothing is published over MQTT",
                        ", ".join(orphans))
        self.samples = SampleFlow(cfg, self.ingest, self.pipeline, self.output, estimates)
        self.registry = VehicleRegistry(cfg, self.admission, parse_forced(cfg.imu_message),
                                        self.samples.forget_source)
        for sysid in cfg.vehicles:
            self.registry.add(sysid, CONFIGURED)
        self.requester = StreamRequester(cfg.component_id)
        self.router = MessageRouter(cfg, self.registry, self.samples, self.requester,
                                    self.admission)
        self.watch = StreamWatch(self.ingest, cfg.source_timeout_s)
        self.lateness = LatenessWatch()
        self.reporter = StatusReporter(cfg, self.link, self.admission, self.registry,
                                       self.ingest, self.pipeline, self.output, self.watch,
                                       self.mqtt)
        self.recorder: TlogRecorder | None = None
        self.web = self._web_view() if cfg.web is not None else None
        self.reporter.web = self.web
        #: Told each estimator's name before and its seconds after it is compiled.
        self.on_progress: Progress | None = None
        #: Called after every status report (the live table).
        self.on_status: Callable[[BridgeService], None] | None = None
        self.ready = asyncio.Event()

    def _web_view(self) -> Any:
        """The live web view (bokeh, from the report extra, serves its drawing code)."""
        try:
            from ..publish.web import WebView, parse_web
        except ImportError as exc:
            raise ValueError(f"--web needs {exc.name}: pip install "
                             "'attitude-bridge[report]'") from None
        from ..publish.snapshot import take

        host, port = parse_web(self.cfg.web)
        return WebView(host, port, lambda: take(self.registry.vehicles, self.pipeline,
                                                self.reporter.last))

    # --- what the parts know, for the table, the CLI and the tests -----------------------
    @property
    def port(self) -> int:
        """Local UDP port of the connection (useful with udpin:...:0)."""
        assert isinstance(self.link, UdpLink)
        return self.link.local_port

    @property
    def vehicles(self) -> dict[int, Vehicle]:
        return self.registry.vehicles

    @property
    def refused(self) -> dict[str, int]:
        return self.registry.refused

    @property
    def last_status(self) -> dict[int, dict[str, Any]]:
        return self.reporter.last

    @property
    def started(self) -> float:
        return self.reporter.started

    @property
    def topics(self) -> dict[str, str]:
        return self.reporter.topics

    def link_status(self) -> dict[str, Any]:
        return self.reporter.link_status()

    def publish_status(self) -> None:
        """Report now (MQTT, status file, the table)."""
        self.reporter.publish()
        if self.on_status is not None:
            self.on_status(self)

    def _on_message(self, msg: MAVLinkMessage, link: Link) -> None:
        self.router.on_message(msg, link)

    # --- lifecycle ---------------------------------------------------------------------
    async def run(self, stop: asyncio.Event | None = None) -> dict[int, dict[str, Any]]:
        """Run until ``stop`` is set or ``cfg.duration`` elapses; return the final status.

        The links open first (a port in use or a host that does not resolve fails at
        once, as :class:`bridge.wire.links.LinkError`), then the estimators are compiled
        (``on_progress`` hears about each), then the service starts.
        """
        stop = stop or asyncio.Event()
        tasks: list[asyncio.Task] = []
        mqtt_task = None
        try:
            if self.cfg.record:
                self.recorder = self.reporter.recorder = TlogRecorder(self.cfg.record)
                self.link.tap = self.recorder.record
            await self.link.start()
            for out in self.outs:
                await out.start()
            if self.web is not None:
                self.web.start()  # before the warm-up: the page is there at once
            with interruptible():  # the loop is blocked: its signal handlers wait
                warm_up_all(self.pipeline.specs, self.on_progress)
            self.reporter.restart_clock()
            if self.mqtt is not None:
                mqtt_task = asyncio.create_task(self.mqtt.run(), name="mqtt")
            tasks.append(asyncio.create_task(self._heartbeat_loop(), name="heartbeat"))
            tasks.append(asyncio.create_task(self._status_loop(), name="status"))
            if self.web is not None:
                tasks.append(asyncio.create_task(self._web_loop(), name="web"))
            if self.emulator is not None:
                tasks.append(asyncio.create_task(self._run_emulator(stop), name="emulator"))
            self.ready.set()
            if self.cfg.duration is not None:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), self.cfg.duration)
            else:
                await stop.wait()
        finally:
            await _cancel(tasks)
            if self.ready.is_set():
                self.publish_status()  # the last status, everywhere, every vehicle offline
                if self.presence is not None:
                    self.presence.all_offline()
                await self._flush_mqtt()
            await self._stop_mqtt(mqtt_task)
            if self.web is not None:
                self.web.close()
            await self.link.close()
            for out in self.outs:
                await out.close()
            if self.recorder is not None:
                self.recorder.close()
        return self.last_status

    def _mqtt_publishers(self) -> list[MqttPublisher]:
        if self.mqtt is None or self.presence is None:
            return []
        return [self.mqtt, *self.presence.publishers.values()]

    async def _flush_mqtt(self) -> None:
        """Give MQTT a moment to deliver what is queued (the last status, offline)."""
        publishers = self._mqtt_publishers()
        if publishers:
            await asyncio.gather(*(p.flush(MQTT_FLUSH_S) for p in publishers))

    async def _stop_mqtt(self, mqtt_task: asyncio.Task | None) -> None:
        presence_tasks = self.presence.tasks if self.presence is not None else []
        await _cancel([t for t in (mqtt_task, *presence_tasks) if t is not None])
        for publisher in self._mqtt_publishers():
            publisher.stats.stopped = True

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
                self._periodic(time.monotonic())
            except Exception:
                log.exception("status update failed")

    async def _web_loop(self) -> None:
        from ..publish.web import FRAME_HZ

        assert self.web is not None
        loop = asyncio.get_running_loop()
        period = 1.0 / FRAME_HZ
        due = loop.time()
        while True:
            due += period  # on schedule on average, a late frame does not cost one
            if loop.time() - due > 1.0:  # starved for a second: start the schedule again
                due = loop.time()
            await asyncio.sleep(max(0.0, due - loop.time()))
            try:
                self.web.tick()
            except Exception:
                log.exception("web view update failed")

    def _periodic(self, now: float) -> None:
        """Once per status period: retries, eviction, the stream watch, presence, the
        report."""
        vehicles = self.registry.vehicles
        self.requester.retry(list(vehicles.values()), now)
        self.registry.evict(now)
        self.watch.check(vehicles, now)
        self.lateness.check(self.output.take_lateness(), self.cfg.status_period_s, now)
        if self.presence is not None:
            for sysid, vehicle in vehicles.items():
                if vehicle.last_imu != 0.0:
                    self.presence.set_online(sysid, sysid not in self.watch.silent_since)
            self.presence.keep_only(set(vehicles))
        self.publish_status()


async def _cancel(tasks: list[asyncio.Task]) -> None:
    for task in tasks:
        task.cancel()
    for task in tasks:
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
