"""Sensor calibration: the file format, the fits on synthetic data with known errors,
refusal of data that cannot determine a calibration, and its application in ingest."""

from __future__ import annotations

import math

import numpy as np
import pytest
from bridge_support import MAG_NED, G, euler_q, gy86_counts

from bridge.calibrate_cli import log_samples
from bridge.cli import main as cli_main
from bridge.config import BridgeConfig
from bridge.ingest import Ingest
from bridge.mav import mavlink
from estimators import quat as Q
from imu.boards import gy86
from imu.calibration import SensorCalibration
from imu.calibration_fit import fit_calibration, fit_magnetometer, static_poses

RATE = 200.0
#: Known errors (numbers chosen here): corrected = M @ (raw - offset) must undo them.
ACC_ERROR = np.array([[1.03, 0.012, -0.008], [0.012, 0.97, 0.015], [-0.008, 0.015, 1.02]])
ACC_OFFSET = np.array([0.35, -0.22, 0.48])  # m/s^2 (36, 22, 49 mg)
GYRO_OFFSET = np.array([0.021, -0.013, 0.007])  # rad/s
SOFT_IRON = np.array([[1.10, 0.05, -0.03], [0.05, 0.92, 0.04], [-0.03, 0.04, 1.01]])
HARD_IRON = np.array([0.12, -0.07, 0.2])  # gauss
FIELD = 0.5  # gauss


def fibonacci_directions(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = math.pi * (1.0 + 5.0 ** 0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def synthetic_session(gravity_dirs: np.ndarray, rng: np.random.Generator,
                      hold_s: float = 1.5, move_s: float = 0.6
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gyr, acc, mag) of a board held still in each direction, turned in between.

    The field direction follows gravity's at a fixed angle (a real dip) but rotated
    about it per pose, so the magnetometer sees many directions.
    """
    gyr, acc, mag = [], [], []
    n_hold, n_move = round(hold_s * RATE), round(move_s * RATE)
    dirs = gravity_dirs / np.linalg.norm(gravity_dirs, axis=1, keepdims=True)
    for i, d in enumerate(dirs):
        f_true = -G * d  # specific force at rest points away from gravity
        a_meas = f_true @ ACC_ERROR.T + ACC_OFFSET
        acc.append(a_meas + rng.normal(0, 0.02, (n_hold, 3)))
        gyr.append(GYRO_OFFSET + rng.normal(0, 0.002, (n_hold, 3)))
        # Field: fresh random directions while moving, one fixed one while held.
        b_hold = fibonacci_directions(len(dirs))[(7 * i) % len(dirs)] * FIELD
        b_move = rng.normal(size=(n_move, 3))
        b_move = b_move / np.linalg.norm(b_move, axis=1, keepdims=True) * FIELD
        mag.append(np.repeat(b_hold[None], n_hold, axis=0))
        mag.append(b_move)
        if i + 1 < len(dirs):  # the turn to the next pose: rate and moving gravity
            u = np.linspace(0, 1, n_move)[:, None]
            f_move = -G * ((1 - u) * d + u * dirs[i + 1])
            acc.append(f_move @ ACC_ERROR.T + ACC_OFFSET + rng.normal(0, 0.3, (n_move, 3)))
            gyr.append(GYRO_OFFSET + np.array([1.5, -0.8, 0.4]) + rng.normal(0, 0.05,
                                                                            (n_move, 3)))
        else:
            mag.pop()
    mag_true = np.concatenate(mag)
    mag_meas = mag_true @ SOFT_IRON.T + HARD_IRON + rng.normal(0, 0.002, mag_true.shape)
    return np.concatenate(gyr), np.concatenate(acc), mag_meas


@pytest.fixture(scope="module")
def synthetic():
    rng = np.random.default_rng(7)
    return synthetic_session(fibonacci_directions(16), rng)


# --- the fits recover known errors --------------------------------------------------

def test_fit_recovers_known_accelerometer_and_gyro_errors(synthetic):
    gyr, acc, mag = synthetic
    cal, report = fit_calibration(gyr, acc, mag, RATE)
    assert report.accel_poses == 16 and report.accel_model == "symmetric"
    np.testing.assert_allclose(cal.gyro_offset, GYRO_OFFSET, atol=5e-4)
    np.testing.assert_allclose(cal.accel_offset, ACC_OFFSET, atol=0.01)
    # The error matrix is symmetric, so the fitted correction is its exact inverse.
    np.testing.assert_allclose(cal.accel_matrix @ ACC_ERROR, np.eye(3), atol=2e-3)
    assert report.accel_norm_std_after < report.accel_norm_std_before / 20
    assert report.accel_norm_rms_error_after < 0.01


def test_fit_recovers_known_hard_and_soft_iron(synthetic):
    _, _, mag = synthetic
    offset, matrix, report = fit_magnetometer(mag)
    np.testing.assert_allclose(offset, HARD_IRON, atol=2e-3)
    undone = matrix @ SOFT_IRON  # the field's own scale is unknown: compare shapes
    np.testing.assert_allclose(undone / np.cbrt(np.linalg.det(undone)), np.eye(3), atol=5e-3)
    corrected = (mag - offset) @ matrix.T
    norms = np.linalg.norm(corrected, axis=1)
    # Scaled so the corrected field keeps the mean measured strength.
    assert np.mean(norms) == pytest.approx(np.mean(np.linalg.norm(mag - offset, axis=1)),
                                           rel=0.01)
    assert report["mag_norm_rel_std_after"] < report["mag_norm_rel_std_before"] / 10


# --- refusing data that cannot determine a calibration ---------------------------

def test_too_few_static_poses_are_refused():
    rng = np.random.default_rng(1)
    dirs = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    gyr, acc, mag = synthetic_session(dirs, rng)
    assert len(static_poses(gyr, acc, RATE)[0]) == 5
    with pytest.raises(ValueError, match=r"4 distinct static pose\(s\).*need 6"):
        fit_calibration(gyr, acc, mag, RATE, magnetometer=False)


def test_poses_in_one_plane_are_refused():
    """Gravity only ever in the x-z plane: the y scale and offset are undetermined."""
    rng = np.random.default_rng(2)
    angles = np.radians(np.arange(0, 360, 30))
    dirs = np.column_stack([np.cos(angles), np.zeros_like(angles), np.sin(angles)])
    gyr, acc, mag = synthetic_session(dirs, rng)
    with pytest.raises(ValueError, match="do not cover enough orientations"):
        fit_calibration(gyr, acc, mag, RATE, magnetometer=False)


def test_magnetometer_turned_about_one_axis_only_is_refused():
    """Yaw-only turns on a level table: the readings form a circle, not a sphere."""
    rng = np.random.default_rng(3)
    yaw = rng.uniform(0, 2 * math.pi, 2000)
    field = np.column_stack([0.2 * np.cos(yaw), 0.2 * np.sin(yaw), np.full_like(yaw, 0.45)])
    mag = field @ SOFT_IRON.T + HARD_IRON + rng.normal(0, 0.002, field.shape)
    with pytest.raises(ValueError, match="sphere"):
        fit_magnetometer(mag)


def test_magnetometer_covering_a_cap_only_is_refused():
    """Tilted at most 40° from one direction: too little of the sphere to trust."""
    rng = np.random.default_rng(4)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cap = d[d[:, 2] > math.cos(math.radians(40))] * FIELD
    mag = cap @ SOFT_IRON.T + HARD_IRON + rng.normal(0, 0.002, cap.shape)
    with pytest.raises(ValueError, match="sphere"):
        fit_magnetometer(mag)


def test_no_still_stretch_refuses_the_gyro_offset():
    rng = np.random.default_rng(5)
    n = 2000
    gyr = rng.normal(0, 0.3, (n, 3))  # always moving
    acc = rng.normal(0, 1.0, (n, 3)) + np.array([0, 0, -G])
    with pytest.raises(ValueError, match="no still stretch"):
        fit_calibration(gyr, acc, None, RATE, accel=False, magnetometer=False)
    with pytest.raises(ValueError, match="no magnetometer"):
        fit_calibration(gyr, acc, None, RATE, gyro=False, accel=False)


# --- the file format -----------------------------------------------------------------

def known_calibration() -> SensorCalibration:
    return SensorCalibration(gyro_offset=GYRO_OFFSET, accel_offset=ACC_OFFSET,
                             accel_matrix=np.linalg.inv(ACC_ERROR), mag_offset=HARD_IRON,
                             mag_matrix=np.linalg.inv(SOFT_IRON))


def test_toml_round_trip_is_exact(tmp_path):
    cal = known_calibration()
    path = tmp_path / "calib.toml"
    cal.save(path, comment="test\nsecond line")
    back = SensorCalibration.load(path)
    for name in ("gyro_offset", "accel_offset", "accel_matrix", "mag_offset", "mag_matrix"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cal, name))
    assert SensorCalibration().is_identity and not back.is_identity
    # Tables may be left out: they stay identity.
    path.write_text("[gyro]\noffset = [0.1, 0, 0]\n")
    partial = SensorCalibration.load(path)
    assert partial.gyro_offset.tolist() == [0.1, 0, 0]
    assert partial.accel_matrix.tolist() == np.eye(3).tolist()


@pytest.mark.parametrize("text, message", [
    ("[accel]\noffset = [1, 2]\n", r"accel\.offset must be 3 numbers"),
    ("[accel]\nmatrix = [[1, 0, 0], [0, 1, 0]]\n", r"accel\.matrix must be 3x3"),
    ("[mag]\noffset = [1, nan, 0]\n", r"mag\.offset must be finite"),
    ("[mag]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, inf, 1]]\n", r"mag\.matrix must be finite"),
    ("[mag]\nmatrix = [[1, 0, 0], [0, 1, 0], [1, 0, 0]]\n", r"mag\.matrix is singular"),
    ("[accel]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]\n", "not a plausible correction"),
    ("[accel]\nmatrix = [[1, 0, 0], [0, 3, 0], [0, 0, 1]]\n", "not a plausible correction"),
    ("[gyro]\nscale = [1, 1, 1]\n", r"unknown key\(s\) \['scale'\] in \[gyro\]"),
    ("[baro]\noffset = 1\n", r"unknown calibration table\(s\) \['baro'\]"),
    ("[gyro]\noffset = 'abc'\n", r"gyro\.offset must be 3 numbers"),
    ("[gyro\noffset = [0, 0, 0]\n", "not valid TOML"),
])
def test_bad_files_give_clear_errors(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        SensorCalibration.load(path)
    assert str(path) in str(info.value)


def test_bridge_config_checks_the_calibration_file(tmp_path):
    with pytest.raises(ValueError, match="cannot read calibration file"):
        BridgeConfig(calibration=str(tmp_path / "missing.toml")).validate()
    (tmp_path / "calib.toml").write_text(known_calibration().to_toml())
    settings = tmp_path / "bridge.toml"
    settings.write_text('calibration = "calib.toml"\n')  # relative to the settings file
    cfg = BridgeConfig.from_toml(settings)
    cfg.validate()
    np.testing.assert_array_equal(cfg.sensor_calibration().gyro_offset, GYRO_OFFSET)


def test_run_command_takes_calibration_option_over_the_settings_file(tmp_path):
    from bridge.cli import build_parser
    from bridge.run_cli import config_from_args

    (tmp_path / "a.toml").write_text(known_calibration().to_toml())
    (tmp_path / "b.toml").write_text(SensorCalibration().to_toml())
    settings = tmp_path / "bridge.toml"
    settings.write_text('calibration = "b.toml"\n')
    args = build_parser().parse_args(["run", "--config", str(settings)])
    assert config_from_args(args, demo=False).calibration == str(tmp_path / "b.toml")
    args = build_parser().parse_args(["run", "--config", str(settings), "--calibration",
                                      str(tmp_path / "a.toml")])
    cfg = config_from_args(args, demo=False)
    assert cfg.calibration == str(tmp_path / "a.toml")
    assert not cfg.sensor_calibration().is_identity


# --- applied in ingest --------------------------------------------------------------

def _decode(msg) -> object:
    return mavlink.MAVLink(None).decode(bytearray(msg.pack(mavlink.MAVLink(None, 1, 1))))


def test_ingest_applies_the_calibration_to_every_message_type():
    cal = known_calibration()
    q = euler_q(20.0, -10.0, 30.0)
    acc, gyr, mag = gy86_counts(q, np.radians([10.0, -5.0, 3.0]))
    a_frd = Q.rotate(Q.conjugate(q), [0, 0, -G])
    m_frd = Q.rotate(Q.conjugate(q), MAG_NED)
    msgs = [
        mavlink.MAVLink_raw_imu_message(5000, *acc, *gyr, *mag, 0, 0),
        mavlink.MAVLink_scaled_imu_message(5, *np.round(a_frd / 9.80665e-3).astype(int),
                                           10, -20, 30, *np.round(m_frd * 1e3).astype(int)),
        mavlink.MAVLink_highres_imu_message(5000, *a_frd, 0.01, -0.02, 0.03, *m_frd,
                                            0, 0, 0, 0, 0x1FF, 0),
    ]
    for msg in msgs:
        plain, calibrated = Ingest(gy86()), Ingest(gy86(), calibration=cal)
        ref, got = plain.handle(_decode(msg)), calibrated.handle(_decode(msg))
        np.testing.assert_allclose(got.gyr, cal.gyro(ref.gyr), atol=1e-12)
        np.testing.assert_allclose(got.acc, cal.accel(ref.acc), atol=1e-12)
        np.testing.assert_allclose(got.mag, cal.mag(ref.mag), atol=1e-12)
        assert not np.allclose(got.acc, ref.acc)


def test_ingest_with_calibration_still_flags_saturation_and_absent_mag():
    """Clipping and a missing magnetometer are judged on the message's own numbers."""
    ingest = Ingest(gy86(), rotation=np.diag([1.0, -1.0, -1.0]),
                    calibration=known_calibration())
    acc, gyr, mag = gy86_counts(euler_q(5.0, 5.0, 0.0))
    good = ingest.handle(_decode(mavlink.MAVLink_raw_imu_message(1000, *acc, *gyr, *mag, 0, 0)))
    sat = ingest.handle(_decode(mavlink.MAVLink_raw_imu_message(
        2000, 32767, 0, 0, -32768, 0, 0, 0, 0, 0, 0, 0)))
    over = ingest.handle(_decode(mavlink.MAVLink_raw_imu_message(
        3000, *acc, *gyr, -4096, mag[1], mag[2], 0, 0)))
    assert good.mag is not None and np.all(np.isfinite(good.acc))
    assert np.all(np.isnan(sat.acc)) and sat.mag is None  # (0, 0, 0): no magnetometer
    np.testing.assert_array_equal(sat.gyr, good.gyr)  # clipped gyro holds the last good one
    assert over.mag is None
    counts = next(iter(ingest.sources.values())).counts
    assert (counts["acc_saturated"], counts["gyro_saturated"], counts["mag_invalid"]) == (1, 1, 1)


# --- the command ---------------------------------------------------------------------

def test_calibrate_command_fits_a_csv_log_and_refuses_a_poor_one(tmp_path, synthetic, capsys):
    gyr, acc, mag = synthetic
    t = np.arange(len(gyr)) / RATE
    header = "t,gx,gy,gz,ax,ay,az,mx,my,mz"
    log = tmp_path / "session.csv"
    np.savetxt(log, np.column_stack([t, gyr, acc, mag]), delimiter=",", header=header,
               comments="")
    out = tmp_path / "calib.toml"
    assert cli_main(["calibrate", str(log), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "16 static poses" in printed and "field norm relative std" in printed
    cal = SensorCalibration.load(out)
    np.testing.assert_allclose(cal.accel_offset, ACC_OFFSET, atol=0.01)
    np.testing.assert_allclose(cal.mag_offset, HARD_IRON, atol=2e-3)
    # With a mounting rotation the fit is in body axes: offsets turn with it.
    assert cli_main(["calibrate", str(log), "-o", str(out), "--rotation", "ROLL_180"]) == 0
    np.testing.assert_allclose(SensorCalibration.load(out).accel_offset,
                               ACC_OFFSET * [1, -1, -1], atol=0.01)
    # Two files are pooled (with a gap between, so no still stretch spans both).
    g2, a2, m2, rate = log_samples([log, log], "gy86", None)
    assert len(g2) > 2 * len(gyr) and rate == pytest.approx(RATE)
    assert a2.shape == g2.shape and np.isnan(a2[len(gyr)]).all()  # the gap
    assert m2 is not None and np.isfinite(m2).all(axis=1).sum() == 2 * len(gyr)
    # A log with only the first three poses: refused, nothing written.
    short = tmp_path / "short.csv"
    n = round(3 * 2.1 * RATE)
    np.savetxt(short, np.column_stack([t, gyr, acc, mag])[:n], delimiter=",", header=header,
               comments="")
    bad_out = tmp_path / "bad.toml"
    assert cli_main(["calibrate", str(short), "-o", str(bad_out)]) == 2
    assert "distinct static pose" in capsys.readouterr().err and not bad_out.exists()
