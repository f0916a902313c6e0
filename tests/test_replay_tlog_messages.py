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
