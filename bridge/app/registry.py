"""Who the bridge serves: the vehicle table, its admission rules and its eviction.

The rules themselves (configured ids, the first autopilot heard, a provisional IMU
stream giving way to a real autopilot) are described in :mod:`bridge.vehicle.vehicle`;
this class applies them and owns the table, so the router only asks "which vehicle is
this message for, if any".
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from ..vehicle.aiding import VelocityAiding
from ..vehicle.declination import Declination
from ..vehicle.imu_delay import ImuDelay
from ..vehicle.ingest import IMU_MESSAGE_IDS, SourceKey
from ..vehicle.negotiate import StreamNegotiation
from ..vehicle.vehicle import HEARTBEAT, PROVISIONAL, Vehicle
from ..wire.admission import Admission
from ..wire.mav import MAVLinkMessage, mavlink
from .config import BridgeConfig

log = logging.getLogger(__name__)

ID_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
#: Vehicle types whose heartbeat does not make them a vehicle to serve.
NOT_VEHICLES = frozenset((mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER))
#: First wait before asking again for a stream that stopped (the requester doubles it).
STREAM_SILENCE_S = 2.0


def is_autopilot(msg: MAVLinkMessage) -> bool:
    """A HEARTBEAT from a flight controller (not a GCS, companion or peer bridge)."""
    return msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type not in NOT_VEHICLES


class VehicleRegistry:
    """The served vehicles by system id, and what their admission refused.

    ``forget_source`` drops one IMU source's estimating state (ingest, estimators,
    output); the registry calls it when a vehicle is replaced or evicted, so the memory
    of a vehicle that went away is given back.
    """

    def __init__(self, cfg: BridgeConfig, admission: Admission, forced_imu: int | None,
                 forget_source: Callable[[SourceKey], None]) -> None:
        self.cfg = cfg
        self.admission = admission
        self.forced_imu = forced_imu
        self.forget_source = forget_source
        self.vehicles: dict[int, Vehicle] = {}
        #: Messages refused after parsing, by cause.
        self.refused = {"not_vehicle": 0, "vehicles_replaced": 0, "evicted": 0}

    def add(self, sysid: int, how: str) -> Vehicle:
        """Serve ``sysid`` from now on (``how``: configured, heartbeat or imu)."""
        v = self.vehicles[sysid] = Vehicle(
            sysid, admitted_by=how, request_backoff=STREAM_SILENCE_S,
            aiding=VelocityAiding(self.cfg.aid_max_age_s),
            negotiation=StreamNegotiation(sysid, self.cfg.imu_rate, self.forced_imu,
                                          self.cfg.aiding),
            declination=Declination(sysid, self.cfg.declination_deg),
            imu_delay=ImuDelay(sysid))
        self.admission.admit_vehicle(sysid)
        log.info("vehicle %d admitted (%s)", sysid, how)
        return v

    def vehicle_for(self, sysid: int, msg: MAVLinkMessage, msg_id: int) -> Vehicle | None:
        """The served vehicle this message is from, admitting it if the rules allow;
        None (counted) if it is nobody the bridge serves."""
        vehicle = self.vehicles.get(sysid)
        if vehicle is None:
            vehicle = self._admit(sysid, msg, msg_id)
            if vehicle is None:
                self.refused["not_vehicle"] += 1
        return vehicle

    def _admit(self, sysid: int, msg: MAVLinkMessage, msg_id: int) -> Vehicle | None:
        if self.cfg.vehicles:
            return None
        if msg_id == ID_HEARTBEAT and is_autopilot(msg):
            current = list(self.vehicles.values())
            if current and current[0].admitted_by != PROVISIONAL:
                return None
            for old in current:  # a bare IMU stream gives way to a real autopilot
                self.drop_state(old)
                del self.vehicles[old.sysid]
                self.admission.forget_vehicle(old.sysid)
                self.refused["vehicles_replaced"] += 1
            return self.add(sysid, HEARTBEAT)
        if msg_id in IMU_MESSAGE_IDS and not self.vehicles:
            return self.add(sysid, PROVISIONAL)
        return None

    def drop_state(self, vehicle: Vehicle) -> None:
        """Forget a vehicle's estimators, clock and references (kept: who it is)."""
        if vehicle.primary is not None:
            self.forget_source(vehicle.primary)
        vehicle.primary = None
        vehicle.refs = None
        vehicle.sequences.clear()
        vehicle.mqtt_sent_t.clear()

    def evict(self, now: float) -> None:
        """Drop the heavy state of vehicles silent for ``evict_after_s`` (monotonic
        ``now``)."""
        for vehicle in self.vehicles.values():
            has_state = vehicle.primary is not None or vehicle.refs is not None
            if has_state and now - vehicle.last_heard > self.cfg.evict_after_s:
                self.drop_state(vehicle)
                self.refused["evicted"] += 1
