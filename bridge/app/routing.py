"""Every parsed message to the part that wants it, for served vehicles only.

The router checks who may say what before anything is kept: our own component id is
ignored (an echo or a peer bridge), unserved system ids are refused by the registry,
and per vehicle only its autopilot component counts for heartbeats, references,
velocities, parameters and flight state (the truth may come from a configured source).
What a message means then lives in the vehicle wing; the router only hands it over and
passes what changed on to the estimators (declination, vehicle model, flight state).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from estimators import quat as Q
from imu.boards import board_profile

from ..estimate.pipeline import Pipeline
from ..vehicle.aiding import VELOCITY_MESSAGE_IDS
from ..vehicle.ingest import IMU_MESSAGE_IDS, Ingest
from ..vehicle.model import model_of, type_name
from ..vehicle.negotiate import board_for
from ..vehicle.vehicle import HEARTBEAT, PROVISIONAL, Vehicle
from ..wire.admission import Admission
from ..wire.links import Link
from ..wire.mav import MAVLinkMessage, mavlink
from .config import BridgeConfig
from .registry import VehicleRegistry, is_autopilot
from .requests import StreamRequester
from .samples import SampleFlow

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
ID_RAW_IMU = mavlink.MAVLINK_MSG_ID_RAW_IMU
ID_PARAM_VALUE = mavlink.MAVLINK_MSG_ID_PARAM_VALUE
ID_GLOBAL_POSITION_INT = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
ID_GPS_RAW_INT = mavlink.MAVLINK_MSG_ID_GPS_RAW_INT


class MessageRouter:
    """``on_message`` is the link's callback for every parsed message."""

    def __init__(self, cfg: BridgeConfig, registry: VehicleRegistry, samples: SampleFlow,
                 requester: StreamRequester, admission: Admission) -> None:
        self.cfg = cfg
        self.registry = registry
        self.samples = samples
        self.requester = requester
        self.admission = admission
        self.pipeline: Pipeline = samples.pipeline
        self.ingest: Ingest = samples.ingest

    def on_message(self, msg: MAVLinkMessage, link: Link) -> None:
        # when the datagram reached this machine (a busy event loop's delay included)
        arrival = time.perf_counter() - link.waited_s
        header = msg.get_header()
        sysid, compid = header.srcSystem, header.srcComponent
        if compid == self.cfg.component_id:
            return  # our own output echoed back, or a peer bridge: not vehicle data
        msg_id = header.msgId
        vehicle = self.registry.vehicle_for(sysid, msg, msg_id)
        if vehicle is None:
            return
        now = time.monotonic()
        if not self._from_where_it_talks(vehicle, compid, msg_id, link, now):
            vehicle.refused["other_address"] += 1
            return
        vehicle.last_heard = now
        vehicle.observe_sequence(compid, header.seq)
        if msg_id in IMU_MESSAGE_IDS:
            self.samples.on_imu(vehicle, msg, link, arrival, now)
        elif msg_id == ID_HEARTBEAT:
            self._heartbeat(vehicle, msg, compid, link, now)
        elif msg_id in TRUTH_MESSAGE_IDS:
            self._truth(vehicle, msg, compid, arrival)
        elif msg_id in (ID_ATTITUDE_QUATERNION, ID_ATTITUDE):
            self._vehicle_attitude(vehicle, msg, msg_id, compid)
        elif msg_id in VELOCITY_MESSAGE_IDS:
            self._velocity(vehicle, msg, msg_id, compid, arrival)
        elif msg_id == ID_PARAM_VALUE:
            if compid == vehicle.autopilot_compid:
                self._param(vehicle, msg)
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

    def _from_where_it_talks(self, vehicle: Vehicle, compid: int, msg_id: int, link: Link,
                             now: float) -> bool:
        """The vehicle's autopilot component only from its one link and address
        (bridge.vehicle.address); a truth source the user named may be elsewhere."""
        if compid != vehicle.reference_compid():
            return True
        if self.cfg.truth is not None and msg_id in TRUTH_MESSAGE_IDS:
            return True
        return vehicle.talks_from.admits(link, link.last_addr, now, self.cfg.source_timeout_s)

    def _vehicle_attitude(self, vehicle: Vehicle, msg: MAVLinkMessage, msg_id: int,
                          compid: int) -> None:
        """The autopilot's own attitude, for the live comparison."""
        if compid != vehicle.reference_compid():
            vehicle.refused["refs_refused"] += 1
        elif msg_id == ID_ATTITUDE_QUATERNION:
            if not vehicle.references().add_vehicle_quaternion(
                    msg.time_boot_ms * 1e-3, np.array([msg.q1, msg.q2, msg.q3, msg.q4])):
                vehicle.refused["refs_invalid"] += 1
        elif not vehicle.references().add_vehicle_euler(msg.time_boot_ms * 1e-3, msg.roll,
                                                        msg.pitch, msg.yaw):
            vehicle.refused["refs_invalid"] += 1

    def _velocity(self, vehicle: Vehicle, msg: MAVLinkMessage, msg_id: int, compid: int,
                  arrival: float) -> None:
        """A velocity for aiding; a position fix for the World Magnetic Model."""
        if compid != vehicle.reference_compid():
            vehicle.refused["other_component"] += 1
            return
        if self.cfg.aiding:
            vehicle.aiding.offer(msg, msg_id, arrival)
        if msg_id == ID_GLOBAL_POSITION_INT or (
                msg_id == ID_GPS_RAW_INT and msg.fix_type >= mavlink.GPS_FIX_TYPE_2D_FIX):
            self._position(vehicle, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)

    def _param(self, vehicle: Vehicle, msg: MAVLinkMessage) -> None:
        """A parameter of the autopilot: its declination, gyro filter or magnetometer
        calibration, when it is one asked."""
        name = msg.param_id if isinstance(msg.param_id, str) else \
            msg.param_id.decode(errors="replace")
        name, value = name.rstrip("\x00"), float(msg.param_value)
        if vehicle.declination.on_param(name, value, time.monotonic(), vehicle.flight.armed):
            self.pipeline.configure(vehicle.sysid, declination_rad=vehicle.declination.rad)
        if vehicle.imu_delay.on_param(name, value):
            self.pipeline.configure(vehicle.sysid, imu_delay_s=vehicle.imu_delay.seconds)
        vehicle.px4_mag.on_param(name, value)

    def _truth(self, vehicle: Vehicle, msg: MAVLinkMessage, compid: int,
               arrival: float) -> None:
        """A simulator's true attitude: HIL_STATE_QUATERNION (the emulator stamps it with
        the board time, PX4 SIH with 0) or ArduPilot SITL's SIMSTATE (no stamp): an
        unstamped one is placed on the board clock by its arrival."""
        sysid = vehicle.sysid
        if (sysid, compid) != (self.cfg.truth or (sysid, vehicle.reference_compid())):
            vehicle.refused["refs_refused"] += 1
            return
        if msg.get_msgId() == ID_SIMSTATE:
            stamp, q = 0, Q.from_euler(msg.roll, msg.pitch, msg.yaw)
        else:
            stamp, q = msg.time_usec, np.array(msg.attitude_quaternion)
            self._position(vehicle, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
        t = stamp * 1e-6 if stamp > 0 else vehicle.arrival_clock.board_time(arrival)
        if t is not None and not vehicle.references().add_truth(t, q):
            vehicle.refused["refs_invalid"] += 1

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
            self._autopilot_heard(vehicle, compid)
        if compid != vehicle.autopilot_compid:
            vehicle.refused["other_component"] += 1
            return
        vehicle.heartbeats += 1
        vehicle.last_heartbeat = now
        was_armed = vehicle.flight.armed
        vehicle.flight.on_heartbeat(now, msg.base_mode, msg.autopilot)
        if was_armed and vehicle.flight.armed is False and vehicle.autopilot is not None:
            # PX4 saves the declination its EKF learned when it disarms: read it again;
            # and the gyro filter, which a user may change between flights
            vehicle.declination.plan(vehicle.autopilot)
            self._plan_imu_delay(vehicle, vehicle.autopilot)
        elif not was_armed and vehicle.flight.armed and vehicle.autopilot is not None:
            # the flight starts with the declination the autopilot has now (it sets it
            # on the ground without telling: bridge.vehicle.declination)
            vehicle.declination.plan(vehicle.autopilot)
        self._flight_state(vehicle)
        if msg.type != vehicle.mav_type:
            if vehicle.mav_type is not None:
                log.warning("vehicle %d: heartbeat type changed from %s to %s", vehicle.sysid,
                            type_name(vehicle.mav_type), type_name(msg.type))
            vehicle.mav_type = msg.type
            self.pipeline.configure(vehicle.sysid, model=model_of(msg.type))
        if msg.autopilot != vehicle.autopilot:
            self._autopilot_known(vehicle, msg.autopilot, link)
        vehicle.link, vehicle.address = link, link.last_addr
        self.requester.pump(vehicle, now)

    def _autopilot_heard(self, vehicle: Vehicle, compid: int) -> None:
        """The first autopilot heartbeat: from now on the gate lets only this component
        (and the truth source) of the system id send more than heartbeats."""
        vehicle.autopilot_compid = compid
        if vehicle.admitted_by == PROVISIONAL:
            vehicle.admitted_by = HEARTBEAT
        comps = {compid}
        truth = self.cfg.truth
        if truth is not None and truth[0] == vehicle.sysid:
            comps.add(truth[1])
        self.admission.admit_vehicle(vehicle.sysid, frozenset(comps))

    def _position(self, vehicle: Vehicle, lat: float, lon: float, alt_m: float) -> None:
        """A position of the vehicle: the World Magnetic Model's declination there, unless
        the user or the autopilot said (bridge.vehicle.declination)."""
        if vehicle.declination.on_position(lat, lon, alt_m):
            self.pipeline.configure(vehicle.sysid, declination_rad=vehicle.declination.rad)

    def _autopilot_known(self, vehicle: Vehicle, autopilot: int, link: Link) -> None:
        """What the autopilot is decides what its RAW_IMU integers mean (unless --board
        says) and which IMU stream to ask it for."""
        entry = mavlink.enums["MAV_AUTOPILOT"].get(autopilot)
        addr = link.last_addr
        log.info("vehicle %d: %s autopilot (component %s), %s, heard on %s from %s",
                 vehicle.sysid, entry.name.removeprefix("MAV_AUTOPILOT_") if entry else
                 autopilot, vehicle.autopilot_compid, type_name(vehicle.mav_type),
                 link.name, f"{addr[0]}:{addr[1]}" if addr else "-")
        vehicle.autopilot = autopilot
        self.ingest.set_scaled_truncated(vehicle.sysid,
                                         autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
        if self.cfg.board is None:
            board = board_for(autopilot)
            if self.ingest.set_board(vehicle.sysid, board_profile(board)):
                log.info("vehicle %d: RAW_IMU read as %s units", vehicle.sysid, board)
                if vehicle.primary is not None and vehicle.primary.msg == ID_RAW_IMU:
                    self.samples.forget_source(vehicle.primary)
                    vehicle.primary = None
        vehicle.negotiation.start(autopilot)
        vehicle.declination.plan(autopilot)
        self._plan_imu_delay(vehicle, autopilot)
        vehicle.px4_mag.plan(autopilot)

    def _plan_imu_delay(self, vehicle: Vehicle, autopilot: int) -> None:
        """The autopilot's default IMU delay now, its parameter asked for."""
        if vehicle.imu_delay.plan(autopilot, vehicle.mav_type):
            self.pipeline.configure(vehicle.sysid, imu_delay_s=vehicle.imu_delay.seconds)

    def _command_ack(self, vehicle: Vehicle, msg: MAVLinkMessage, compid: int) -> None:
        """COMMAND_ACK for one of our SET_MESSAGE_INTERVAL requests: on to the next."""
        vehicle.command_acks += 1
        ours = getattr(msg, "target_component", 0) in (0, self.cfg.component_id)
        if compid != vehicle.autopilot_compid or not ours or \
                msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        now = time.monotonic()
        vehicle.negotiation.on_ack(msg.result, now)
        self.requester.pump(vehicle, now)
