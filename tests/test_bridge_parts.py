"""The parts BridgeService is composed of, each on its own: the vehicle registry, the
stream requester, the stream watch, the message router and the status reporter.

Messages are real pymavlink encodings parsed back from their bytes; links are real UDP
sockets on 127.0.0.1. The whole service is exercised by test_bridge_service.py; here
each part's own rules are checked where they live.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import time

import numpy as np
import pytest
from bridge_support import async_test

from bridge.app.config import BridgeConfig
from bridge.app.registry import VehicleRegistry
from bridge.app.requests import HEARTBEAT_ALIVE_S, STREAM_RETRY_MAX_S, StreamRequester
from bridge.app.service import BridgeService
from bridge.app.watch import StreamWatch
from bridge.vehicle.ingest import Ingest, SourceKey
from bridge.vehicle.vehicle import CONFIGURED, HEARTBEAT, PROVISIONAL
from bridge.wire.admission import Admission
from bridge.wire.links import UdpLink, parse_url
from bridge.wire.mav import mavlink
from imu.boards import board_profile

AUTOPILOT, GCS = 1, 190


def on_wire(sysid: int, compid: int, build):
    """``build(mav)`` encoded by a sender (sysid, compid) and parsed back from bytes."""
    sender = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    data = build(sender).pack(sender)
    (msg,) = mavlink.MAVLink(None).parse_buffer(data)
    return msg


def heartbeat(sysid: int, compid: int = AUTOPILOT, mav_type: int = mavlink.MAV_TYPE_QUADROTOR,
              autopilot: int = mavlink.MAV_AUTOPILOT_PX4, base_mode: int = 0):
    return on_wire(sysid, compid, lambda m: m.heartbeat_encode(
        mav_type, autopilot, base_mode, 0, mavlink.MAV_STATE_STANDBY))


def highres_imu(sysid: int, t_us: int, compid: int = AUTOPILOT):
    return on_wire(sysid, compid, lambda m: m.highres_imu_encode(
        t_us, 0.0, 0.0, -9.80665, 0.0, 0.0, 0.0, 0.25, 0.0, 0.43, 1013.0, 0.0, 0.0, 20.0,
        0x1FFF))


def make_registry(**settings) -> tuple[VehicleRegistry, list[SourceKey], Admission]:
    forgotten: list[SourceKey] = []
    admission = Admission(None)
    return (VehicleRegistry(BridgeConfig(**settings), admission, None, forgotten.append),
            forgotten, admission)


# --- the registry ---------------------------------------------------------------------
def test_registry_admits_a_bare_imu_stream_until_an_autopilot_is_heard():
    registry, forgotten, admission = make_registry()
    imu = highres_imu(7, 1000)
    v = registry.vehicle_for(7, imu, imu.get_msgId())
    assert v is not None and v.admitted_by == PROVISIONAL and 7 in admission.vehicles
    v.primary = SourceKey(7, AUTOPILOT, imu.get_msgId(), 0)
    # a second IMU stream from another system id is nobody's
    other = highres_imu(8, 1000)
    assert registry.vehicle_for(8, other, other.get_msgId()) is None
    # a real autopilot takes the slot: the provisional vehicle's state is given back
    hb = heartbeat(3)
    v3 = registry.vehicle_for(3, hb, hb.get_msgId())
    assert v3 is not None and v3.admitted_by == HEARTBEAT
    assert sorted(registry.vehicles) == [3] and 7 not in admission.vehicles
    assert forgotten == [SourceKey(7, AUTOPILOT, imu.get_msgId(), 0)]
    assert registry.refused == {"not_vehicle": 1, "vehicles_replaced": 1, "evicted": 0}
    # ...and then no other autopilot does
    hb2 = heartbeat(4)
    assert registry.vehicle_for(4, hb2, hb2.get_msgId()) is None


def test_registry_serves_only_the_configured_vehicles_and_no_ground_station():
    registry, _, _ = make_registry(vehicles=[2])
    registry.add(2, CONFIGURED)
    for sysid, msg in ((5, heartbeat(5)), (5, highres_imu(5, 10))):
        assert registry.vehicle_for(sysid, msg, msg.get_msgId()) is None
    learning, _, _ = make_registry()
    gcs = heartbeat(255, GCS, mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID)
    assert learning.vehicle_for(255, gcs, gcs.get_msgId()) is None
    assert learning.vehicles == {} and learning.refused["not_vehicle"] == 1


def test_registry_evicts_the_state_of_a_silent_vehicle_and_keeps_who_it_is():
    registry, forgotten, _ = make_registry(evict_after_s=30.0)
    v = registry.add(2, CONFIGURED)
    key = SourceKey(2, AUTOPILOT, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 0)
    v.primary, v.last_heard = key, 100.0
    v.references()
    registry.evict(now=129.0)  # 29 s of silence: kept
    assert v.primary == key and forgotten == []
    registry.evict(now=131.0)
    assert v.primary is None and v.refs is None and forgotten == [key]
    assert registry.vehicles == {2: v} and registry.refused["evicted"] == 1
    registry.evict(now=200.0)  # nothing left to drop: not counted again
    assert registry.refused["evicted"] == 1


# --- the stream requester ---------------------------------------------------------------
async def _requests_seen(sock: socket.socket, wait_s: float = 0.5) -> list:
    parser = mavlink.MAVLink(None)
    out = []
    end = time.monotonic() + wait_s
    while time.monotonic() < end:
        try:
            out += parser.parse_buffer(sock.recv(4096)) or []
        except BlockingIOError:
            await asyncio.sleep(0.01)
    return out


@async_test
async def test_requester_asks_only_a_heard_autopilot_at_its_own_address():
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot.bind(("127.0.0.1", 0))
    autopilot.setblocking(False)
    link = UdpLink(parse_url("udpin:127.0.0.1:0"))
    await link.start()
    try:
        registry, _, _ = make_registry()
        v = registry.add(1, CONFIGURED)
        requester = StreamRequester(component_id=191)
        now = time.monotonic()
        v.link, v.address, v.autopilot_compid = link, autopilot.getsockname(), AUTOPILOT
        v.negotiation.start(mavlink.MAV_AUTOPILOT_PX4)
        v.last_heartbeat = now - HEARTBEAT_ALIVE_S - 1.0  # its autopilot went quiet
        requester.pump(v, now)
        assert await _requests_seen(autopilot, 0.3) == [] and v.stream_requests == 0
        v.last_heartbeat = now
        requester.pump(v, now)
        (cmd,) = await _requests_seen(autopilot)
        assert cmd.get_type() == "COMMAND_LONG"
        assert cmd.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
        assert (cmd.target_system, cmd.target_component) == (1, AUTOPILOT)
        assert int(cmd.param1) == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU  # PX4 sends no RAW_IMU
        assert cmd.param2 == pytest.approx(1e6 / 250.0)
        assert (cmd.get_srcSystem(), cmd.get_srcComponent()) == (1, 191)
        assert v.stream_requests == 1
    finally:
        await link.close()
        autopilot.close()


def test_requester_backs_off_asking_again_for_a_stream_that_stopped():
    registry, _, _ = make_registry()
    v = registry.add(1, CONFIGURED)
    v.autopilot_compid, v.stream_requests = AUTOPILOT, 1  # asked once, data then stopped
    requester = StreamRequester(component_id=191)
    waits = []
    now = 1000.0
    for _ in range(8):
        requester.retry([v], now)
        waits.append(v.next_request - now)
        now = v.next_request
    assert waits == [2.0, 4.0, 8.0, 16.0, STREAM_RETRY_MAX_S, 30.0, 30.0, 30.0]


# --- the stream watch -----------------------------------------------------------------
def test_watch_says_when_a_stream_stops_and_comes_back(caplog):
    registry, _, _ = make_registry()
    v = registry.add(1, CONFIGURED)
    watch = StreamWatch(Ingest(board_profile("gy86")), source_timeout_s=3.0)
    assert not watch.online(v)  # no data yet
    v.last_imu = 100.0
    caplog.set_level(logging.INFO, logger="bridge")
    watch.check(registry.vehicles, now=101.0)
    assert watch.online(v) and not caplog.records
    watch.check(registry.vehicles, now=104.5)
    assert not watch.online(v)
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [
        ("WARNING", "vehicle 1: no IMU data for 4 s (link lost, or the vehicle stopped "
                    "sending)")]
    watch.check(registry.vehicles, now=110.0)  # said once
    assert len(caplog.records) == 1
    v.last_imu = 112.0
    watch.check(registry.vehicles, now=112.1)
    assert watch.online(v)
    assert caplog.records[-1].getMessage() == "vehicle 1: IMU data again after 12.0 s"


# --- the router and the status report, on a service that is built but not run -----------
@pytest.fixture
def service(tmp_path):
    svc = BridgeService(BridgeConfig(connect="udpin:127.0.0.1:0", estimators=["mahony"],
                                     status_file=str(tmp_path / "status.json")))
    return svc


@async_test
async def test_router_takes_each_message_only_from_the_vehicles_autopilot(service):
    route = service.router.on_message
    link = service.link
    await link.start()
    try:
        route(heartbeat(1, base_mode=mavlink.MAV_MODE_FLAG_SAFETY_ARMED), link)
        v = service.vehicles[1]
        assert v.autopilot_compid == AUTOPILOT and v.flight.armed is True
        assert service.admission.vehicles[1] == frozenset({AUTOPILOT})
        # another component's attitude, velocity and landed state do not count
        route(on_wire(1, GCS, lambda m: m.attitude_quaternion_encode(
            10, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)), link)
        route(on_wire(1, GCS, lambda m: m.local_position_ned_encode(
            10, 0, 0, 0, 5.0, 0, 0)), link)
        route(on_wire(1, GCS, lambda m: m.extended_sys_state_encode(
            0, mavlink.MAV_LANDED_STATE_IN_AIR)), link)
        assert v.refs is None
        assert (v.refused["refs_refused"], v.refused["other_component"]) == (1, 2)
        assert service.pipeline.setup(1).airborne is not True
        # the autopilot's own do
        route(on_wire(1, AUTOPILOT, lambda m: m.extended_sys_state_encode(
            0, mavlink.MAV_LANDED_STATE_IN_AIR)), link)
        assert v.flight.airborne is True and service.pipeline.setup(1).airborne is True
        route(on_wire(1, AUTOPILOT, lambda m: m.param_value_encode(
            b"EKF2_MAG_DECL", 3.5, mavlink.MAV_PARAM_TYPE_REAL32, 1, 0)), link)
        assert service.pipeline.setup(1).declination_rad == pytest.approx(np.radians(3.5))
        # our own component id is an echo, never vehicle data
        route(heartbeat(9, compid=service.cfg.component_id), link)
        assert 9 not in service.vehicles and service.refused["not_vehicle"] == 0
    finally:
        await link.close()


@async_test
async def test_status_reports_what_the_router_counted(service, tmp_path):
    link = service.link
    await link.start()
    try:
        route = service.router.on_message
        route(heartbeat(1), link)
        for i in range(1, 201):
            route(highres_imu(1, i * 4000), link)
        route(highres_imu(1, 200 * 4000), link)  # the same sample again
        route(on_wire(1, GCS, lambda m: m.attitude_quaternion_encode(
            10, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)), link)
        route(heartbeat(4), link)  # another autopilot: not served
        service.publish_status()
    finally:
        await link.close()
    st = service.last_status[1]
    assert st["samples"] == 200 and st["drops"]["duplicate"] == 1
    assert st["refused"]["refs_refused"] == 1
    assert st["primary"] == {"sysid": 1, "compid": AUTOPILOT, "message": "HIGHRES_IMU",
                             "imu": 0}
    assert st["vehicle"]["type"] == "quadrotor" and st["admitted_by"] == HEARTBEAT
    assert st["connection"]["refused"]["not_vehicle"] == 1
    assert st["estimator_topics"] == {"mahony": "mahony"}
    written = json.loads((tmp_path / "status.json").read_text())
    assert written["vehicles"]["1"]["samples"] == 200
    assert "connection" not in written["vehicles"]["1"]


def test_status_file_that_cannot_be_written_is_a_warning(tmp_path, caplog):
    folder = tmp_path / "status"
    folder.mkdir()
    svc = BridgeService(BridgeConfig(connect="udpin:127.0.0.1:0", estimators=["mahony"],
                                     status_file=str(folder / "status.json")))
    folder.rmdir()  # removed while the bridge runs
    caplog.set_level(logging.WARNING, logger="bridge")
    svc.publish_status()
    assert any("cannot write the status file" in r.getMessage() for r in caplog.records)


def test_a_declination_the_user_set_survives_the_vehicles_own():
    """`run -e eskf:declination_deg=90` was overridden by the vehicle's parameter or the
    World Magnetic Model without a word; the other estimators follow the vehicle's."""
    import math

    from bridge.estimate.pipeline import SourcePipeline
    from estimators.spec import EstimatorSpec

    specs = [EstimatorSpec.parse("eskf"), EstimatorSpec.parse("eskf:declination_deg=90")]
    src = SourcePipeline(SourceKey(1, 1, 27, 0), specs, 250.0, 16)
    src.set_declination(math.radians(12.0))
    follows, kept = (est.params.declination for est in src.estimators)
    assert math.degrees(follows) == pytest.approx(12.0)
    assert math.degrees(kept) == pytest.approx(90.0)


def test_an_imu_id_the_vehicle_does_not_have_is_told_once(caplog):
    """`--imu-id 3` on a vehicle with IMU 0 only refused every sample (counted as
    not_primary) and said nothing; now one warning names the ids it sends."""
    from bridge.vehicle.vehicle import WRONG_IMU_SAMPLES, Vehicle

    vehicle = Vehicle(1)
    with caplog.at_level(logging.WARNING, logger="bridge.vehicle"):
        for k in range(2 * WRONG_IMU_SAMPLES):
            used, _ = vehicle.choose_source(SourceKey(1, 1, 27, k % 2), k * 0.004,
                                            imu_id=3, preferred_msg=27, source_timeout_s=3.0)
            assert not used
    told = [r.getMessage() for r in caplog.records]
    assert told == [f"vehicle 1: no IMU with id 3 (--imu-id) in {WRONG_IMU_SAMPLES} samples; "
                    f"it sends id(s) 0, 1"]
