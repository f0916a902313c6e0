"""The live bridge follows the vehicle's flight state (imu.flight_state): it asks for the
landed state, believes only the vehicle's own autopilot, and passes every switch to the
estimators; a bare board leaves the decision to the data; a broken source falls back.

Real UDP, real pymavlink encoding, the real emulator (--fast) or a pymavlink vehicle.
"""

from __future__ import annotations

import asyncio
import json
import logging

import numpy as np
from bridge_support import (
    MavSender,
    UdpListener,
    async_test,
    running_bridge,
    send_static,
    stream_emulator,
)

from bridge.app.table import render
from bridge.wire.mav import mavlink
from estimators import quat as Q
from hil import EmulatorConfig
from imu import flight_state as fs

IN_AIR, ON_GROUND = mavlink.MAV_LANDED_STATE_IN_AIR, mavlink.MAV_LANDED_STATE_ON_GROUND


async def _emulate(cfg: EmulatorConfig, **settings) -> dict:
    listener = UdpListener()
    out_port = await listener.start()
    async with running_bridge(estimators=[], out_rate=50.0, imu_rate=cfg.imu_rate_hz,
                              max_source_rate=1e7, **settings) as bridge:
        await stream_emulator(bridge, cfg, out_port)
        bridge.publish_status()
        status = bridge.last_status[cfg.sysid]
        status["table"] = render(bridge)
    listener.close()
    return status


@async_test
async def test_a_flight_switches_the_drag_model_on_when_it_takes_off(tmp_path):
    """The emulator's `flight`: on the ground, armed at 3.5 s, airborne from 5 s. The
    state, its source and its switches show in the status file and the live table."""
    path = tmp_path / "status.json"
    status = await _emulate(EmulatorConfig(profile="flight", duration_s=20.0, seed=2,
                                           fast=True), status_file=str(path))
    on_disk = json.loads(path.read_text())["vehicles"]["1"]["flight_state"]
    assert on_disk["state"] == "airborne" and on_disk["board_switches"]
    assert "flight: airborne (landed state)" in status["table"]
    assert "in-flight model: eskf" in status["table"]
    fl = status["flight_state"]
    assert status["imu_stream"]["flight_state_stream"] == "MAV_RESULT_ACCEPTED"
    assert fl["state"] == "airborne" and fl["source"] == fs.SOURCE_LANDED
    states = [s for _, s in fl["board_switches"]]
    assert states[-2:] == ["on ground", "airborne"] and "unknown" not in states[1:]
    # the emulator takes off at 5 s (board time); the landed state is asked for after the
    # IMU stream is settled, and --fast runs the emulator's clock ahead of the bridge's
    t_air = fl["board_switches"][-1][0]
    assert 5.0 <= t_air <= 8.0
    assert fl["air_model"]["eskf"] is True
    assert status["vehicle"]["model"] == "multirotor"


@async_test
async def test_a_bare_board_leaves_it_to_the_data():
    """--no-flight-state: never the armed flag, EXTENDED_SYS_STATE refused."""
    status = await _emulate(EmulatorConfig(profile="flight", duration_s=20.0, seed=2,
                                           fast=True, flight_state=False))
    fl = status["flight_state"]
    assert status["imu_stream"]["flight_state_stream"] == "MAV_RESULT_DENIED"
    assert fl["state"] == "unknown" and fl["source"] == fs.SOURCE_DATA
    assert fl["board_switches"] == []
    assert fl["air_model"]["eskf"] is True  # in flight at 20 s: the data said so


@async_test
async def test_a_disarmed_hand_held_board_never_runs_the_drag_model():
    status = await _emulate(EmulatorConfig(profile="tilt", duration_s=10.0, seed=1,
                                           fast=True, autopilot="px4"))
    fl = status["flight_state"]
    assert fl["state"] == "on ground" and fl["armed"] is False
    assert "airborne" not in [s for _, s in fl["board_switches"]]
    assert fl["air_model"]["eskf"] is False


async def _static_vehicle(bridge, sender: MavSender, extra, seconds: float = 3.0) -> None:
    """A level PX4 quadrotor, armed, streaming RAW_IMU; ``extra(k)`` sends more."""
    q = Q.identity()
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                           mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0, 4, 3)
    t = 1_000_000
    for k in range(int(seconds * 10)):
        sender.send(hb)
        extra(k)
        t = await send_static(sender, q, 0.1, t0_us=t)
    await asyncio.sleep(0.2)
    bridge.publish_status()


@async_test
async def test_a_spoofed_landed_state_from_another_system_changes_nothing():
    async with running_bridge(estimators=["eskf"]) as bridge:
        vehicle = MavSender(bridge.port, sysid=1, compid=1)
        spoofer = MavSender(bridge.port, sysid=99, compid=1)
        await vehicle.start()
        await spoofer.start()

        def extra(k: int) -> None:
            vehicle.send(mavlink.MAVLink_extended_sys_state_message(0, ON_GROUND))
            spoofer.send(mavlink.MAVLink_extended_sys_state_message(0, IN_AIR))

        await _static_vehicle(bridge, vehicle, extra)
        status = bridge.last_status[1]
        vehicle.close()
        spoofer.close()
    fl = status["flight_state"]
    assert fl["state"] == "on ground" and fl["reports"] >= 25
    assert "airborne" not in [s for _, s in fl["board_switches"]]
    assert 99 not in bridge.vehicles


@async_test
async def test_a_flapping_landed_state_falls_back_to_the_data(caplog):
    caplog.set_level(logging.WARNING)
    async with running_bridge(estimators=["eskf"]) as bridge:
        vehicle = MavSender(bridge.port, sysid=1, compid=1)
        await vehicle.start()

        def extra(k: int) -> None:  # in the air, on the ground, in the air, ...
            vehicle.send(mavlink.MAVLink_extended_sys_state_message(
                0, IN_AIR if k % 2 else ON_GROUND))

        await _static_vehicle(bridge, vehicle, extra)
        status = bridge.last_status[1]
        vehicle.close()
    fl = status["flight_state"]
    assert fl["flap_fallbacks"] == 1 and fl["source"] == fs.SOURCE_FLAPPING
    assert fl["state"] == "unknown"
    states = [s for _, s in fl["board_switches"]]
    assert "airborne" not in states and len(states) <= 2
    assert any("landed state changed" in r.getMessage() for r in caplog.records)
    assert np.isfinite(status["samples"])
