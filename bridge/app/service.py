"""The bridge service: links in, ingest, estimators, MAVLink and MQTT out, comparison.

Everything runs in one asyncio loop. The per-sample path (packet -> ingest -> all
estimators -> decimated MAVLink output) is synchronous inside the datagram callback,
so nothing queues between reading an IMU packet and sending its attitude. MQTT only
ever gets a non-blocking enqueue; comparison, status and the live table run in a 1 Hz
task off the sample path.

Hostile input is refused as early as it can be and counted where it was refused: the
UDP gate (:mod:`bridge.wire.admission`) before parsing, the codec (CRC, signing), the
vehicle table (:mod:`bridge.vehicle.vehicle`: unserved system ids, non-primary IMUs, references
from other senders), ingest (clock, plausibility). Per-vehicle state exists only for
served vehicles and is dropped after ``evict_after_s`` of silence.

The service talks without the live table: what it learns and what goes wrong is logged
(INFO: a vehicle served, its autopilot and the IMU stream negotiated, a link regained;
WARNING: a gap or reboot restarting the estimate, a vehicle gone silent, a stream
refused or below its rate, an unreachable MQTT broker). On MQTT each served vehicle
has a retained ``<prefix>/<sysid>/online``: ``online`` while its attitude is being
published, ``offline`` when its data stopped or the bridge stopped, and — as the last
will of a connection of its own — when the bridge died.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from estimators import quat as Q
from imu.boards import board_profile
from imu.flight_state import state_name
from imu.rotations import rotation_matrix

from ..estimate.compare import compare_all, vehicle_against_truth
from ..estimate.pipeline import Estimate, Pipeline
from ..publish.mqtt import MqttPublisher, MqttSettings, Outgoing
from ..publish.output import AttitudeOutput, euler_zyx
from ..publish.record import TlogRecorder
from ..vehicle.aiding import VELOCITY_MESSAGE_IDS, VelocityAiding
from ..vehicle.declination import Declination
from ..vehicle.ingest import (
    DROP_CAUSES,
    FLAG_CAUSES,
    IMU_MESSAGE_IDS,
    Ingest,
    Limits,
)
from ..vehicle.model import describe, model_of, type_name
from ..vehicle.negotiate import Request, StreamNegotiation, board_for, parse_forced
from ..vehicle.vehicle import CONFIGURED, HEARTBEAT, PROVISIONAL, Vehicle
from ..wire.admission import Admission
from ..wire.codec import SigningConfig, load_signing_key
from ..wire.links import Link, LinkOptions, UdpLink, open_link, parse_url
from ..wire.mav import MAVLinkMessage, mavlink
from .config import BridgeConfig
from .health import write_status_file
from .warmup import Progress, warm_up_all

log = logging.getLogger(__name__)

ID_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
ID_HIL_STATE_QUATERNION = mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION
ID_SIMSTATE = mavlink.MAVLINK_MSG_ID_SIMSTATE
TRUTH_MESSAGE_IDS = (ID_HIL_STATE_QUATERNION, ID_SIMSTATE)
ID_ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
ID_ATTITUDE_QUATERNION = mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
ID_COMMAND_ACK = mavlink.MAVLINK_MSG_ID_COMMAND_ACK
ID_SYSTEM_TIME = mavlink.MAVLINK_MSG_ID_SYSTEM_TIME
ID_EXTENDED_SYS_STATE = mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
FLIGHT_SWITCHES_SHOWN = 10  # the status report lists this many of the latest switches
ID_RAW_IMU = mavlink.MAVLINK_MSG_ID_RAW_IMU
ID_PARAM_VALUE = mavlink.MAVLINK_MSG_ID_PARAM_VALUE
ID_GLOBAL_POSITION_INT = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
ID_GPS_RAW_INT = mavlink.MAVLINK_MSG_ID_GPS_RAW_INT

#: Ask again for the IMU stream after this long without samples, backing off to the max;
#: only while the vehicle's autopilot is heard (its heartbeat within HEARTBEAT_ALIVE_S).
STREAM_SILENCE_S = 2.0
STREAM_RETRY_MAX_S = 30.0
HEARTBEAT_ALIVE_S = 5.0
#: Vehicle types whose heartbeat does not make them a vehicle to serve.
NOT_VEHICLES = frozenset((mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER))

#: Starts an emulator sending to the given UDP port; returns its awaitable run.
EmulatorStarter = Callable[[int], Awaitable[Any]]
#: At stop, MQTT gets this long to deliver the last status and the offline states.
MQTT_FLUSH_S = 1.0
#: What the JSON on MQTT and in the status file says about its quaternions.
FRAME = {"frame": "NED", "body_frame": "FRD", "q_order": "wxyz", "north": "true"}


def estimator_topics(labels: list[str], names: list[str]) -> dict[str, str]:
    """Estimator label -> topic name: the estimator's name (``mahony``), with ``-2``,
    ``-3``... for further instances of the same estimator (their parameters are in the
    payload; topic names stay stable when a parameter is tuned)."""
    seen: dict[str, int] = {}
    out = {}
    for label, name in zip(labels, names, strict=True):
        seen[name] = seen.get(name, 0) + 1
        out[label] = name if seen[name] == 1 else f"{name}-{seen[name]}"
    return out


def is_autopilot(msg: MAVLinkMessage) -> bool:
    """A HEARTBEAT from a flight controller (not a GCS, companion or peer bridge)."""
    return msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type not in NOT_VEHICLES


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
        options = LinkOptions(max_peers=cfg.max_peers, peer_timeout_s=cfg.peer_timeout_s,
                              idle_timeout_s=cfg.idle_timeout_s)
        self.link: Link = open_link(parse_url(connect), self._on_message, self.signing,
                                    options)
        # The built-in emulator is trusted and may run faster than real time (--fast).
        self.admission = Admission(None if emulator is not None else cfg.max_source_rate)
        self.link.gate = self.admission
        if isinstance(self.link, UdpLink):
            self.admission.on_flood = self.link.kernel_filter
        self.outs: list[Link] = [open_link(u, self._on_out_message, self.signing, options)
                                 for u in cfg.outs]
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
        if cfg.mqtt:
            self.mqtt = MqttPublisher(MqttSettings.from_url(
                cfg.mqtt, username=cfg.mqtt_username, password=cfg.mqtt_password,
                tls=cfg.mqtt_tls or None, ca_file=cfg.mqtt_ca, cert_file=cfg.mqtt_cert,
                key_file=cfg.mqtt_key, topic_prefix=cfg.mqtt_prefix))
        #: Per served vehicle: a connection holding its online state and last will.
        self.presence: dict[int, MqttPublisher] = {}
        self._presence_tasks: list[asyncio.Task] = []
        specs = self.pipeline.specs
        self.topics = estimator_topics([s.label for s in specs], [s.name for s in specs])
        self._user_params = {s.label: s.user_params() for s in specs}
        self.recorder: TlogRecorder | None = None
        #: Told each estimator's name before and its seconds after it is compiled.
        self.on_progress: Progress | None = None
        self._silent_since: dict[int, float] = {}  # vehicles whose IMU data stopped
        self._streams_told: dict[int, str] = {}  # IMU stream last logged per vehicle
        self.forced_imu = parse_forced(cfg.imu_message)
        self.vehicles: dict[int, Vehicle] = {}
        for sysid in cfg.vehicles:
            self._add_vehicle(sysid, CONFIGURED)
        self.truth = cfg.truth
        #: Messages refused by the service (after parsing), by cause.
        self.refused = {"not_vehicle": 0, "vehicles_replaced": 0, "evicted": 0}
        self.started = time.monotonic()
        self.last_status: dict[int, dict[str, Any]] = {}
        self.on_status: Callable[[BridgeService], None] | None = None
        self.ready = asyncio.Event()
        self._mqtt_period = 1.0 / cfg.mqtt_rate if cfg.mqtt_rate > 0 else 0.0
        self._last_status_wall = time.monotonic()

    # --- lifecycle ---------------------------------------------------------------------
    @property
    def port(self) -> int:
        """Local UDP port of the connection (useful with udpin:...:0)."""
        assert isinstance(self.link, UdpLink)
        return self.link.local_port

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
                self.recorder = TlogRecorder(self.cfg.record)
                self.link.tap = self.recorder.record
            await self.link.start()
            for out in self.outs:
                await out.start()
            warm_up_all(self.pipeline.specs, self.on_progress)
            self.started = time.monotonic()
            self._last_status_wall = self.started
            if self.mqtt is not None:
                mqtt_task = asyncio.create_task(self.mqtt.run(), name="mqtt")
            tasks.append(asyncio.create_task(self._heartbeat_loop(), name="heartbeat"))
            tasks.append(asyncio.create_task(self._status_loop(), name="status"))
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
                self._final_status()
                await self._flush_mqtt()
            await _cancel([t for t in (mqtt_task, *self._presence_tasks) if t is not None])
            for publisher in (self.mqtt, *self.presence.values()):
                if publisher is not None:
                    publisher.stats.stopped = True
            await self.link.close()
            for out in self.outs:
                await out.close()
            if self.recorder is not None:
                self.recorder.close()
        return self.last_status

    def _final_status(self) -> None:
        """The last status, everywhere, with every vehicle offline (the bridge stops)."""
        self.publish_status()
        for sysid, presence in self.presence.items():
            presence.set_retained(presence.topic(sysid, "online"), "offline")

    async def _flush_mqtt(self) -> None:
        """Give MQTT a moment to deliver what is queued (the last status, offline)."""
        publishers = [p for p in (self.mqtt, *self.presence.values()) if p is not None]
        if publishers:
            await asyncio.gather(*(p.flush(MQTT_FLUSH_S) for p in publishers))

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
                self._evict()
                self._watch_streams()
                self.publish_status()
            except Exception:
                log.exception("status update failed")

    def _watch_streams(self) -> None:
        """Say when a vehicle's IMU data stops and when it comes back, and keep its
        MQTT online state to match."""
        now = time.monotonic()
        timeout = self.cfg.source_timeout_s
        for sysid, vehicle in self.vehicles.items():
            if vehicle.last_imu == 0.0:
                continue  # no data yet: nothing to lose
            stream = vehicle.negotiation.status()
            if stream["achieved_hz"] is not None and \
                    self._streams_told.get(sysid) != stream["message"]:
                self._streams_told[sysid] = stream["message"]
                board = (f", board {self.ingest.board_of(sysid).name}"
                         if stream["message"] == "RAW_IMU" else "")  # SI units otherwise
                log.info("vehicle %d: estimating from %s at %.0f Hz, jitter %.2f ms (asked "
                         "%.4g Hz: %s)%s", sysid, stream["message"], stream["achieved_hz"],
                         stream["jitter_ms"], stream["asked_hz"], stream["state"], board)
            silent = now - vehicle.last_imu
            since = self._silent_since.get(sysid)
            if silent >= timeout and since is None:
                self._silent_since[sysid] = vehicle.last_imu
                log.warning("vehicle %d: no IMU data for %.0f s (link lost, or the vehicle "
                            "stopped sending)", sysid, silent)
            elif silent < timeout and since is not None:
                del self._silent_since[sysid]
                log.info("vehicle %d: IMU data again after %.1f s", sysid,
                         vehicle.last_imu - since)
            if self.mqtt is not None:
                online = sysid not in self._silent_since
                presence = self._presence(sysid)
                presence.set_retained(presence.topic(sysid, "online"),
                                      "online" if online else "offline")
        for sysid, presence in self.presence.items():
            if sysid not in self.vehicles:  # replaced (a provisional vehicle)
                presence.set_retained(presence.topic(sysid, "online"), "offline")

    def _presence(self, sysid: int) -> MqttPublisher:
        """The vehicle's own MQTT connection: its online state, and "offline" as the
        last will (one will per connection, so one connection per vehicle)."""
        presence = self.presence.get(sysid)
        if presence is None:
            assert self.mqtt is not None
            settings = dataclasses.replace(self.mqtt.settings, client_id=None, queue_size=16)
            topic = self.mqtt.topic(sysid, "online")
            presence = self.presence[sysid] = MqttPublisher(
                settings, will=Outgoing(topic, "offline", True, 1), quiet=True)
            self._presence_tasks.append(asyncio.create_task(
                presence.run(), name=f"mqtt online {sysid}"))
        return presence

    # --- who is served -----------------------------------------------------------------
    def _add_vehicle(self, sysid: int, how: str) -> Vehicle:
        v = self.vehicles[sysid] = Vehicle(
            sysid, admitted_by=how, request_backoff=STREAM_SILENCE_S,
            aiding=VelocityAiding(self.cfg.aid_max_age_s),
            negotiation=StreamNegotiation(sysid, self.cfg.imu_rate, self.forced_imu,
                                          self.cfg.aiding),
            declination=Declination(sysid, self.cfg.declination_deg))
        self.admission.admit_vehicle(sysid)
        log.info("vehicle %d admitted (%s)", sysid, how)
        return v

    def _drop_state(self, vehicle: Vehicle) -> None:
        """Forget a vehicle's estimators, clock and references (kept: who it is)."""
        if vehicle.primary is not None:
            self.ingest.forget(vehicle.primary)
            self.pipeline.forget(vehicle.primary)
            self.output.forget(vehicle.primary)
        vehicle.primary = None
        vehicle.refs = None
        vehicle.sequences.clear()
        vehicle.next_mqtt_t.clear()

    def _admit(self, sysid: int, msg: MAVLinkMessage, msg_id: int) -> Vehicle | None:
        """A vehicle for a system id not served yet, if it may become one (learning)."""
        if self.cfg.vehicles:
            return None
        if msg_id == ID_HEARTBEAT and is_autopilot(msg):
            current = list(self.vehicles.values())
            if current and current[0].admitted_by != PROVISIONAL:
                return None
            for old in current:  # a bare IMU stream gives way to a real autopilot
                self._drop_state(old)
                del self.vehicles[old.sysid]
                self.admission.forget_vehicle(old.sysid)
                self.refused["vehicles_replaced"] += 1
            return self._add_vehicle(sysid, HEARTBEAT)
        if msg_id in IMU_MESSAGE_IDS and not self.vehicles:
            return self._add_vehicle(sysid, PROVISIONAL)
        return None

    def _evict(self) -> None:
        """Drop the heavy state of vehicles silent for evict_after_s."""
        now = time.monotonic()
        for vehicle in self.vehicles.values():
            has_state = vehicle.primary is not None or vehicle.refs is not None
            if has_state and now - vehicle.last_heard > self.cfg.evict_after_s:
                self._drop_state(vehicle)
                self.refused["evicted"] += 1

    # --- input -------------------------------------------------------------------------
    def _on_out_message(self, msg: MAVLinkMessage, link: Link) -> None:
        """Output links only deliver; what their peers say (heartbeats) is ignored."""

    def _on_message(self, msg: MAVLinkMessage, link: Link) -> None:
        arrival = time.perf_counter()
        header = msg.get_header()
        sysid, compid = header.srcSystem, header.srcComponent
        if compid == self.cfg.component_id:
            return  # our own output echoed back, or a peer bridge: not vehicle data
        msg_id = header.msgId
        vehicle = self.vehicles.get(sysid)
        if vehicle is None:
            vehicle = self._admit(sysid, msg, msg_id)
            if vehicle is None:
                self.refused["not_vehicle"] += 1
                return
        now = time.monotonic()
        vehicle.last_heard = now
        vehicle.observe_sequence(compid, header.seq)
        if msg_id in IMU_MESSAGE_IDS:
            self._imu(vehicle, msg, link, arrival, now)
        elif msg_id == ID_HEARTBEAT:
            self._heartbeat(vehicle, msg, compid, link, now)
        elif msg_id in TRUTH_MESSAGE_IDS:
            self._truth(vehicle, msg, sysid, compid, arrival)
        elif msg_id in (ID_ATTITUDE_QUATERNION, ID_ATTITUDE):
            if compid != vehicle.reference_compid():
                vehicle.refused["refs_refused"] += 1
            elif msg_id == ID_ATTITUDE_QUATERNION:
                vehicle.references().add_vehicle_quaternion(
                    msg.time_boot_ms * 1e-3, np.array([msg.q1, msg.q2, msg.q3, msg.q4]))
            else:
                vehicle.references().add_vehicle_euler(msg.time_boot_ms * 1e-3, msg.roll,
                                                       msg.pitch, msg.yaw)
        elif msg_id in VELOCITY_MESSAGE_IDS:
            if compid != vehicle.reference_compid():
                vehicle.refused["other_component"] += 1
                return
            if self.cfg.aiding:
                vehicle.aiding.offer(msg, msg_id, arrival)
            if msg_id == ID_GLOBAL_POSITION_INT or (
                    msg_id == ID_GPS_RAW_INT and msg.fix_type >= mavlink.GPS_FIX_TYPE_2D_FIX):
                self._position(vehicle, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
        elif msg_id == ID_PARAM_VALUE:
            if compid == vehicle.autopilot_compid:
                name = msg.param_id if isinstance(msg.param_id, str) else \
                    msg.param_id.decode(errors="replace")
                if vehicle.declination.on_param(name.rstrip("\x00"), float(msg.param_value)):
                    self.pipeline.configure(vehicle.sysid,
                                            declination_rad=vehicle.declination.rad)
        elif msg_id == ID_SYSTEM_TIME:
            if compid == vehicle.reference_compid():
                vehicle.boot_hint = (msg.time_boot_ms * 1e-3, arrival)
        elif msg_id == ID_COMMAND_ACK:
            self._command_ack(vehicle, msg, compid)
        elif msg_id == ID_EXTENDED_SYS_STATE:
            if compid != vehicle.autopilot_compid:
                vehicle.refused["other_component"] += 1
                return
            vehicle.flight.on_extended_sys_state(now, msg.landed_state)
            self._flight_state(vehicle)

    def _truth(self, vehicle: Vehicle, msg: MAVLinkMessage, sysid: int, compid: int,
               arrival: float) -> None:
        """A simulator's true attitude: HIL_STATE_QUATERNION (the emulator stamps it with
        the board time, PX4 SIH with 0) or ArduPilot SITL's SIMSTATE (no stamp): an
        unstamped one is placed on the board clock by its arrival."""
        if (sysid, compid) != (self.truth or (sysid, vehicle.reference_compid())):
            vehicle.refused["refs_refused"] += 1
            return
        if msg.get_msgId() == ID_SIMSTATE:
            stamp, q = 0, Q.from_euler(msg.roll, msg.pitch, msg.yaw)
        else:
            stamp, q = msg.time_usec, np.array(msg.attitude_quaternion)
            self._position(vehicle, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
        t = stamp * 1e-6 if stamp > 0 else vehicle.arrival_clock.board_time(arrival)
        if t is not None and np.all(np.isfinite(q)):
            vehicle.references().add_truth(t, q)

    def _flight_state(self, vehicle: Vehicle) -> None:
        """Pass a change of the vehicle's flight state on to its estimators."""
        airborne = vehicle.flight.airborne
        if self.pipeline.setup(vehicle.sysid).airborne is not airborne:
            self.pipeline.set_flight_state(vehicle.sysid, airborne)
            src = self.pipeline.sources.get(vehicle.primary) if vehicle.primary else None
            last = src.last_sample.t if src is not None and src.last_sample else None
            # board time of the last sample before the switch: a replay of the same
            # samples can apply it at the same place
            vehicle.flight_board_switches.append((last, airborne))

    def _heartbeat(self, vehicle: Vehicle, msg: MAVLinkMessage, compid: int, link: Link,
                   now: float) -> None:
        if not is_autopilot(msg):
            return
        if vehicle.autopilot_compid is None:
            vehicle.autopilot_compid = compid
            if vehicle.admitted_by == PROVISIONAL:
                vehicle.admitted_by = HEARTBEAT
            # From now on the gate lets only the autopilot (and the truth source) of this
            # system id send more than heartbeats.
            comps = {compid}
            if self.truth is not None and self.truth[0] == vehicle.sysid:
                comps.add(self.truth[1])
            self.admission.admit_vehicle(vehicle.sysid, frozenset(comps))
        if compid != vehicle.autopilot_compid:
            vehicle.refused["other_component"] += 1
            return
        vehicle.heartbeats += 1
        vehicle.last_heartbeat = now
        was_armed = vehicle.flight.armed
        vehicle.flight.on_heartbeat(now, msg.base_mode, msg.autopilot)
        if was_armed and vehicle.flight.armed is False and vehicle.autopilot is not None:
            # PX4 saves the declination its EKF learned when it disarms: read it again
            vehicle.declination.plan(vehicle.autopilot)
        self._flight_state(vehicle)
        if msg.type != vehicle.mav_type:
            if vehicle.mav_type is not None:
                log.warning("vehicle %d: heartbeat type changed from %s to %s", vehicle.sysid,
                            type_name(vehicle.mav_type), type_name(msg.type))
            vehicle.mav_type = msg.type
            self.pipeline.configure(vehicle.sysid, model=model_of(msg.type))
        if msg.autopilot != vehicle.autopilot:
            self._autopilot_known(vehicle, msg.autopilot)
        vehicle.link, vehicle.address = link, link.last_addr
        self._pump_requests(vehicle)

    def _position(self, vehicle: Vehicle, lat: float, lon: float, alt_m: float) -> None:
        """A position of the vehicle: the World Magnetic Model's declination there, unless
        the user or the autopilot said (bridge.declination)."""
        if vehicle.declination.on_position(lat, lon, alt_m):
            self.pipeline.configure(vehicle.sysid, declination_rad=vehicle.declination.rad)

    def _autopilot_known(self, vehicle: Vehicle, autopilot: int) -> None:
        """What the autopilot is decides what its RAW_IMU integers mean (unless --board
        says) and which IMU stream to ask it for."""
        entry = mavlink.enums["MAV_AUTOPILOT"].get(autopilot)
        log.info("vehicle %d: %s autopilot (component %s), %s, heard on %s from %s",
                 vehicle.sysid, entry.name.removeprefix("MAV_AUTOPILOT_") if entry else
                 autopilot, vehicle.autopilot_compid, type_name(vehicle.mav_type),
                 self.link.name, _address(self.link.last_addr))
        vehicle.autopilot = autopilot
        if self.cfg.board is None:
            board = board_for(autopilot)
            if self.ingest.set_board(vehicle.sysid, board_profile(board)):
                log.info("vehicle %d: RAW_IMU read as %s units", vehicle.sysid, board)
                if vehicle.primary is not None and vehicle.primary.msg == ID_RAW_IMU:
                    self._forget_source(vehicle.primary)
                    vehicle.primary = None
        vehicle.negotiation.start(autopilot)
        vehicle.declination.plan(autopilot)

    def _command_ack(self, vehicle: Vehicle, msg: MAVLinkMessage, compid: int) -> None:
        """COMMAND_ACK for one of our SET_MESSAGE_INTERVAL requests: on to the next."""
        vehicle.command_acks += 1
        ours = getattr(msg, "target_component", 0) in (0, self.cfg.component_id)
        if compid != vehicle.autopilot_compid or not ours or \
                msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        vehicle.negotiation.on_ack(msg.result, time.monotonic())
        self._pump_requests(vehicle)

    def _imu(self, vehicle: Vehicle, msg: MAVLinkMessage, link: Link, arrival: float,
             now: float) -> None:
        key = self.ingest.key_of(msg)
        assert key is not None
        old = vehicle.primary
        use, new = vehicle.choose_source(key, now, self.cfg.imu_id,
                                         vehicle.negotiation.preferred_id,
                                         self.cfg.source_timeout_s)
        if not use:
            return
        if new:
            for stale in (old, key):
                if stale is not None:
                    self._forget_source(stale)
        state = self.ingest.sources.get(key)
        if state is not None:
            state.clock.boot_hint = vehicle.boot_hint
        samples = self.ingest.handle_all(msg, arrival, key)
        if not samples:
            return
        vehicle.last_imu = now
        vehicle.request_backoff = STREAM_SILENCE_S
        if vehicle.autopilot_compid is None or key.compid == vehicle.autopilot_compid:
            vehicle.link, vehicle.address = link, link.last_addr
        aiding = vehicle.aiding if self.cfg.aiding else None
        negotiation = vehicle.negotiation
        for sample in samples:
            negotiation.observe(key.msg, sample.t)
            if sample.restart is not None:
                self._log_restart(vehicle, sample)
                vehicle.arrival_clock.reset()
            vehicle.arrival_clock.observe(sample.t, sample.arrival)
            if sample.restart == "reboot":
                vehicle.refs = None  # the references' clock restarted too
                if vehicle.autopilot is not None:
                    # a rebooted autopilot has forgotten every interval it was asked for
                    log.info("vehicle %d: asking again for its streams", vehicle.sysid)
                    negotiation.start(vehicle.autopilot)
            vel, vel_age = None, 0.0
            if aiding is not None:
                if sample.restart is not None:
                    aiding.forget_pending()
                vel, vel_age = aiding.take(sample.t, sample.arrival)
            est = self.pipeline.process(sample, vel, vel_age)
            if est.initialising:
                self.output.hold(est)
            else:
                self.output.offer(est)
            if self.mqtt is not None:
                self._maybe_publish_estimates(vehicle, est)

    def _log_restart(self, vehicle: Vehicle, sample: Any) -> None:
        """A reboot or an outage restarts the estimate: say so, with the board times."""
        src = self.pipeline.sources.get(sample.key)
        before = src.last_sample.t if src is not None and src.last_sample is not None else None
        was = f"{before:.3f} s" if before is not None else "unknown"
        if sample.restart == "reboot":
            log.warning("vehicle %d rebooted (board time went back from %s to %.3f s); "
                        "estimators restarted, output held %g s while they settle",
                        vehicle.sysid, was, sample.t, self.cfg.reinit_settle_s)
        else:
            log.warning("vehicle %d: IMU data resumed after a gap (board time %s -> %.3f s); "
                        "estimators restarted, output held %g s while they settle",
                        vehicle.sysid, was, sample.t, self.cfg.reinit_settle_s)

    # --- stream requests -----------------------------------------------------------------
    def _forget_source(self, key) -> None:
        self.ingest.forget(key)
        self.pipeline.forget(key)
        self.output.forget(key)

    def _pump_requests(self, vehicle: Vehicle) -> None:
        """Send the vehicle's next SET_MESSAGE_INTERVAL if one is due (see
        bridge.negotiate), to its own address only, while its autopilot is heard."""
        if vehicle.link is None or vehicle.autopilot_compid is None:
            return
        if time.monotonic() - vehicle.last_heartbeat > HEARTBEAT_ALIVE_S:
            return  # nobody there to ask
        now = time.monotonic()
        req = vehicle.negotiation.next_send(now)
        if req is not None:
            self._send_request(vehicle, req)
        name = vehicle.declination.param_to_send(now)
        if name is not None:
            read = mavlink.MAVLink_param_request_read_message(
                vehicle.sysid, vehicle.autopilot_compid, name.encode(), -1)
            vehicle.link.send_to(read, vehicle.sysid, self.cfg.component_id, vehicle.address)
            log.info("asked vehicle %d for %s", vehicle.sysid, name)

    def _send_request(self, vehicle: Vehicle, req: Request) -> None:
        cmd = mavlink.MAVLink_command_long_message(
            vehicle.sysid, vehicle.autopilot_compid or 1,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            float(req.msg_id), req.interval_us, 0, 0, 0, 0, 0)
        vehicle.link.send_to(cmd, vehicle.sysid, self.cfg.component_id, vehicle.address)
        vehicle.stream_requests += 1
        log.info("asked vehicle %d for %s at %g Hz", vehicle.sysid, req.name, req.rate_hz)

    def _request_streams(self) -> None:
        """Retries (no answer yet), and the IMU stream asked for again when it stopped
        coming, backing off to STREAM_RETRY_MAX_S."""
        now = time.monotonic()
        for vehicle in self.vehicles.values():
            if vehicle.autopilot_compid is None:
                continue
            if now >= vehicle.next_request and now - vehicle.last_imu > STREAM_SILENCE_S \
                    and vehicle.stream_requests > 0:
                vehicle.negotiation.repeat_imu()
                vehicle.next_request = now + vehicle.request_backoff
                vehicle.request_backoff = min(2.0 * vehicle.request_backoff,
                                              STREAM_RETRY_MAX_S)
            self._pump_requests(vehicle)

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
        now = time.time()
        declination = math.degrees(src.declination_rad)
        for label, estimator in zip(src.labels, src.estimators, strict=True):
            st = estimator.status
            q = st.q
            roll, pitch, yaw = euler_zyx(q)
            name = self.topics[label]
            self.mqtt.publish(self.mqtt.topic(est.key.sysid, name), {
                "sysid": est.key.sysid, "estimator": name, "label": label,
                "params": self._user_params[label],
                "primary": label == self.pipeline.primary_label,
                "source": _source(est.key),
                "time_unix": round(now, 3), "time_s": est.t, "time_boot_ms": est.time_boot_ms,
                **FRAME, "declination_deg": round(declination, 3),
                "q": _finite_list(q),
                "euler_deg": {"roll": _finite(math.degrees(roll)),
                              "pitch": _finite(math.degrees(pitch)),
                              "yaw": _finite(math.degrees(yaw))},
                "gyro_bias_dps": [_finite(math.degrees(b)) for b in st.bias],
                "flags": {"initialising": st.initialising or est.initialising,
                          "acc_rejected": st.acc_rejected, "mag_rejected": st.mag_rejected},
            })

    # --- status --------------------------------------------------------------------------
    def vehicle_status(self, vehicle: Vehicle, elapsed: float) -> dict[str, Any]:
        """Rates, drops and refusals by cause, latency and the live comparison of one
        vehicle."""
        sources = {k: s for k, s in self.ingest.sources.items() if k.sysid == vehicle.sysid}
        samples = sum(s.accepted for s in sources.values())
        if samples < vehicle.samples_at_last_status:  # its state was dropped meanwhile
            vehicle.samples_at_last_status = 0
        rate = (samples - vehicle.samples_at_last_status) / elapsed if elapsed > 0 else 0.0
        vehicle.samples_at_last_status = samples
        drops = dict.fromkeys(DROP_CAUSES, 0)
        flags = dict.fromkeys(FLAG_CAUSES, 0)
        pending = 0
        for s in sources.values():
            for cause in DROP_CAUSES:
                drops[cause] += s.counts[cause]
            for cause in FLAG_CAUSES:
                flags[cause] += s.counts[cause]
            pending += s.clock.pending
        link = {"lost": sum(t.lost for t in vehicle.sequences.values()),
                "late": sum(t.late for t in vehicle.sequences.values()),
                "repeated": sum(t.duplicate for t in vehicle.sequences.values())}
        compare: dict[str, Any] = {}
        counters: dict[str, Any] = {}
        t_last = None
        restarts = 0
        initialising = False
        src = self.pipeline.sources.get(vehicle.primary) if vehicle.primary else None
        if src is not None:
            restarts = src.restarts
            if src.last_sample is not None:
                t_last = src.last_sample.t
            initialising = src.initialising
            for label, est in zip(src.labels, src.estimators, strict=True):
                counters[label] = est.counters.__dict__
            if vehicle.refs is not None:
                for ref, by_label in compare_all(src.history, vehicle.refs,
                                                 self.cfg.window_s).items():
                    compare[ref] = {label: c.to_dict() for label, c in by_label.items()}
        own = None
        if vehicle.refs is not None:
            c = vehicle_against_truth(vehicle.refs, self.cfg.window_s)
            own = c.to_dict() if c is not None else None
        return {
            "sysid": vehicle.sysid, "time_unix": round(time.time(), 3), "time_s": t_last,
            "online": vehicle.last_imu > 0.0 and vehicle.sysid not in self._silent_since,
            "samples": samples,
            "input_rate_hz": round(rate, 1), "sources": [_source(k) for k in sources],
            "primary": _source(vehicle.primary) if vehicle.primary else None,
            "estimator_topics": {label: self.topics[label] for label in self.topics},
            "admitted_by": vehicle.admitted_by, "source_switches": vehicle.source_switches,
            "drops": drops, "flags": flags, "link": link, "refused": dict(vehicle.refused),
            "clock_pending": pending, "restarts": restarts, "initialising": initialising,
            "sent": self.output.sent.get(vehicle.sysid, 0),
            "held_initialising": self.output.held.get(vehicle.sysid, 0),
            "latency_ms": self.output.latency_percentiles_ms(),
            "estimator_counters": counters, "compare": compare, "vehicle_vs_truth": own,
            "stream_requests": vehicle.stream_requests,
            "imu_stream": vehicle.negotiation.status(),
            "board": self.ingest.board_of(vehicle.sysid).name,
            "declination": vehicle.declination.status(),
            "vehicle": self._vehicle_description(vehicle),
            "aiding": {**vehicle.aiding.status(), "enabled": self.cfg.aiding,
                       "aided_samples": src.aided if src is not None else 0},
            "flight_state": self._flight_status(vehicle, src),
        }

    @staticmethod
    def _flight_status(vehicle: Vehicle, src: Any) -> dict[str, Any]:
        """The vehicle's flight state, where it came from, its last switches (seconds
        ago) and, per estimator, whether its in-flight model (eskf's drag) is running."""
        now = time.monotonic()
        recent = list(vehicle.flight.switches)[-FLIGHT_SWITCHES_SHOWN:]
        return {**vehicle.flight.status(),
                "recent_switches": [{"s_ago": round(now - s.t, 1),
                                     "state": state_name(s.airborne), "source": s.source}
                                    for s in recent],
                "air_model": src.air_models() if src is not None else {},
                "board_switches": [[t, state_name(a)] for t, a in vehicle.flight_board_switches]}

    def _vehicle_description(self, vehicle: Vehicle) -> dict[str, Any]:
        """What the heartbeat says the vehicle is, and what that made of the estimators."""
        model = model_of(vehicle.mav_type)
        autopilot = None
        if vehicle.autopilot is not None:
            entry = mavlink.enums["MAV_AUTOPILOT"].get(vehicle.autopilot)
            autopilot = entry.name if entry is not None else str(vehicle.autopilot)
        return {"autopilot": autopilot, "type": type_name(vehicle.mav_type), "model": model,
                "estimators": {spec.label: describe(spec, model)
                               for spec in self.pipeline.specs}}

    def link_status(self) -> dict[str, Any]:
        c = self.link.codec.stats
        ls = self.link.stats
        s = {"bytes_in": c.bytes_in, "messages_in": c.messages_in, "bad_crc": c.bad_crc,
             "bad_frame": c.bad_frame, "unsigned_rejected": c.unsigned_rejected,
             "unsigned_accepted": c.unsigned_accepted, "bad_signature": c.bad_signature,
             "replayed": c.replayed, "unknown_message": c.unknown_message,
             "truncated": c.truncated, "send_dropped": ls.send_dropped,
             "send_errors": ls.send_errors, "reconnects": ls.reconnects,
             "idle_timeouts": ls.idle_timeouts, "write_stalls": ls.write_stalls,
             "peers": ls.peers,
             "peers_refused": ls.peers_refused, "peers_expired": ls.peers_expired,
             "gate": self.admission.stats.to_dict(), "refused": dict(self.refused),
             "vehicles": sorted(self.vehicles)}
        if self.mqtt is not None:
            m = self.mqtt.stats
            s["mqtt"] = {"connected": m.connected, "published": m.published,
                         "dropped": m.dropped, "connects": m.connects,
                         "last_error": m.last_error or None, "stopped": m.stopped}
        if self.recorder is not None:
            s["record"] = {"file": str(self.recorder.path), "frames_in":
                           self.recorder.frames_in, "frames_out": self.recorder.frames_out}
        return s

    def publish_status(self) -> None:
        now = time.monotonic()
        elapsed = now - self._last_status_wall
        self._last_status_wall = now
        self.admission.tick(elapsed)
        link = self.link_status()
        for vehicle in list(self.vehicles.values()):
            status = self.vehicle_status(vehicle, elapsed)
            status["connection"] = link
            self.last_status[vehicle.sysid] = status
            if self.mqtt is not None:
                self.mqtt.publish(self.mqtt.topic(vehicle.sysid, "status"), status)
        for sysid in [s for s in self.last_status if s not in self.vehicles]:
            del self.last_status[sysid]  # replaced (a provisional vehicle)
        if self.recorder is not None:
            self.recorder.flush()
        if self.cfg.status_file:
            self._write_status_file(link)
        if self.on_status is not None:
            self.on_status(self)

    def _write_status_file(self, link: dict[str, Any]) -> None:
        status = {"time_unix": round(time.time(), 3),
                  "uptime_s": round(time.monotonic() - self.started, 1),
                  "vehicles": {str(k): {n: v for n, v in st.items() if n != "connection"}
                               for k, st in self.last_status.items()},
                  "connection": link, "mqtt": link.get("mqtt")}
        try:
            write_status_file(self.cfg.status_file, status)
        except OSError as exc:  # disk full, folder removed: keep serving, say so
            log.warning("cannot write the status file %s: %s", self.cfg.status_file, exc)


def _source(key: Any) -> dict[str, Any]:
    """An IMU source as an object: who sent it, which message, which IMU."""
    entry = mavlink.mavlink_map.get(key.msg)
    return {"sysid": key.sysid, "compid": key.compid,
            "message": entry.msgname if entry is not None else str(key.msg), "imu": key.imu}


def _address(addr: tuple | None) -> str:
    return f"{addr[0]}:{addr[1]}" if addr else "-"


async def _cancel(tasks: list[asyncio.Task]) -> None:
    for task in tasks:
        task.cancel()
    for task in tasks:
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _finite_list(v: np.ndarray) -> list[float | None]:
    return [_finite(float(x)) for x in v]
