"""tlog input paths not in the sample log: HIGHRES_IMU + HIL_STATE_QUATERNION truth,
SCALED_IMU + ATTITUDE_QUATERNION, RAW_IMU with the gy86 board profile; duplicated and
backwards messages dropped and counted. The tlogs are written here with pymavlink."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common

import replay
from imu.boards import gy86
from replay.synthetic import SyntheticConfig, generate

G = 9.80665
BOOT_US = 5_000_000  # board clock at the first sample


def write_tlog(path, messages) -> None:
    mav = common.MAVLink(None, srcSystem=1, srcComponent=1)
    with path.open("wb") as f:
        for k, msg in enumerate(messages):
            stamp = int(1.7e15) + 1000 * k  # arrival time: ignored by replay for timing
            f.write(stamp.to_bytes(8, "big") + msg.pack(mav))


@pytest.fixture(scope="module")
def motion():
    return generate(SyntheticConfig(duration_s=4.0, rate_hz=100.0, seed=9))


def test_highres_imu_with_hil_truth(tmp_path, motion):
    msgs = []
    for i in range(motion.n):
        us = BOOT_US + round(motion.t[i] * 1e6)
        a, g, m = motion.acc[i], motion.gyr[i], motion.mag[i]
        msgs.append(common.MAVLink_highres_imu_message(us, *a, *g, *m, 1013.0, 0.0, 0.0, 20.0,
                                                       0x1FF))
        msgs.append(common.MAVLink_hil_state_quaternion_message(
            us, motion.reference.q[i], 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    duplicate, late = msgs[20], msgs[40]  # even indices are HIGHRES_IMU
    msgs.insert(61, late)  # an old IMU message arriving late (time goes backwards)
    msgs.insert(21, duplicate)  # the same IMU message twice
    path = tmp_path / "highres.tlog"
    write_tlog(path, msgs)
    rec = replay.load(path)
    assert rec.source == "HIGHRES_IMU" and rec.n == motion.n
    assert (rec.cleanup.duplicates, rec.cleanup.backwards) == (1, 1)
    np.testing.assert_allclose(rec.t - rec.t[0], motion.t, atol=1e-9)
    np.testing.assert_allclose(rec.gyr, motion.gyr, rtol=1e-6, atol=1e-7)  # float32 fields
    assert rec.reference.kind == "truth" and rec.reference.source == "HIL_STATE_QUATERNION"
    ours = replay.evaluate(rec, ["mahony"]).scores["mahony"]
    direct = replay.evaluate(motion, ["mahony"]).scores["mahony"]
    assert ours.total_deg == pytest.approx(direct.total_deg, rel=1e-3)


def test_scaled_imu_units_and_attitude_quaternion(tmp_path, motion):
    msgs = []
    for i in range(motion.n):
        ms = BOOT_US // 1000 + round(motion.t[i] * 1e3)
        a = np.round(motion.acc[i] / G * 1e3).astype(int)  # mG
        g = np.round(motion.gyr[i] * 1e3).astype(int)  # mrad/s
        m = np.round(motion.mag[i] * 1e3).astype(int)  # mgauss
        msgs.append(common.MAVLink_scaled_imu_message(ms, *a, *g, *m))
        q = motion.reference.q[i]
        msgs.append(common.MAVLink_attitude_quaternion_message(ms, *q, 0, 0, 0))
    path = tmp_path / "scaled.tlog"
    write_tlog(path, msgs)
    rec = replay.load(path)
    assert rec.source == "SCALED_IMU" and rec.n == motion.n
    np.testing.assert_allclose(rec.acc, motion.acc, atol=0.5e-3 * G + 1e-9)
    np.testing.assert_allclose(rec.gyr, motion.gyr, atol=0.5e-3 + 1e-9)
    assert rec.reference.kind == "autopilot"
    assert rec.reference.source == "ATTITUDE_QUATERNION"


def test_raw_imu_with_gy86_profile(tmp_path, motion):
    board = gy86()
    to_chip = board.to_frd.T  # RFU chip axes from FRD (a permutation: its own inverse)

    def counts(v, scale):
        return np.round(to_chip @ v / scale).astype(int)

    msgs = [common.MAVLink_raw_imu_message(
        BOOT_US + round(motion.t[i] * 1e6),
        *counts(motion.acc[i], board.accel_scale), *counts(motion.gyr[i], board.gyro_scale),
        *counts(motion.mag[i], board.mag_scale)) for i in range(motion.n)]
    path = tmp_path / "raw.tlog"
    write_tlog(path, msgs)
    rec = replay.load(path, board="gy86")
    assert rec.source == "RAW_IMU" and rec.reference is None
    np.testing.assert_allclose(rec.acc, motion.acc, atol=0.51 * board.accel_scale)
    np.testing.assert_allclose(rec.mag, motion.mag, atol=0.51 * board.mag_scale)
    assert rec.warnings == ()
    # Without --board the profile that gives 1 g at rest is chosen, and said so.
    detected = replay.load(path)
    assert detected.board == "gy86" and np.array_equal(detected.acc, rec.acc)
    assert any("gy86 (detected)" in n for n in detected.notes)
    # The wrong profile reads the same integers as ArduPilot's mG: 4 g, and a warning.
    wrong = replay.load(path, board="ardupilot")
    assert not np.allclose(wrong.acc, motion.acc, atol=0.5)
    assert len(wrong.warnings) == 1 and "--board gy86" in wrong.warnings[0]
    with pytest.raises(ValueError, match="unknown board profile"):
        replay.load(path, board="pixhawk9")


def highres(us: int, motion, i: int):
    a, g, m = motion.acc[i], motion.gyr[i], motion.mag[i]
    return common.MAVLink_highres_imu_message(us, *a, *g, *m, 1013.0, 0.0, 0.0, 20.0, 0x1FF)


def test_truth_without_time_stamp_is_aligned_by_arrival(tmp_path, motion):
    """PX4 SITL sends HIL_STATE_QUATERNION with time_usec = 0: each gets the board time of
    the IMU message before it in the file, so the scores equal those on the true times."""
    msgs = []
    for i in range(motion.n):
        msgs.append(highres(BOOT_US + round(motion.t[i] * 1e6), motion, i))
        if i % 2 == 0:  # truth at half the IMU rate, sent right after "its" IMU sample
            msgs.append(common.MAVLink_hil_state_quaternion_message(
                0, motion.reference.q[i], 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    path = tmp_path / "sitl.tlog"
    write_tlog(path, msgs)
    rec = replay.load(path)
    assert "aligned by arrival" in rec.reference.timing
    np.testing.assert_allclose(rec.reference.t - rec.t[0], motion.t[::2], atol=1e-9)
    ours = replay.evaluate(rec, ["mahony"]).scores["mahony"]
    direct = replay.evaluate(motion, ["mahony"]).scores["mahony"]
    assert ours.total_deg == pytest.approx(direct.total_deg, rel=0.05)
    assert ours.lag_s == pytest.approx(direct.lag_s, abs=0.5 / 100.0)  # half an IMU step


def test_velocity_placed_at_arrival_with_its_age(tmp_path, motion):
    """LOCAL_POSITION_NED valid 30 ms before it arrives lands on the next IMU sample with
    age 30 ms + one step; a GPS_RAW_INT without time stamp (PX4: time_usec = 0) gives
    horizontal velocity only, aged from its arrival; LOCAL_POSITION_NED is preferred."""
    step_us = 10_000  # motion is at 100 Hz
    lpn_at, gps_at = {10: (1.0, -2.0, 0.5), 50: (3.0, 4.0, -1.0)}, {20: (300, 9000)}
    msgs = []
    for i in range(motion.n):
        us = BOOT_US + round(motion.t[i] * 1e6)
        msgs.append(highres(us, motion, i))
        if i in lpn_at:
            valid_ms = (us - 30_000) // 1000
            msgs.append(common.MAVLink_local_position_ned_message(valid_ms, 0, 0, 0, *lpn_at[i]))
        if i in gps_at:
            vel, cog = gps_at[i]  # 3 m/s towards 90° (east)
            msgs.append(common.MAVLink_gps_raw_int_message(0, 3, 473977421, 85455954, 489658,
                                                           70, 110, vel, cog, 10))
    path = tmp_path / "vel.tlog"
    write_tlog(path, msgs)
    v = replay.load(path).velocity
    assert v.source == "LOCAL_POSITION_NED" and v.count == 2
    for i, expected in lpn_at.items():
        np.testing.assert_allclose(v.vel[i + 1], expected, rtol=1e-6)
        assert v.age[i + 1] == pytest.approx(0.030 + step_us * 1e-6, abs=1.5e-3)
    rows = np.flatnonzero(np.any(np.isfinite(v.vel), axis=1))
    assert list(rows) == [11, 51]

    # Without LOCAL_POSITION_NED the GPS is the source: north/east from speed and course.
    write_tlog(path, [m for m in msgs if m.get_type() != "LOCAL_POSITION_NED"])
    v = replay.load(path).velocity
    assert v.source == "GPS_RAW_INT" and v.count == 1
    np.testing.assert_allclose(v.vel[21, :2], [0.0, 3.0], atol=1e-9)
    assert np.isnan(v.vel[21, 2])  # no vertical velocity in GPS_RAW_INT
    assert v.age[21] == pytest.approx(step_us * 1e-6, abs=1e-6)  # arrival is all we know
    assert "aged from their arrival" in v.placement


def test_declination_from_parameter_position_or_option(tmp_path, motion):
    from pygeomag import GeoMag

    imu_msgs = [highres(BOOT_US + round(motion.t[i] * 1e6), motion, i)
                for i in range(motion.n)]
    gps = common.MAVLink_gps_raw_int_message(0, 3, -353627085, 1491656122, 588590, 70, 110,
                                             0, 0, 10)
    when = common.MAVLink_system_time_message(int(1.7e15), 5000)  # 2023-11-14
    path = tmp_path / "dec.tlog"
    write_tlog(path, [gps, when, *imu_msgs])
    rec = replay.load(path)
    dec = replay.evaluate(rec, ["mahony"]).prepared.declination
    wmm = GeoMag(coefficients_file="wmm/WMM_2025.COF").calculate(
        glat=-35.3627085, glon=149.1656122, alt=0.58859, time=2023.87,
        allow_date_outside_lifespan=True)
    assert dec.deg == pytest.approx(wmm.d, abs=0.02)
    assert "WMM2025" in dec.source and "GPS_RAW_INT" in dec.source
    assert "2023-11-14 from SYSTEM_TIME" in dec.source
    # The vehicle's own parameter wins over the model (ArduPilot: radians) ...
    param = common.MAVLink_param_value_message(b"COMPASS_DEC", 0.2, 9, 1, 0)
    write_tlog(path, [param, gps, when, *imu_msgs])
    dec = replay.evaluate(replay.load(path), ["mahony"]).prepared.declination
    assert dec.deg == pytest.approx(np.degrees(0.2), abs=1e-5)
    assert dec.source == "vehicle parameter COMPASS_DEC"
    # ... and the command line over both; the estimators get it in radians.
    ev = replay.evaluate(replay.load(path), ["mahony"], declination_deg=-7.0)
    assert ev.prepared.declination.deg == -7.0
    est = replay.evaluate(replay.load(path), ["mahony:declination_deg=17.2"])
    run = est.runs["mahony:declination_deg=17.2"]
    assert run.spec.params["declination"] == pytest.approx(np.radians(17.2))


def test_corrupt_records_are_skipped_and_counted(tmp_path, motion):
    msgs = [highres(BOOT_US + round(motion.t[i] * 1e6), motion, i) for i in range(motion.n)]
    path = tmp_path / "corrupt.tlog"
    write_tlog(path, msgs)
    data = bytearray(path.read_bytes())
    record = len(data) // motion.n  # every HIGHRES_IMU record has the same size
    data[100 * record + 20] ^= 0xFF  # a payload byte of sample 100: its CRC fails
    data[200 * record:200 * record] = b"\x00garbage\xfd\x01"  # bytes between two records
    path.write_bytes(bytes(data))
    rec = replay.load(path)
    assert rec.n == motion.n - 1  # only the corrupted sample is lost
    assert 100 * 0.01 not in np.round(rec.t - rec.t[0], 6)
    assert any("skipped 2 unreadable" in n for n in rec.notes)


def test_aiding_goes_to_the_estimators_through_one_function(tmp_path, motion):
    """``aiding_kwargs`` hands the estimators exactly the aligned ``vel`` / ``vel_age``
    slices when aiding is on, nothing otherwise; ``--aid velocity`` without velocity in
    the log is refused."""
    from dataclasses import replace

    from replay.evaluate import aiding_kwargs, prepare

    msgs = []
    for i in range(motion.n):
        us = BOOT_US + round(motion.t[i] * 1e6)
        msgs.append(highres(us, motion, i))
        if i % 10 == 5:
            msgs.append(common.MAVLink_local_position_ned_message(us // 1000, 0, 0, 0,
                                                                  1.0, 2.0, 3.0))
    path = tmp_path / "aid.tlog"
    write_tlog(path, msgs)
    rec = replay.load(path)
    prep = replace(prepare(rec), aid="velocity")
    kw = aiding_kwargs(prep, slice(3, None))
    np.testing.assert_array_equal(kw["vel"], rec.velocity.vel[3:])
    np.testing.assert_array_equal(kw["vel_age"], rec.velocity.age[3:])
    assert aiding_kwargs(prepare(rec, aid="none"), slice(0, None)) == {}
    with pytest.raises(replay.ReplayInputError, match="--aid velocity: the log has no velocity"):
        prepare(motion, aid="velocity")
