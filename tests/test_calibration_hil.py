"""Calibration against the HIL emulator's uncalibrated GY-86 (default sensor errors).

The emulator draws each chip's errors (MPU6050 zero-g offsets of 20 mg 1σ, 1 % scale,
0.5 % cross-axis; HMC5883L gain errors) from the seed, the same on every motion
profile: a calibration fitted on the `calibration` profile (the board turned through 15
still poses, the six faces among them) must recover those errors — the accelerometer's
and gyro's full matrices, rotation included — and then correct a `flight` of the same
board.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from bridge_support import UdpListener, running_bridge, stream_emulator

import estimators
from bridge.app.calibrate_cli import emulator_samples
from bridge.app.emulator import emulator_declination_deg
from estimators import metrics
from estimators import quat as Q
from hil import EmulatorConfig, simulate
from hil.motion import CALIBRATION_POSES_DEG, calibration_duration_s
from hil.sensors.hmc5883l import Hmc5883lConfig
from hil.sensors.mpu6050 import Mpu6050
from hil.source import random_streams
from imu.boards import RFU_TO_FRD
from imu.calibration import SensorCalibration
from imu.calibration_fit import fit_calibration

RATE_HZ = 250.0
#: `flight` is a multirotor: without velocity aiding eskf needs its rotor-drag model, or
#: the flight's linear acceleration tilts it by ~5° whatever the calibration.
ESKF_DRAG = 0.5
#: Seeds whose uncalibrated board puts eskf off by more than 2° RMS on `flight` (checked
#: below); seeds 1 and 5 happen to draw small errors (1.7° and 1.5°).
SEEDS = (3, 6)
#: A board with iron near the compass (battery, screws): hard iron of ~0.1 G against the
#: Earth's ~0.5 G, and a few percent of soft iron.
IRON = Hmc5883lConfig(hard_iron_gauss=(0.08, -0.05, 0.12),
                      soft_iron=((1.06, 0.03, -0.02), (0.03, 0.95, 0.025),
                                 (-0.02, 0.025, 1.01)))
_FITS: dict[int, tuple] = {}


def fitted(seed: int) -> tuple:
    """(calibration, report) fitted from the seed's calibration session (cached)."""
    if seed not in _FITS:
        gyr, acc, mag, rate = emulator_samples(seed, RATE_HZ)
        _FITS[seed] = fit_calibration(gyr, acc, mag, rate)
    return _FITS[seed]


def eskf_error_after_10s(rec, gyr, acc, mag) -> float:
    dt = np.diff(rec.time_us, prepend=rec.time_us[0] - round(1e6 / RATE_HZ)) * 1e-6
    q = estimators.batch("eskf", gyr, acc, mag, rate_hz=RATE_HZ, dt=dt, drag=ESKF_DRAG,
                         declination=math.radians(emulator_declination_deg()))
    converged = rec.t_s >= 10.0
    return metrics.rms_errors(q[converged], rec.truth_q[converged]).total_deg


@pytest.mark.parametrize("seed", SEEDS)
def test_fit_on_the_emulated_board_removes_its_errors(seed):
    cal, report = fitted(seed)
    assert report.accel_poses >= 12 and report.accel_model == "full"
    # Gravity norm over the static poses: ~0.1-0.2 m/s^2 spread before, noise after.
    assert report.accel_norm_std_after < report.accel_norm_std_before / 20
    assert report.accel_norm_rms_error_after < 0.01
    # The gyro offset (1 °/s 1σ) is found to a few hundredths of a degree per second.
    rec = simulate(EmulatorConfig(profile="static", duration_s=2.0, seed=seed,
                                  rate_hz=RATE_HZ))
    true_offset = rec.gyr.mean(axis=0)  # at rest: the mean rate is the offset
    assert np.max(np.abs(cal.gyro_offset - true_offset)) < math.radians(0.05)


def true_error_matrices(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(gyro, accel) error matrices of the seed's MPU6050 in body FRD axes.

    The chip reads ``T @ true + offset`` in its RFU axes and RFU_TO_FRD is its own
    inverse, so in the body the error is ``P T P``; the correction must be its inverse.
    """
    chip = Mpu6050(EmulatorConfig(seed=seed, rate_hz=RATE_HZ).mpu,
                   random_streams(seed)["mpu_build"])
    p = RFU_TO_FRD
    return p @ chip.gyro_matrix @ p, p @ chip.accel_matrix @ p


def misalignment_deg(m: np.ndarray) -> float:
    """Angle of the rotation in m (its orthogonal polar factor)."""
    u, _, vt = np.linalg.svd(m)
    return float(np.degrees(np.arccos(np.clip((np.trace(u @ vt) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("seed", SEEDS)
def test_fit_recovers_the_chips_error_matrices_including_rotation(seed):
    cal, report = fitted(seed)
    gyro_error, accel_error = true_error_matrices(seed)
    assert report.accel_faces == 6 and report.accel_face_residual_deg < 0.1
    # The chip's accelerometer axes are turned against the board by a few tenths of a
    # degree (what a norm-only fit leaves); the six-face fit removes the turn as well.
    assert misalignment_deg(accel_error) > 0.3
    assert misalignment_deg(cal.accel_matrix @ accel_error) < 0.05
    np.testing.assert_allclose(cal.accel_matrix @ accel_error, np.eye(3), atol=1e-3)
    # Gyro scale and cross-axis (~1 % and 0.5 % drawn) recovered to 0.1 %.
    assert np.max(np.abs(gyro_error - np.eye(3))) > 0.005
    np.testing.assert_allclose(cal.gyro_matrix @ gyro_error, np.eye(3), atol=1e-3)
    assert report.gyro_turns == len(CALIBRATION_POSES_DEG) - 1
    assert report.gyro_turn_error_after_deg < min(0.15, report.gyro_turn_error_before_deg / 5)


def test_fit_removes_hard_and_soft_iron():
    cfg = EmulatorConfig(profile="calibration", duration_s=calibration_duration_s() + 1.0,
                         seed=SEEDS[0], rate_hz=RATE_HZ, hmc5883l=IRON)
    rec = simulate(cfg)
    cal, report = fit_calibration(rec.gyr, rec.acc, rec.mag, cfg.imu_rate_hz)
    assert report.mag_norm_rel_std_before > 0.1
    assert report.mag_norm_rel_std_after < report.mag_norm_rel_std_before / 20
    fresh = rec.mag_updated & np.all(np.isfinite(rec.mag), axis=1)

    def direction_error_deg(mag: np.ndarray) -> float:
        truth = rec.truth_mag[fresh]
        cos = np.sum(mag * truth, axis=1) / np.linalg.norm(mag, axis=1) / np.linalg.norm(
            truth, axis=1)
        return float(np.degrees(np.mean(np.arccos(np.clip(cos, -1.0, 1.0)))))

    before = direction_error_deg(rec.mag[fresh])
    after = direction_error_deg(cal.mag(rec.mag[fresh]))
    assert before > 8.0 and after < 0.6, (before, after)


@pytest.mark.parametrize("seed", SEEDS)
def test_eskf_on_calibrated_flight_is_within_2_degrees(seed):
    cal, _ = fitted(seed)
    rec = simulate(EmulatorConfig(profile="flight", duration_s=30.0, seed=seed,
                                  rate_hz=RATE_HZ))
    raw = eskf_error_after_10s(rec, rec.gyr, rec.acc, rec.mag)
    calibrated = eskf_error_after_10s(rec, cal.gyro(rec.gyr), cal.accel(rec.acc),
                                      cal.mag(rec.mag))
    assert raw > 2.0, raw  # the uncalibrated board misses the target...
    assert calibrated < 2.0, calibrated  # ...the calibrated one meets it
    assert calibrated < raw / 1.5


def test_bridge_with_calibration_file_meets_the_target(tmp_path):
    """Uncalibrated emulator -> bridge started with `calibration=` -> < 2° RMS vs truth."""
    seed = SEEDS[1]
    cal, report = fitted(seed)
    path = tmp_path / "calib.toml"
    cal.save(path, "\n".join(report.lines()))
    cfg = EmulatorConfig(profile="flight", duration_s=25.0, seed=seed, fast=True,
                         rate_hz=RATE_HZ)
    listener = asyncio.run(stream_through_bridge(cfg, str(path)))
    out, truth = listener.outputs_with_truth()
    assert len(out) > 0.9 * 25.0 * 50.0
    stamps = np.array([m.time_boot_ms for m in out])
    est = np.array([[m.q1, m.q2, m.q3, m.q4] for m in out])
    ref = np.array([truth[t] for t in stamps])
    converged = stamps >= stamps[0] + 10_000
    err = metrics.rms_errors(est[converged], ref[converged])
    assert err.total_deg < 2.0, err
    # And the output is exactly the estimator on the calibrated samples, i.e. ingest
    # applied the file (and nothing else) to every sample.
    rec = simulate(cfg)
    loaded = SensorCalibration.load(path)
    dt = np.diff(rec.time_us, prepend=rec.time_us[0] - round(1e6 / RATE_HZ)) * 1e-6
    q = estimators.batch("eskf", loaded.gyro(rec.gyr), loaded.accel(rec.acc),
                         loaded.mag(rec.mag), rate_hz=RATE_HZ, dt=dt,
                         declination=math.radians(emulator_declination_deg()),
                         drag=ESKF_DRAG)
    offline = dict(zip((rec.time_us // 1000).tolist(), q, strict=True))
    same = np.array([offline[t] for t in stamps])
    assert np.max(np.degrees(Q.angle_between(est, same))) < 0.05


async def stream_through_bridge(cfg: EmulatorConfig, calibration: str) -> UdpListener:
    listener = UdpListener()
    out_port = await listener.start()
    async with running_bridge(estimators=[f"eskf:drag={ESKF_DRAG}"], out_rate=50.0,
                              imu_rate=cfg.imu_rate_hz,
                              max_source_rate=1e7,  # --fast: faster than real time
                              declination_deg=emulator_declination_deg(),
                              outs=[f"udpout:127.0.0.1:{out_port}"],
                              calibration=calibration) as bridge:
        await stream_emulator(bridge, cfg, out_port)
    listener.close()
    return listener


def test_calibrate_command_reads_a_raw_imu_tlog(tmp_path, capsys):
    """The emulated session's RAW_IMU integers in a tlog, through `attitude-bridge
    calibrate --board gy86`: the same calibration as fitted from the SI arrays."""
    from bridge.app.cli import main as cli_main
    from bridge.wire.mav import mavlink

    seed = SEEDS[0]
    cfg = EmulatorConfig(profile="calibration", duration_s=calibration_duration_s() + 1.0,
                         seed=seed, rate_hz=RATE_HZ)
    rec = simulate(cfg)
    mav = mavlink.MAVLink(None, 1, 1)
    path = tmp_path / "session.tlog"
    with path.open("wb") as f:
        for k in range(len(rec.time_us)):
            msg = mavlink.MAVLink_raw_imu_message(
                int(rec.time_us[k]), *map(int, rec.acc_counts[k]), *map(int, rec.gyr_counts[k]),
                *map(int, rec.mag_counts[k]), 0, 0)
            f.write((1_700_000_000_000_000 + 4000 * k).to_bytes(8, "big") + msg.pack(mav))
    out = tmp_path / "calib.toml"
    assert cli_main(["calibrate", str(path), "-o", str(out), "--board", "gy86"]) == 0
    assert "static poses" in capsys.readouterr().out
    from_log = SensorCalibration.load(out)
    expected, _ = fitted(seed)
    np.testing.assert_allclose(from_log.accel_offset, expected.accel_offset, atol=1e-6)
    np.testing.assert_allclose(from_log.accel_matrix, expected.accel_matrix, atol=1e-6)
    np.testing.assert_allclose(from_log.mag_offset, expected.mag_offset, atol=1e-6)
    np.testing.assert_allclose(from_log.gyro_offset, expected.gyro_offset, atol=1e-9)
    np.testing.assert_allclose(from_log.gyro_matrix, expected.gyro_matrix, atol=1e-6)
