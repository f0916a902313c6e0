"""The emulator behaves like a flight controller on its link: it reads its socket,
answers SET_MESSAGE_INTERVAL and parameter requests like PX4 / ArduPilot / the seeds'
board, honours the asked rates and sends its own onboard attitude. Real UDP sockets,
real pymavlink on the listener's side."""

from __future__ import annotations

import asyncio
import math
import os

import numpy as np
import pytest
from hil_support import Receiver

from estimators import metrics
from hil import Emulator, EmulatorConfig, GpsConfig, simulate
from hil.environment import G
from hil.personality import personality
from hil.source import CHUNK_S
from hil.streams import StreamTable

os.environ["MAVLINK20"] = "1"
import itertools

from pymavlink.dialects.v20 import common as mavlink

SET_INTERVAL = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL


def interval_request(msg_id: int, interval_us: float, sysid: int = 1):
    return mavlink.MAVLink_command_long_message(sysid, 1, SET_INTERVAL, 0, msg_id, interval_us,
                                                0, 0, 0, 0, 0)


def param_read(name: str, sysid: int = 1):
    return mavlink.MAVLink_param_request_read_message(sysid, 1, name.encode(), -1)


def run_with_requests(cfg: EmulatorConfig, requests: list, after_s: float = 0.0
                      ) -> tuple[Emulator, Receiver, float]:
    """Stream cfg to a listener that sends ``requests`` to the emulator once the stream
    has begun (and ``after_s`` of board time has gone by); returns the board time [µs]
    of the last message received before the requests went out."""
    rx = Receiver.open()
    sent_at: list[int] = []

    async def scenario() -> Emulator:
        loop = asyncio.get_running_loop()
        rx.attach(loop)
        emu = Emulator(cfg)
        task = asyncio.create_task(emu.run([("127.0.0.1", rx.port)]))
        try:
            while True:
                stamps = [m.time_usec for m in rx.of_type("HIL_STATE_QUATERNION")]
                if stamps and stamps[-1] - stamps[0] >= after_s * 1e6:
                    break
                await asyncio.sleep(0.002)
            sent_at.append(stamps[-1])
            for msg in requests:
                rx.send(msg)
            await task
            await asyncio.sleep(0.05)
        finally:
            rx.detach(loop)
        return emu

    emu = asyncio.run(scenario())
    return emu, rx, sent_at[0]


def acks(rx: Receiver) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for m in rx.of_type("COMMAND_ACK"):
        out.setdefault(m.command, []).append(m.result)
    return out


def truth_by_ms(rx: Receiver) -> dict[int, list[float]]:
    return {m.time_usec // 1000: m.attitude_quaternion for m in rx.of_type("HIL_STATE_QUATERNION")}


# ---- PX4 ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def px4_flight():
    """A PX4 board in flight; the listener asks for RAW_IMU (refused) and HIGHRES_IMU at
    200 Hz, and reads the declination parameter."""
    cfg = EmulatorConfig(profile="flight", autopilot="px4", duration_s=30.0, seed=2, fast=True,
                         gps=GpsConfig(), truth_rate_hz=250.0)
    requests = [interval_request(mavlink.MAVLINK_MSG_ID_RAW_IMU, 1000),
                interval_request(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 5000),
                param_read("EKF2_MAG_DECL"),
                mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL,
                                                     0, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU,
                                                     0, 0, 0, 0, 0, 0),
                mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_NAV_TAKEOFF, 0,
                                                     0, 0, 0, 0, 0, 0, 0),
                interval_request(mavlink.MAVLINK_MSG_ID_RAW_IMU, 1000, sysid=9)]  # not us
    return cfg, *run_with_requests(cfg, requests, after_s=1.0)


@pytest.mark.xdist_group("hil_px4_flight")  # one worker builds the fixture once
def test_px4_heartbeat_and_default_streams(px4_flight):
    _cfg, _, rx, sent_at = px4_flight
    hb = rx.of_type("HEARTBEAT")[0]
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert not rx.of_type("RAW_IMU")
    before = [m.time_usec for m in rx.of_type("HIGHRES_IMU") if m.time_usec <= sent_at]
    assert len(before) >= 40
    assert np.all(np.diff(before) == 20_000)  # 50 Hz until asked


@pytest.mark.xdist_group("hil_px4_flight")  # one worker builds the fixture once
def test_px4_refuses_raw_imu_and_honours_the_highres_rate(px4_flight):
    cfg, emu, rx, sent_at = px4_flight
    got = acks(rx)
    # RAW_IMU refused (FAILED), HIGHRES_IMU accepted; GET answered; the take-off command
    # unsupported; the request for system 9 ignored (no answer)
    assert got == {SET_INTERVAL: [mavlink.MAV_RESULT_FAILED, mavlink.MAV_RESULT_ACCEPTED],
                   mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: [mavlink.MAV_RESULT_ACCEPTED],
                   mavlink.MAV_CMD_NAV_TAKEOFF: [mavlink.MAV_RESULT_UNSUPPORTED]}
    ack = rx.of_type("COMMAND_ACK")[0]
    assert (ack.target_system, ack.target_component) == (255, 190)  # back to the asker
    assert ack.get_srcSystem() == cfg.sysid
    assert rx.of_type("MESSAGE_INTERVAL")[0].interval_us == 5000
    assert emu.stats.requests.interval_refused == 1 and emu.stats.requests.ignored == 1
    assert not rx.of_type("RAW_IMU")
    # HIGHRES_IMU at 200 Hz without exception from the chunk after the one being made
    # when the emulator took the request (its ACCEPTED answer marks that point in the
    # stream: in --fast mode board time runs ahead of the wall clock, so the board time
    # at which it reads its socket depends on the machine's load, not on the emulator).
    msgs = [r.msg for r in rx.valid]
    accepted = next(i for i, m in enumerate(msgs) if m.get_type() == "COMMAND_ACK"
                    and m.result == mavlink.MAV_RESULT_ACCEPTED and m.command == SET_INTERVAL)
    taken_at = max(m.time_usec for m in msgs[:accepted]
                   if m.get_type() in ("HIGHRES_IMU", "HIL_STATE_QUATERNION"))
    stamps = np.array([m.time_usec for m in rx.of_type("HIGHRES_IMU")])
    off_rate = np.nonzero(np.diff(stamps) != 5_000)[0]
    switch = stamps[off_rate[-1] + 1]
    assert sent_at <= taken_at and sent_at < switch <= taken_at + 2 * CHUNK_S * 1e6, \
        (sent_at, taken_at, switch)
    late = stamps[stamps >= switch]
    assert len(late) > 0.9 * 200 * (stamps[-1] - sent_at) * 1e-6
    assert np.all(np.diff(late) == 5_000)
    # the link's sequence numbers have no gap although replies were slotted in
    seqs = [r.seq for r in rx.valid]
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(seqs))


@pytest.mark.xdist_group("hil_px4_flight")  # one worker builds the fixture once
def test_px4_highres_imu_is_si_frd_with_its_bias_removed(px4_flight):
    cfg, _, rx, _ = px4_flight
    msgs = rx.of_type("HIGHRES_IMU")
    rec = simulate(cfg)
    k = {t: i for i, t in enumerate(rec.time_us.tolist())}
    idx = np.array([k[m.time_usec] for m in msgs])
    acc = np.array([[m.xacc, m.yacc, m.zacc] for m in msgs])
    gyr = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in msgs])
    assert np.allclose(acc, rec.acc[idx], atol=1e-5)
    # the board's gyro offset (1 °/s per axis) is mostly gone after convergence
    late = rec.t_s[idx] > 15.0
    raw_err = np.abs(np.mean(rec.gyr[idx][late] - rec.truth_rates[idx][late], axis=0))
    px4_err = np.abs(np.mean(gyr[late] - rec.truth_rates[idx][late], axis=0))
    assert np.all(px4_err < 0.5 * raw_err + math.radians(0.1))
    # fields_updated: accel/gyro always, magnetometer and barometer when new since the last
    fields = np.array([m.fields_updated for m in msgs])
    assert np.all(fields & 0x3F == 0x3F)
    mag_share = np.mean(fields & 0x1C0 == 0x1C0)
    assert 0.05 < mag_share < 0.3  # 15 Hz magnetometer among 50-200 Hz messages
    assert np.mean(fields & 0x200 == 0x200) > 0.2  # 50 Hz barometer


@pytest.mark.xdist_group("hil_px4_flight")  # one worker builds the fixture once
def test_px4_onboard_attitude_is_stamped_and_close_to_the_truth(px4_flight):
    _cfg, _, rx, _ = px4_flight
    truth = truth_by_ms(rx)
    aq = [m for m in rx.of_type("ATTITUDE_QUATERNION") if m.time_boot_ms in truth]
    assert len(aq) == len(rx.of_type("ATTITUDE_QUATERNION"))  # stamped on the board clock
    assert len(aq) > 0.95 * 50 * 30
    est = np.array([[m.q1, m.q2, m.q3, m.q4] for m in aq])
    ref = np.array([truth[m.time_boot_ms] for m in aq])
    t_ms = np.array([m.time_boot_ms for m in aq])
    converged = t_ms > t_ms[0] + 10_000
    err = metrics.rms_errors(est[converged], ref[converged])
    # An unaided Mahony-type filter with PX4's attitude_estimator_q gains on a quadrotor
    # flight (accelerating for seconds): a few degrees of tilt (4.7° here; such filters
    # do 3.5-9° on PX4's SIH flights), heading from the magnetometer with the WMM
    # declination and a slowly learned gyro bias (6.9° here).
    assert err.inclination_deg < 6.0 and err.heading_deg < 10.0, err
    att = rx.of_type("ATTITUDE")
    euler = np.array([[m.roll, m.pitch, m.yaw] for m in att])
    assert np.all(np.abs(euler[:, 2]) <= math.pi)


@pytest.mark.xdist_group("hil_px4_flight")  # one worker builds the fixture once
def test_px4_declination_parameter_is_the_wmm_value(px4_flight):
    cfg, *_, rx, _ = px4_flight
    (pv,) = rx.of_type("PARAM_VALUE")
    assert pv.param_id == "EKF2_MAG_DECL" and pv.param_type == mavlink.MAV_PARAM_TYPE_REAL32
    assert pv.param_value == pytest.approx(cfg.environment.magnetic_declination_deg, abs=1e-5)


# ---- ArduPilot ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def ardupilot():
    cfg = EmulatorConfig(profile="flight", autopilot="ardupilot", duration_s=8.0, seed=3,
                         fast=True)
    requests = [interval_request(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 1000),
                interval_request(mavlink.MAVLINK_MSG_ID_RAW_IMU, 2500),
                param_read("COMPASS_DEC"), param_read("NO_SUCH_PARAM")]
    return cfg, *run_with_requests(cfg, requests, after_s=0.5)


@pytest.mark.xdist_group("hil_ardupilot_flight")  # one worker builds the fixture once
def test_ardupilot_raw_imu_in_its_units(ardupilot):
    cfg, _, rx, _sent_at = ardupilot
    hb = rx.of_type("HEARTBEAT")[0]
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    rec = simulate(cfg)
    k = {t: i for i, t in enumerate(rec.time_us.tolist())}
    raw = rx.of_type("RAW_IMU")
    idx = np.array([k[m.time_usec] for m in raw])
    acc_mg = np.array([[m.xacc, m.yacc, m.zacc] for m in raw])
    gyr_mrad = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in raw])
    mag_mgauss = np.array([[m.xmag, m.ymag, m.zmag] for m in raw])
    # truncated toward zero, as ArduPilot's float -> int16 conversion does: each count
    # is the value's integer part, never further from zero than the value
    for counts, value in ((acc_mg, rec.acc[idx] / G * 1000.0),
                          (gyr_mrad, rec.gyr[idx] * 1000.0), (mag_mgauss, rec.mag[idx] * 1000.0)):
        assert np.all(np.abs(counts) <= np.abs(value) + 1e-6)
        assert np.all(np.abs(value) - np.abs(counts) < 1.0 + 1e-6)
        assert np.all((counts == 0) | (np.sign(counts) == np.sign(value)))
    on_ground = rec.t_s[idx] < 4.0
    assert np.allclose(acc_mg[on_ground].mean(axis=0), [0, 0, -1000], atol=60)  # FRD, mG
    # SCALED_IMU2 as well, in the same units
    s2 = rx.of_type("SCALED_IMU2")
    assert s2 and s2[0].time_boot_ms in (rec.time_us // 1000).tolist()


@pytest.mark.xdist_group("hil_ardupilot_flight")  # one worker builds the fixture once
def test_ardupilot_answers_and_rates(ardupilot):
    cfg, _emu, rx, sent_at = ardupilot
    assert acks(rx) == {SET_INTERVAL: [mavlink.MAV_RESULT_FAILED, mavlink.MAV_RESULT_ACCEPTED]}
    assert not rx.of_type("HIGHRES_IMU")
    stamps = np.array([m.time_usec for m in rx.of_type("RAW_IMU")])
    before, late = stamps[stamps <= sent_at], stamps[stamps > sent_at + 200_000]
    assert np.all(np.diff(before) == 20_000)  # its default 50 Hz
    # 2.5 ms is kept as whole milliseconds (2 ms): 500 Hz from the 1 kHz IMU
    assert np.all(np.diff(late) == 2_000)
    (pv,) = rx.of_type("PARAM_VALUE")  # the unknown name gets no answer
    assert pv.param_id == "COMPASS_DEC"
    assert pv.param_value == pytest.approx(math.radians(cfg.environment.magnetic_declination_deg),
                                           abs=1e-7)


# ---- the seeds' board --------------------------------------------------------------------

def test_stm32_board_runs_the_seed_filter_and_denies_what_it_lacks():
    cfg = EmulatorConfig(profile="tilt", duration_s=6.0, seed=1, fast=True)
    _emu, rx, sent_at = run_with_requests(
        cfg, [interval_request(mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 10_000),
              interval_request(mavlink.MAVLINK_MSG_ID_ATTITUDE, 10_000),
              param_read("EKF2_MAG_DECL")], after_s=1.0)
    assert rx.of_type("HEARTBEAT")[0].autopilot == mavlink.MAV_AUTOPILOT_GENERIC
    assert acks(rx) == {SET_INTERVAL: [mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_ACCEPTED]}
    assert not rx.of_type("PARAM_VALUE") and not rx.of_type("ATTITUDE_QUATERNION")
    assert len(rx.of_type("RAW_IMU")) == 6000  # every sample, raw counts
    att = rx.of_type("ATTITUDE")
    t = np.array([m.time_boot_ms for m in att])
    assert np.all(np.diff(t[t * 1000 <= sent_at]) == 20)  # 50 Hz, then 100 Hz as asked
    assert np.all(np.diff(t[t * 1000 > sent_at + 200_000]) == 10)
    truth = truth_by_ms(rx)
    assert all(m.time_boot_ms in truth for m in att)
    # After 3 s the seed filter sits on the (uncalibrated) accelerometer's tilt: the
    # board's 20 mg (1σ) offsets put it within ~2° of the paper's 15.9° / 9.2°.
    last = [m for m in att if m.time_boot_ms > t[0] + 3000]
    roll = np.degrees([m.roll for m in last])
    pitch = np.degrees([m.pitch for m in last])
    assert np.all(np.abs(roll - 15.9) < 2.5) and np.all(np.abs(pitch - 9.2) < 2.5)


# ---- the stream scheduler ------------------------------------------------------------------

def test_stream_rate_is_the_asked_one_on_average():
    table = StreamTable(personality("px4"), "HIGHRES_IMU", 1e-3)
    table.set_interval("HIGHRES_IMU", 1.0 / 300.0)
    t = np.arange(3000) * 1e-3
    sent = [x for x in t if table.due("HIGHRES_IMU", x)]
    assert len(sent) == pytest.approx(900, abs=1)
    assert set(np.round(np.diff(sent) * 1e3).astype(int)) == {3, 4}
    table.set_interval("HIGHRES_IMU", 1e-4)  # faster than the IMU: every sample
    assert all(table.due("HIGHRES_IMU", x) for x in t[:100])
    with pytest.raises(KeyError):
        table.set_interval("RAW_IMU", 0.01)  # PX4 has no such stream
