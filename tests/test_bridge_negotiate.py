"""IMU stream negotiation against the emulator's autopilot personalities, over real UDP.

The emulator reads its socket like the autopilot it plays: it answers
SET_MESSAGE_INTERVAL with COMMAND_ACK (PX4 refuses RAW_IMU with MAV_RESULT_FAILED,
streams HIGHRES_IMU at 50 Hz until asked) and changes its streams accordingly.
"""

from __future__ import annotations

import asyncio
import logging

import pytest
from bridge_support import UdpListener, async_test, running_bridge, wait_until

from bridge.app.emulator import emulator_declination_deg
from bridge.vehicle.ingest import IMU_MESSAGE_NAMES
from bridge.wire.mav import mavlink
from hil import Emulator, EmulatorConfig

IMU_RATE = 250.0


async def negotiate(autopilot: str, duration_s: float = 6.0, **settings):
    """A `flight` of the given personality into a bridge asking for 250 Hz; returns
    (final status of sysid 1, the bridge's primary source key, emulator stats)."""
    listener = UdpListener()
    await listener.start()
    cfg = EmulatorConfig(profile="flight", duration_s=duration_s, seed=2, fast=True,
                         autopilot=autopilot)
    async with running_bridge(estimators=["eskf"], imu_rate=IMU_RATE, max_source_rate=1e7,
                              declination_deg=emulator_declination_deg(),
                              **settings) as bridge:
        stats = await Emulator(cfg).run(targets=[("127.0.0.1", bridge.port)])
        await wait_until(lambda: bridge.vehicles and bridge.vehicles[1].last_imu > 0)
        await asyncio.sleep(0.3)
        bridge.publish_status()
        status = bridge.last_status[1]
        primary = bridge.vehicles[1].primary
    listener.close()
    return status, primary, stats


def warnings_of(caplog) -> list[str]:
    """The bridge's warnings about the stream; not "attitudes sent late", which a loaded
    test machine may cause and which says nothing about the negotiation."""
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING
            and r.name.startswith("bridge") and r.name != "bridge.app.lateness"]


@async_test
async def test_px4_ends_on_highres_imu_at_the_asked_rate_without_a_flag(caplog):
    with caplog.at_level(logging.INFO, logger="bridge"):
        status, primary, stats = await negotiate("px4")
    stream = status["imu_stream"]
    assert stream["message"] == stream["asked"] == "HIGHRES_IMU"
    assert stream["state"] == "accepted" and not stream["below_request"]
    assert stream["achieved_hz"] == pytest.approx(IMU_RATE, rel=0.02)
    assert primary.msg == IMU_MESSAGE_NAMES["HIGHRES_IMU"]
    assert stream["refused"] == [] and not warnings_of(caplog)
    # The velocity streams were asked for too, after the IMU, and accepted.
    assert stream["aiding_streams"] == {"LOCAL_POSITION_NED": "MAV_RESULT_ACCEPTED",
                                        "GPS_RAW_INT": "MAV_RESULT_ACCEPTED"}
    # IMU, two velocity streams, the landed state (EXTENDED_SYS_STATE), the two
    # references of the live comparison (its own attitude, the simulator's truth) and
    # the raw magnetometer (SCALED_IMU, without PX4's bias estimate: imu.px4_mag)
    assert stream["flight_state_stream"] == "MAV_RESULT_ACCEPTED"
    assert stream["reference_streams"] == {"ATTITUDE_QUATERNION": "MAV_RESULT_ACCEPTED",
                                           "HIL_STATE_QUATERNION": "MAV_RESULT_ACCEPTED"}
    assert stream["raw_mag_stream"] == "MAV_RESULT_ACCEPTED"
    assert stats.requests.interval_accepted == 7 and stats.requests.interval_refused == 0
    # The emulator really streamed at 250 Hz after the request (50 Hz before it).
    assert stats.messages["HIGHRES_IMU"] > 0.8 * IMU_RATE * 6.0


@async_test
async def test_ardupilot_ends_on_raw_imu_read_in_its_units(caplog):
    with caplog.at_level(logging.INFO, logger="bridge"):
        status, primary, _ = await negotiate("ardupilot", duration_s=8.0)
    stream = status["imu_stream"]
    assert stream["message"] == "RAW_IMU" and stream["state"] == "accepted"
    assert stream["achieved_hz"] == pytest.approx(IMU_RATE, rel=0.02)
    assert primary.msg == IMU_MESSAGE_NAMES["RAW_IMU"]
    assert status["board"] == "ardupilot" and not warnings_of(caplog)
    # mG / mrad/s / mGauss in FRD read as such: the estimate follows the truth (an
    # uncalibrated board converging over these 8 s: measured 2.2°, gate 1.5x); read as
    # GY-86 counts (chip axes RFU) it would be upside down.
    truth = status["compare"]["truth"]["eskf"]
    assert truth["inclination_deg"] < 3.3 and truth["total_deg"] < 3.3, truth


@async_test
async def test_refused_request_is_logged_and_the_next_candidate_asked(caplog):
    with caplog.at_level(logging.INFO, logger="bridge"):
        status, primary, stats = await negotiate("px4", imu_message="RAW_IMU,HIGHRES_IMU")
    warned = warnings_of(caplog)
    assert any("refused RAW_IMU" in w and "MAV_RESULT_FAILED" in w and
               "asking for HIGHRES_IMU" in w for w in warned), warned
    stream = status["imu_stream"]
    assert stream["refused"] == ["RAW_IMU at 250 Hz: MAV_RESULT_FAILED"]
    assert stream["message"] == "HIGHRES_IMU" and stream["state"] == "accepted"
    assert stream["achieved_hz"] == pytest.approx(IMU_RATE, rel=0.02)
    assert stats.requests.interval_refused == 1
    assert primary.msg == IMU_MESSAGE_NAMES["HIGHRES_IMU"]


@async_test
async def test_forced_message_refused_leaves_the_vehicle_stream_with_a_rate_warning(caplog):
    with caplog.at_level(logging.INFO, logger="bridge"):
        status, primary, _ = await negotiate("px4", imu_message="RAW_IMU")
    warned = warnings_of(caplog)
    assert any("refused RAW_IMU" in w and "no other IMU message" in w for w in warned)
    assert any("HIGHRES_IMU at 50 Hz, below the 250 Hz asked" in w for w in warned), warned
    stream = status["imu_stream"]
    assert stream["state"] == "refused" and stream["below_request"]
    assert stream["message"] == "HIGHRES_IMU" and stream["forced"]
    assert stream["achieved_hz"] == pytest.approx(50.0, rel=0.02)
    assert primary.msg == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU


@async_test
async def test_vehicle_that_never_answers_is_used_as_it_streams(caplog):
    """A PX4 heartbeat, a RAW_IMU stream and no COMMAND_ACK for us (one for another
    component's request is not ours): three tries, a warning, and its stream is used."""
    from bridge_support import MavSender, autopilot_heartbeat, euler_q, send_static

    with caplog.at_level(logging.INFO, logger="bridge"):
        async with running_bridge(estimators=["mahony"], imu_rate=IMU_RATE) as bridge:
            vehicle = MavSender(bridge.port)
            await vehicle.start()
            t = 1_000_000
            for _ in range(5):
                vehicle.send(autopilot_heartbeat())
                vehicle.send(mavlink.MAVLink_command_ack_message(
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_DENIED, 0, 0,
                    1, 190))
                t = await send_static(vehicle, euler_q(0, 0, 0), 1.0, t0_us=t)
            bridge.publish_status()
            stream = bridge.last_status[1]["imu_stream"]
            asked = vehicle.listener.of_type("COMMAND_LONG")
            vehicle.close()
    assert stream["state"] == "no_answer" and stream["message"] == "RAW_IMU"
    assert stream["refused"] == []  # the other component's DENIED was not taken as ours
    imu_asks = [c for c in asked if c.param1 == IMU_MESSAGE_NAMES["HIGHRES_IMU"]]
    assert len(imu_asks) == 3  # then on to the velocity streams (no answer either)
    # (on a slow machine the 5 s reach the GPS_RAW_INT fallback too)
    assert {c.param1 for c in asked} <= {IMU_MESSAGE_NAMES["HIGHRES_IMU"],
                                        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                                        mavlink.MAVLINK_MSG_ID_GPS_RAW_INT}
    assert any("does not answer SET_MESSAGE_INTERVAL" in w for w in warnings_of(caplog))
    assert stream["achieved_hz"] == pytest.approx(500.0, rel=0.02)


@pytest.mark.parametrize("text, bad", [
    ("RAW_IMU,FOO", "'FOO'"),
    ("foo, raw_imu", "'foo'"),
    ("RAW_IMU,FOO,BAR", "'FOO', 'BAR'"),
    ("FOO", "'FOO'"),
])
def test_forced_message_error_names_the_bad_name(text, bad):
    """``--imu-message RAW_IMU,FOO`` said the unknown name was 'RAW_IMU,FOO'."""
    from bridge.vehicle.negotiate import parse_forced

    with pytest.raises(ValueError) as info:
        parse_forced(text)
    message = str(info.value)
    assert f"unknown IMU message(s) {bad} in --imu-message {text!r}" in message
    assert f"valid: {sorted(IMU_MESSAGE_NAMES)}" in message and "\n" not in message


def test_forced_message_list_without_a_name_is_refused():
    from bridge.vehicle.negotiate import parse_forced

    with pytest.raises(ValueError, match=r"--imu-message ' , ' names no IMU message; valid: "):
        parse_forced(" , ")
    assert parse_forced(" raw_imu , HIGHRES_IMU ") == ("RAW_IMU", "HIGHRES_IMU")
