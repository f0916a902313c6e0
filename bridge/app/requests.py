"""What the bridge asks of an autopilot: SET_MESSAGE_INTERVAL and PARAM_REQUEST_READ.

Each vehicle's :class:`~bridge.vehicle.negotiate.StreamNegotiation` and
:class:`~bridge.vehicle.declination.Declination` decide *what* to ask and when it is due;
this class sends it, to the vehicle's own address on the link it talks on, and only
while its autopilot is heard (a request into silence only tells an attacker or a
stranger that we exist). When the IMU stream stops it is asked for again, backing off
so a vehicle that will not answer is not flooded.
"""

from __future__ import annotations

import logging

from ..vehicle.negotiate import Request
from ..vehicle.vehicle import Vehicle
from ..wire.mav import mavlink
from .registry import STREAM_SILENCE_S

log = logging.getLogger(__name__)

#: Ask again for the IMU stream after STREAM_SILENCE_S without samples, doubling the
#: wait up to this; only while the vehicle's autopilot is heard (its heartbeat within
#: HEARTBEAT_ALIVE_S).
STREAM_RETRY_MAX_S = 30.0
HEARTBEAT_ALIVE_S = 5.0


class StreamRequester:
    """Sends the due requests of each vehicle, as component ``component_id``."""

    def __init__(self, component_id: int) -> None:
        self.component_id = component_id

    def pump(self, vehicle: Vehicle, now: float) -> None:
        """Send the vehicle's next SET_MESSAGE_INTERVAL and parameter read, if due
        (monotonic ``now``)."""
        if vehicle.link is None or vehicle.autopilot_compid is None:
            return
        if now - vehicle.last_heartbeat > HEARTBEAT_ALIVE_S:
            return  # nobody there to ask
        req = vehicle.negotiation.next_send(now)
        if req is not None:
            self._send_interval(vehicle, req)
        # (the declination's routine re-reads on the ground, every 10 s, log at debug)
        for name, routine in ((vehicle.declination.param_to_send(now),
                               vehicle.declination.query.routine),
                              (vehicle.imu_delay.param_to_send(now), False),
                              (vehicle.px4_mag.param_to_send(now), False)):
            if name is None:
                continue
            read = mavlink.MAVLink_param_request_read_message(
                vehicle.sysid, vehicle.autopilot_compid, name.encode(), -1)
            vehicle.link.send_to(read, vehicle.sysid, self.component_id, vehicle.address)
            log.log(logging.DEBUG if routine else logging.INFO, "asked vehicle %d for %s",
                    vehicle.sysid, name)

    def _send_interval(self, vehicle: Vehicle, req: Request) -> None:
        cmd = mavlink.MAVLink_command_long_message(
            vehicle.sysid, vehicle.autopilot_compid or 1,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            float(req.msg_id), req.interval_us, 0, 0, 0, 0, 0)
        vehicle.link.send_to(cmd, vehicle.sysid, self.component_id, vehicle.address)
        vehicle.stream_requests += 1
        log.info("asked vehicle %d for %s at %g Hz", vehicle.sysid, req.name, req.rate_hz)

    def retry(self, vehicles: list[Vehicle], now: float) -> None:
        """Retries of unanswered requests, and the IMU stream asked for again when it
        stopped coming (backing off to STREAM_RETRY_MAX_S)."""
        for vehicle in vehicles:
            if vehicle.autopilot_compid is None:
                continue
            if now >= vehicle.next_request and now - vehicle.last_imu > STREAM_SILENCE_S \
                    and vehicle.stream_requests > 0:
                vehicle.negotiation.repeat_imu()
                vehicle.next_request = now + vehicle.request_backoff
                vehicle.request_backoff = min(2.0 * vehicle.request_backoff,
                                              STREAM_RETRY_MAX_S)
            self.pump(vehicle, now)
