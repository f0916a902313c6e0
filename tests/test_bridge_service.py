"""The bridge over real UDP sockets with a pymavlink 'vehicle' and a pymavlink listener."""

from __future__ import annotations

import asyncio
import logging
import math
import warnings

import numpy as np
import pytest
from bridge_support import (
    MavSender,
    UdpListener,
    accepted,
    angle_deg,
    async_test,
    attitude_of,
    autopilot_heartbeat,
    euler_q,
    raw_imu,
    rotating,
    running_bridge,
    send_rotating,
    send_static,
    wait_until,
)

from bridge.wire.codec import signing_key_from_text
from bridge.wire.mav import mavlink

#: mostly waits on real time: spread among computing tests (conftest)
pytestmark = pytest.mark.realtime

OMEGA = np.radians([0.0, 0.0, 40.0])  # yaw rate of the test motion


def scored(listener: UdpListener, q0, omega, sysid=1, t0_us=1_000_000):
    """Angle (deg) between each ATTITUDE_QUATERNION and the motion's truth at its stamp."""
    msgs = listener.of_type("ATTITUDE_QUATERNION", sysid)
    est = attitude_of(msgs)
    truth = np.array([rotating(q0, omega, m.time_boot_ms * 1e-3 - t0_us * 1e-6) for m in msgs])
    return msgs, angle_deg(est, truth)


@async_test
async def test_attitude_out_heartbeat_and_rate():
    listener = UdpListener()
    out_port = await listener.start()
    q0 = euler_q(12.0, -8.0, 20.0)
    async with running_bridge(estimators=["mahony", "quaternion"],
                              outs=[f"udpout:127.0.0.1:{out_port}"], out_rate=50.0) as bridge:
        vehicle = MavSender(bridge.port)
        await vehicle.start()
        await send_rotating(vehicle, q0, OMEGA, 3.0)
        await wait_until(lambda: accepted(bridge) == 1500)
        await asyncio.sleep(1.2)  # at least one more heartbeat
        status = bridge.last_status[1]
    msgs, err = scored(listener, q0, OMEGA)
    assert len(msgs) > 100
    assert np.max(err[10:]) < 1.5, err.max()
    assert {m.get_srcComponent() for m in msgs} == {191}
    assert {m.get_srcSystem() for m in msgs} == {1}
    # time_boot_ms is the board time of a sample (2 ms grid from t0 = 1 s), rate 50 Hz.
    stamps = np.array([m.time_boot_ms for m in msgs])
    assert np.all((stamps - 1000) % 2 == 0)
    assert np.median(np.diff(stamps)) == 20
    # Rates are the bias-corrected gyro: the yaw rate of the motion.
    assert np.median([m.yawspeed for m in msgs]) == pytest.approx(OMEGA[2], abs=0.01)
    att = listener.of_type("ATTITUDE")
    assert len(att) == len(msgs)
    q_from_euler = np.array([euler_q(*np.degrees([a.roll, a.pitch, a.yaw])) for a in att])
    assert np.max(angle_deg(q_from_euler, attitude_of(msgs))) < 0.01
    hb = [m for m in listener.of_type("HEARTBEAT") if m.get_srcComponent() == 191]
    assert len(hb) >= 3
    assert hb[0].type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert hb[0].autopilot == mavlink.MAV_AUTOPILOT_INVALID
    # The vehicle side of the connection gets the same output (udpin answers its peer).
    assert len(vehicle.listener.of_type("ATTITUDE_QUATERNION")) == len(msgs)
    assert status["samples"] == 1500 and status["sent"] == len(msgs)
    vehicle.close()
    listener.close()


@async_test
async def test_requests_imu_stream_and_repeats_when_it_stops():
    async with running_bridge(imu_rate=200.0, imu_message="HIGHRES_IMU") as bridge:
        vehicle = MavSender(bridge.port)
        await vehicle.start()
        for _ in range(4):  # heartbeats only, no IMU: the request must be repeated
            vehicle.send(mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4, 3))
            await asyncio.sleep(1.0)
        cmds = vehicle.listener.of_type("COMMAND_LONG")
    assert len(cmds) >= 2
    c = cmds[0]
    assert c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert c.param1 == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU and c.param2 == pytest.approx(5000.0)
    assert (c.target_system, c.target_component, c.get_srcComponent()) == (1, 1, 191)
    vehicle.close()


@async_test
async def test_two_vehicles_on_one_port_are_estimated_separately():
    qa, qb = euler_q(10.0, 5.0, 30.0), euler_q(-20.0, 15.0, -120.0)
    async with running_bridge(out_rate=0.0, vehicles=[1, 2]) as bridge:
        va, vb = MavSender(bridge.port, sysid=1), MavSender(bridge.port, sysid=2)
        await va.start()
        await vb.start()
        await asyncio.gather(send_rotating(va, qa, OMEGA, 2.0),
                             send_rotating(vb, qb, -OMEGA, 2.0))
        await wait_until(lambda: len(va.listener.of_type("ATTITUDE_QUATERNION")) >= 2000 and
                         len(vb.listener.of_type("ATTITUDE_QUATERNION")) >= 2000)
        bridge.publish_status()
        status = dict(bridge.last_status)
    # Each vehicle's own socket sees both vehicles' output (udpin answers all peers).
    for sender, q0, omega, sysid in ((va, qa, OMEGA, 1), (vb, qb, -OMEGA, 2)):
        msgs, err = scored(sender.listener, q0, omega, sysid)
        assert len(msgs) == 1000  # out_rate 0: every sample
        assert np.max(err[5:]) < 1.5
    assert {s for s in status} == {1, 2}
    va.close()
    vb.close()


@async_test
async def test_bad_input_is_counted_never_crashes():
    q0 = euler_q(5.0, -5.0, 45.0)
    async with running_bridge(out_rate=0.0, estimators=["mahony"]) as bridge:
        v = MavSender(bridge.port)
        await v.start()
        t = await send_static(v, q0, 0.5, t0_us=10_000_000)  # 250 good samples
        step = 2000
        # Corrupt bytes: random junk, a packet with a flipped payload byte, a truncated one.
        v.send_bytes(b"\xfd\x09junk\x00\xff" * 3)
        bad = bytearray(v.pack(raw_imu(t, q0)))
        bad[15] ^= 0x55
        v.send_bytes(bytes(bad))
        v.send_bytes(v.pack(raw_imu(t, q0))[:12])
        # Duplicate (same packet twice), reordered pair, isolated jump and step back.
        pkt = v.pack(raw_imu(t, q0))
        v.send_bytes(pkt)
        v.send_bytes(pkt)
        a, b = v.pack(raw_imu(t + step, q0)), v.pack(raw_imu(t + 2 * step, q0))
        v.send_bytes(b)
        v.send_bytes(a)
        v.send(raw_imu(t + 3 * step + 5_000_000, q0))  # 5 s ahead, once
        v.send(raw_imu(t + 3 * step, q0))
        v.send(raw_imu(t - 3_000_000, q0))  # 3 s back, once
        v.send(raw_imu(t + 4 * step, q0))
        # NaN via HIGHRES_IMU floats (another stream of the vehicle than its primary
        # RAW_IMU: refused as such), a saturated accelerometer, a gyro beyond full scale.
        v.send(mavlink.MAVLink_highres_imu_message(
            t + 5 * step, 0, 0, -9.8, math.nan, 0, 0, 0.2, 0, 0.4, 0, 0, 0, 0, 0, 0))
        sat = raw_imu(t + 6 * step, q0)
        sat.xacc = 32767
        v.send(sat)
        t = t + 7 * step
        await asyncio.sleep(0.2)
        # The peer vanishes for 1.5 s (board clock keeps running), then comes back: the
        # estimate starts over and is held back while it settles (1 s), then sent.
        await asyncio.sleep(1.5)
        back_ms = (t + 1_700_000) // 1000
        t = await send_static(v, q0, 1.6, t0_us=t + 1_700_000)
        last_ms = (t - 2000) // 1000
        await wait_until(lambda: any(m.time_boot_ms == last_ms for m in
                                     v.listener.of_type("ATTITUDE_QUATERNION")[-5:]))
        bridge.publish_status()
        status = bridge.last_status[1]
    drops, flags, conn = status["drops"], status["flags"], status["connection"]
    assert drops["duplicate"] == 1
    assert drops["reordered"] == 1
    assert drops["jump"] == 1 and drops["backwards"] == 1
    assert status["refused"]["not_primary"] == 1
    assert flags["acc_saturated"] == 1
    assert conn["bad_crc"] == 1 and conn["truncated"] == 1
    assert conn["gate"]["not_vehicle"] == 1  # the junk's "header" names no vehicle
    assert flags["gap"] == 1 and flags["reinit"] == 1 and status["restarts"] == 1
    assert 400 <= status["held_initialising"] <= 520  # ~1 s at 500 Hz
    msgs = v.listener.of_type("ATTITUDE_QUATERNION")
    after = [m for m in msgs if m.time_boot_ms >= back_ms]
    assert after and min(m.time_boot_ms for m in after) >= back_ms + 990
    assert np.max(angle_deg(attitude_of(msgs[-50:]), q0)) < 1.0
    assert all(np.all(np.isfinite([m.q1, m.q2, m.q3, m.q4])) for m in msgs)
    v.close()


@async_test
async def test_signing_rejects_unsigned_and_signs_output(tmp_path):
    key_file = tmp_path / "key"
    key_file.write_text("bridge test passphrase")
    key = signing_key_from_text("bridge test passphrase")
    q0 = euler_q(0.0, 10.0, 0.0)
    async with running_bridge(signing_key=f"file:{key_file}", out_rate=0.0) as bridge:
        intruder = MavSender(bridge.port, sysid=7)
        await intruder.start()
        await send_static(intruder, q0, 0.2)  # 100 unsigned samples
        good = MavSender(bridge.port, sysid=1, signing_key=key)
        await good.start()
        await send_static(good, q0, 0.2)
        await wait_until(lambda: len(good.listener.of_type("ATTITUDE_QUATERNION")) >= 100)
        conn = bridge.link_status()
        vehicles = set(bridge.vehicles)
    assert conn["unsigned_rejected"] == 100
    assert vehicles == {1}
    msgs = good.listener.of_type("ATTITUDE_QUATERNION")
    assert len(msgs) == 100 and all(m.get_signed() for m in msgs)
    intruder.close()
    good.close()


@async_test
async def test_live_comparison_with_the_vehicles_late_stamped_attitude():
    """The vehicle's own ATTITUDE_QUATERNION stamped 30 ms late (publish time): the
    bridge finds the offset and scores its estimate at it."""
    q0 = euler_q(5.0, 5.0, 0.0)
    async with running_bridge(estimators=["quaternion"], window_s=3.0) as bridge:
        v = MavSender(bridge.port)
        await v.start()
        rate, t0 = 500.0, 1_000_000
        for i in range(int(3.0 * rate)):
            t_us = t0 + i * 2000
            q = rotating(q0, OMEGA, (t_us - t0) * 1e-6)
            v.send(raw_imu(t_us, q, OMEGA))
            if i % 5 == 0:  # the autopilot's own estimate at 100 Hz, stamped +30 ms
                v.send(mavlink.MAVLink_attitude_quaternion_message(
                    (t_us + 30_000) // 1000, *q, 0, 0, 0, [1, 0, 0, 0]))
            if i % 25 == 24:
                await asyncio.sleep(0.05)
        await wait_until(lambda: accepted(bridge) == 1500)
        bridge.publish_status()
        vehicle_cmp = bridge.last_status[1]["compare"]["vehicle"]["quaternion"]
    assert vehicle_cmp["lag_s"] == pytest.approx(-0.030, abs=0.005)
    assert vehicle_cmp["total_deg"] < 0.5
    v.close()


@async_test
async def test_the_service_says_what_happens(caplog):
    """Without the table the log tells the story: the vehicle and its stream, data
    stopping and coming back, a gap and a reboot restarting the estimate."""
    caplog.set_level(logging.INFO, logger="bridge")
    q0 = euler_q(0.0, 5.0, 10.0)
    async with running_bridge(estimators=["quaternion"], status_period_s=0.2,
                              source_timeout_s=0.6) as bridge:
        v = MavSender(bridge.port)
        await v.start()
        v.send(autopilot_heartbeat())
        t = await send_static(v, q0, 0.6, t0_us=50_000_000)
        await asyncio.sleep(1.0)  # silent: more than source_timeout_s and reinit_gap_s
        t = await send_static(v, q0, 0.6, t0_us=t + 1_000_000)
        await send_static(v, q0, 1.4, t0_us=200_000)  # rebooted: board time from 0.2 s
        await wait_until(lambda: bridge.last_status[1]["flags"]["reboot"] == 1, 3.0)
    text = [r.getMessage() for r in caplog.records]
    levels = {r.getMessage(): r.levelno for r in caplog.records}

    def said(fragment: str, level: int) -> bool:
        return any(fragment in m and levels[m] == level for m in text)

    assert said("vehicle 1: PX4 autopilot (component 1)", logging.INFO), text
    assert said("vehicle 1: estimating from RAW_IMU at", logging.INFO), text
    assert said("vehicle 1: no IMU data for", logging.WARNING), text
    assert said("vehicle 1: IMU data again after", logging.INFO), text
    assert said("vehicle 1: IMU data resumed after a gap (board time 50.", logging.WARNING)
    assert said("vehicle 1 rebooted (board time went back from", logging.WARNING), text
    v.close()


@async_test
async def test_the_vehicles_ids_from_another_address_are_refused(caplog):
    """A forger on another socket sends with the vehicle's own system and component id
    while the vehicle talks: its gyro (200 °/s) never reaches the estimate, its
    heartbeats do not take the stream requests, and it is counted and warned about.
    Once the vehicle's address has been silent for the source timeout, a new address is
    the vehicle's own (an autopilot restarted on another port), and that is logged."""
    caplog.set_level(logging.WARNING, logger="bridge")
    q0 = euler_q(5.0, -5.0, 45.0)
    spin = np.radians([0.0, 200.0, 0.0])
    async with running_bridge(out_rate=0.0, estimators=["mahony"],
                              source_timeout_s=0.6) as bridge:
        vehicle, forger = MavSender(bridge.port), MavSender(bridge.port)
        await vehicle.start()
        await forger.start()
        vehicle.send(autopilot_heartbeat())
        t = await send_static(vehicle, q0, 0.5, t0_us=10_000_000)
        for i in range(500):  # the forger's samples 1 ms after each of the vehicle's
            vehicle.send(raw_imu(t, q0))
            forger.send(raw_imu(t + 1000, q0, spin))
            if i % 100 == 0:
                vehicle.send(autopilot_heartbeat())
                forger.send(autopilot_heartbeat())
            t += 2000
            if i % 25 == 24:
                await asyncio.sleep(0.05)
        last_ms = (t - 2000) // 1000
        await wait_until(lambda: any(m.time_boot_ms == last_ms for m in
                                     vehicle.listener.of_type("ATTITUDE_QUATERNION")[-5:]))
        bridge.publish_status()
        refused = bridge.last_status[1]["refused"]["other_address"]
        forged_commands = len(forger.listener.of_type("COMMAND_LONG"))
        # the vehicle goes silent; then its ids come from the other socket only
        await asyncio.sleep(1.0)
        await send_static(forger, q0, 0.6, t0_us=t + 1_000_000)
        bridge.publish_status()
        refused_after_move = bridge.last_status[1]["refused"]["other_address"]
    msgs = [m for m in vehicle.listener.of_type("ATTITUDE_QUATERNION")
            if m.time_boot_ms <= last_ms]
    assert len(msgs) >= 700
    assert np.max(angle_deg(attitude_of(msgs[5:]), q0)) < 1.0
    assert refused == 500 + 5  # every forged sample and heartbeat
    assert vehicle.listener.of_type("COMMAND_LONG") and forged_commands == 0
    assert refused_after_move == refused
    text = [r.getMessage() for r in caplog.records]
    assert any("vehicle 1: its system and component id also come from 127.0.0.1:" in m
               for m in text), text
    assert any("vehicle 1 now talks from 127.0.0.1:" in m for m in text), text
    vehicle.close()
    forger.close()


@async_test
async def test_references_that_are_no_attitude_are_refused_and_counted():
    """A zero quaternion as the truth or as the vehicle's own attitude, and a NaN
    ATTITUDE, are no attitude: counted (refused.refs_invalid), never compared (they
    scored 180° of inclination and leaked numpy's divide warning), while the valid
    truth between them is still scored."""
    q0 = euler_q(5.0, 5.0, 0.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        async with running_bridge(estimators=["quaternion"], window_s=2.0) as bridge:
            v = MavSender(bridge.port)
            await v.start()
            for i in range(1000):
                t_us = 1_000_000 + i * 2000
                v.send(raw_imu(t_us, q0))
                if i % 5 == 0:
                    q_truth = q0 if i % 10 == 0 else [0.0, 0.0, 0.0, 0.0]
                    v.send(mavlink.MAVLink_hil_state_quaternion_message(
                        t_us, q_truth, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
                    v.send(mavlink.MAVLink_attitude_quaternion_message(
                        t_us // 1000, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, [1, 0, 0, 0]))
                    v.send(mavlink.MAVLink_attitude_message(
                        t_us // 1000, math.nan, 0.0, 0.0, 0, 0, 0))
                if i % 25 == 24:
                    await asyncio.sleep(0.05)
            await wait_until(lambda: accepted(bridge) == 1000)
            bridge.publish_status()
            status = bridge.last_status[1]
    assert status["refused"]["refs_invalid"] == 100 + 200 + 200
    truth = status["compare"]["truth"]["quaternion"]
    assert truth["inclination_deg"] < 0.5 and truth["samples"] > 0
    assert "vehicle" not in status["compare"] or not status["compare"]["vehicle"]
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], caught
    v.close()


@async_test
async def test_a_vehicle_over_its_rate_budget_is_told_and_not_counted_as_link_loss(caplog):
    """The vehicle itself sends faster than --max-source-rate: what the gate refuses is
    warned about and counted as over budget, not as link loss (its sequence numbers
    have gaps there only because the bridge refused those datagrams)."""
    caplog.set_level(logging.WARNING, logger="bridge")
    q0 = euler_q(5.0, -5.0, 45.0)
    async with running_bridge(out_rate=0.0, estimators=["mahony"], max_source_rate=400.0,
                              status_period_s=0.2) as bridge:
        v = MavSender(bridge.port)
        await v.start()
        await send_static(v, q0, 2.0, rate_hz=1000.0, burst=50)
        await asyncio.sleep(0.5)
        bridge.publish_status()
        status = bridge.last_status[1]
    link, gate = status["link"], status["connection"]["gate"]
    assert gate["over_budget"] > 500 and link["over_budget"] == gate["over_budget"]
    assert link["lost"] == 0
    assert any("refused: over --max-source-rate (400/s per sender), the last from system "
               "1 component 1" in r.getMessage() for r in caplog.records)
    v.close()


@async_test
async def test_a_stream_of_unusable_samples_is_not_called_a_lost_link(caplog):
    """HIGHRES_IMU keeps arriving with a NaN gyro: the warning says the samples are
    refused and why, not that the link was lost."""
    caplog.set_level(logging.WARNING, logger="bridge")
    async with running_bridge(estimators=["mahony"], status_period_s=0.2,
                              source_timeout_s=0.6) as bridge:
        v = MavSender(bridge.port)
        await v.start()
        v.send(autopilot_heartbeat())
        for i in range(int(2.2 * 250)):
            gyro = math.nan if i >= 150 else 0.0
            v.send(mavlink.MAVLink_highres_imu_message(
                1_000_000 + i * 4000, 0.0, 0.0, -9.8, gyro, 0.0, 0.0, 0.2, 0.0, 0.4,
                1013.0, 0.0, 0.0, 25.0, 0x1FFF, 0))
            if i % 25 == 24:
                await asyncio.sleep(0.1)
        await asyncio.sleep(0.3)
        bridge.publish_status()
        drops = bridge.last_status[1]["drops"]
    text = [r.getMessage() for r in caplog.records]
    assert drops["nonfinite"] >= 300
    assert any("vehicle 1: IMU messages arrive but none was usable for" in m and
               "(refused: nonfinite " in m for m in text), text
    assert not any("link lost" in m for m in text), text
    v.close()


@async_test
async def test_an_ardupilot_heartbeat_makes_its_scaled_imu_read_as_truncated():
    """What an autopilot's SCALED_IMU integers mean follows its heartbeat: ArduPilot's
    are truncated (read as the middle of their step), PX4's are not."""
    async with running_bridge(out_rate=0.0, estimators=["mahony"], vehicles=[1, 2]) as bridge:
        ardupilot, px4 = MavSender(bridge.port, sysid=1), MavSender(bridge.port, sysid=2)
        await ardupilot.start()
        await px4.start()
        ardupilot.send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3))
        px4.send(autopilot_heartbeat())
        assert await wait_until(lambda: bridge.ingest.scaled_truncated(1))
        await asyncio.sleep(0.2)
        assert not bridge.ingest.scaled_truncated(2)
    ardupilot.close()
    px4.close()
