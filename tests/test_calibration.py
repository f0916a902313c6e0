"""Sensor calibration: the file format, the fits on synthetic data with known errors,
refusal of data that cannot determine a calibration, and its application in ingest."""

from __future__ import annotations

import math

import numpy as np
import pytest
from bridge_support import MAG_NED, G, euler_q, gy86_counts

from bridge.app.calibrate_cli import log_samples
from bridge.app.cli import main as cli_main
from bridge.app.config import BridgeConfig
from bridge.vehicle.ingest import Ingest
from bridge.wire.mav import mavlink
from estimators import quat as Q
from imu.boards import gy86
from imu.calibration import SensorCalibration
from imu.calibration_fit import fit_calibration, fit_magnetometer, static_poses

RATE = 200.0
#: Known errors (numbers chosen here): corrected = M @ (raw - offset) must undo them.
ACC_ERROR = np.array([[1.03, 0.012, -0.008], [0.012, 0.97, 0.015], [-0.008, 0.015, 1.02]])
ACC_OFFSET = np.array([0.35, -0.22, 0.48])  # m/s^2 (36, 22, 49 mg)
GYRO_OFFSET = np.array([0.021, -0.013, 0.007])  # rad/s
#: Gyro scale and cross-axis errors: not symmetric (a rotation part too).
GYRO_ERROR = np.array([[1.012, 0.006, -0.004], [-0.005, 0.991, 0.007],
                       [0.003, -0.008, 1.009]])
SOFT_IRON = np.array([[1.10, 0.05, -0.03], [0.05, 0.92, 0.04], [-0.03, 0.04, 1.01]])
HARD_IRON = np.array([0.12, -0.07, 0.2])  # gauss
FIELD = 0.5  # gauss
DIP_DEG = 60.0


def fibonacci_directions(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = math.pi * (1.0 + 5.0 ** 0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def pose_attitude(down: np.ndarray, heading: float) -> np.ndarray:
    """Quaternion (body -> NED) of a board whose body sees gravity along ``down``."""
    cross = np.cross([0.0, 0.0, 1.0], down)
    if np.linalg.norm(cross) < 1e-9:  # already along ±z: none, or half a turn about x
        tilt = np.zeros(3) if down[2] > 0 else np.array([math.pi, 0.0, 0.0])
    else:
        tilt = cross / np.linalg.norm(cross) * math.atan2(np.linalg.norm(cross), down[2])
    return Q.multiply(Q.from_rotvec(np.array([0.0, 0.0, heading])),
                      Q.conjugate(Q.from_rotvec(tilt)))


def smoothstep(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quintic 0 -> 1 and its derivative (zero rate and acceleration at both ends)."""
    return u**3 * (10 - 15 * u + 6 * u**2), 30 * u**2 * (1 - u) ** 2


def synthetic_session(gravity_dirs: np.ndarray, rng: np.random.Generator,
                      hold_s: float = 1.5, move_s: float = 0.6,
                      acc_error: np.ndarray = ACC_ERROR, heading_step_deg: float = 60.0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gyr, acc, mag) of a board held still in each direction, turned in between.

    Physically consistent, as the gyro matrix fit needs: each pose has its own heading
    (``heading_step_deg`` apart), so the field (FIELD at DIP_DEG) points in many body directions;
    between poses the board turns about one fixed body axis along a quintic, and the
    gyro reads that turn through GYRO_ERROR; the hand's shake shows in the accelerometer.
    """
    dirs = gravity_dirs / np.linalg.norm(gravity_dirs, axis=1, keepdims=True)
    dip = math.radians(DIP_DEG)
    field = FIELD * np.array([math.cos(dip), 0.0, math.sin(dip)])
    poses = [pose_attitude(d, math.radians(heading_step_deg * i)) for i, d in enumerate(dirs)]
    n_hold, n_move = round(hold_s * RATE), round(move_s * RATE)
    u, du = smoothstep(np.arange(n_move) / n_move)
    q_parts, rate_parts, shake = [], [], []
    for i, q in enumerate(poses):
        q_parts.append(np.repeat(q[None], n_hold, axis=0))
        rate_parts.append(np.zeros((n_hold, 3)))
        shake.append(np.full(n_hold, 0.02))
        if i + 1 < len(poses):
            turn = Q.to_rotvec(Q.multiply(Q.conjugate(q), poses[i + 1]))
            q_parts.append(Q.multiply(q, Q.from_rotvec(u[:, None] * turn)))
            rate_parts.append(du[:, None] * turn / move_s)
            shake.append(np.full(n_move, 0.3))
    q_all, rates = np.concatenate(q_parts), np.concatenate(rate_parts)
    sigma = np.concatenate(shake)[:, None]
    f_true = Q.rotate(Q.conjugate(q_all), np.array([0.0, 0.0, -G]))  # at rest: away from g
    acc = f_true @ acc_error.T + ACC_OFFSET + rng.normal(0, 1.0, f_true.shape) * sigma
    gyr = rates @ GYRO_ERROR.T + GYRO_OFFSET + rng.normal(0, 0.002, rates.shape)
    mag_true = Q.rotate(Q.conjugate(q_all), field)
    mag = mag_true @ SOFT_IRON.T + HARD_IRON + rng.normal(0, 0.002, mag_true.shape)
    return gyr, acc, mag


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


def test_fit_recovers_gyro_scale_and_cross_axis_from_the_turns(synthetic):
    gyr, acc, mag = synthetic
    cal, report = fit_calibration(gyr, acc, mag, RATE)
    # The accelerometer frame is the body frame here (symmetric error), so the fitted
    # gyro correction must undo GYRO_ERROR, rotation part included, to 0.1 %.
    np.testing.assert_allclose(cal.gyro_matrix @ GYRO_ERROR, np.eye(3), atol=1e-3)
    assert report.gyro_turns == 15
    assert report.gyro_turn_error_before_deg > 0.5
    assert report.gyro_turn_error_after_deg < 0.05
    # Applied everywhere the offset is: cal.gyro, and the affine map ingest folds in.
    raw = np.array([[0.3, -1.2, 2.0]])
    np.testing.assert_allclose(cal.gyro(raw)[0], cal.gyro_matrix @ (raw[0] - GYRO_OFFSET),
                               atol=1e-3)
    m, c = cal.affine("gyro")
    np.testing.assert_allclose(m @ raw[0] + c, cal.gyro(raw)[0], atol=1e-12)


#: Six faces and eight corners; an error matrix with a rotation part, which no norm can see.
CORNERS = np.array([(i, j, k) for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
SIX_FACES_AND_CORNERS = np.vstack([np.eye(3), -np.eye(3), CORNERS])
ACC_ERROR_ROTATED = np.array([[1.03, 0.018, -0.004], [0.006, 0.97, 0.021],
                              [-0.012, 0.009, 1.02]])


def misalignment_deg(m: np.ndarray) -> float:
    """Angle of the rotation in m (its orthogonal polar factor)."""
    u, _, vt = np.linalg.svd(m)
    return float(np.degrees(np.arccos(np.clip((np.trace(u @ vt) - 1) / 2, -1, 1))))


def test_six_faces_give_the_full_accelerometer_matrix():
    gyr, acc, mag = synthetic_session(SIX_FACES_AND_CORNERS, np.random.default_rng(11),
                                      acc_error=ACC_ERROR_ROTATED)
    cal, report = fit_calibration(gyr, acc, mag, RATE)
    assert (report.accel_model, report.accel_faces) == ("full", 6)
    assert report.accel_face_residual_deg < 0.05
    assert misalignment_deg(ACC_ERROR_ROTATED) > 0.4  # what the symmetric fit would leave
    assert misalignment_deg(cal.accel_matrix @ ACC_ERROR_ROTATED) < 0.02
    np.testing.assert_allclose(cal.accel_matrix @ ACC_ERROR_ROTATED, np.eye(3), atol=5e-4)
    np.testing.assert_allclose(cal.accel_offset, ACC_OFFSET, atol=0.005)
    # The gyro is fitted in the corrected accelerometer's frame, i.e. the body's.
    np.testing.assert_allclose(cal.gyro_matrix @ GYRO_ERROR, np.eye(3), atol=1e-3)
    assert any("square on a level surface" in line for line in report.lines())


def test_without_six_square_faces_the_accelerometer_falls_back_and_says_so():
    # One face missing: the symmetric (norm-only) fit, with the reason in the report.
    five = np.delete(SIX_FACES_AND_CORNERS, 5, axis=0)  # no -z face
    gyr, acc, mag = synthetic_session(five, np.random.default_rng(12),
                                      acc_error=ACC_ERROR_ROTATED)
    cal, report = fit_calibration(gyr, acc, mag, RATE)
    assert (report.accel_model, report.accel_faces) == ("symmetric", 5)
    assert "accel: no rotation correction (only 5 of the 6 faces" in "\n".join(report.lines())
    assert misalignment_deg(cal.accel_matrix @ ACC_ERROR_ROTATED) > 0.4  # rotation stays
    assert report.accel_norm_rms_error_after < 0.01  # but the norms are right
    # A face tilted 1.5° (not square on the table): the face fit would carry the tilt.
    tilted = SIX_FACES_AND_CORNERS.copy()
    tilted[2] = [math.sin(math.radians(1.5)), 0.0, math.cos(math.radians(1.5))]
    gyr, acc, mag = synthetic_session(tilted, np.random.default_rng(13),
                                      acc_error=ACC_ERROR_ROTATED)
    _, report = fit_calibration(gyr, acc, mag, RATE)
    assert (report.accel_model, report.accel_faces) == ("symmetric", 6)
    assert "not square and level" in report.accel_note


def test_turns_about_one_axis_only_refuse_the_gyro_matrix():
    """Gravity only ever in the y-z plane and no change of heading: every turn is about
    body x, so the gyro's y and z columns are never seen."""
    angles = np.radians(np.arange(0, 360, 40))
    dirs = np.column_stack([np.zeros_like(angles), np.sin(angles), np.cos(angles)])
    gyr, acc, mag = synthetic_session(dirs, np.random.default_rng(14), heading_step_deg=0.0)
    with pytest.raises(ValueError, match="do not excite all axes"):
        fit_calibration(gyr, acc, mag, RATE, accel=False, magnetometer=False)
    cal, report = fit_calibration(gyr, acc, mag, RATE, accel=False, magnetometer=False,
                                  gyro_matrix=False)  # the offset alone is still fine
    assert report.gyro_turns == 0 and np.array_equal(cal.gyro_matrix, np.eye(3))
    np.testing.assert_allclose(cal.gyro_offset, GYRO_OFFSET, atol=5e-4)


def test_a_gyro_that_cannot_reproduce_the_turns_is_refused(synthetic):
    """Samples lost during one turn: no matrix explains it, so none is written."""
    gyr, acc, mag = synthetic
    gyr = gyr.copy()
    first_turn = slice(round(1.5 * RATE), round(2.1 * RATE))
    gyr[first_turn] = GYRO_OFFSET
    with pytest.raises(ValueError, match="even the best matrix leaves the turns"):
        fit_calibration(gyr, acc, mag, RATE)


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
    return SensorCalibration(gyro_offset=GYRO_OFFSET, gyro_matrix=np.linalg.inv(GYRO_ERROR),
                             accel_offset=ACC_OFFSET,
                             accel_matrix=np.linalg.inv(ACC_ERROR), mag_offset=HARD_IRON,
                             mag_matrix=np.linalg.inv(SOFT_IRON))


def test_toml_round_trip_is_exact(tmp_path):
    cal = known_calibration()
    path = tmp_path / "calib.toml"
    cal.save(path, comment="test\nsecond line")
    back = SensorCalibration.load(path)
    for name in ("gyro_offset", "gyro_matrix", "accel_offset", "accel_matrix", "mag_offset",
                 "mag_matrix"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cal, name))
    assert SensorCalibration().is_identity and not back.is_identity
    # Tables may be left out: they stay identity.
    path.write_text("[gyro]\noffset = [0.1, 0, 0]\n")
    partial = SensorCalibration.load(path)
    assert partial.gyro_offset.tolist() == [0.1, 0, 0]
    assert partial.accel_matrix.tolist() == np.eye(3).tolist()
    assert partial.gyro_matrix.tolist() == np.eye(3).tolist()


def test_files_written_before_the_gyro_matrix_still_load(tmp_path):
    """The format before ``[gyro] matrix`` existed: the gyro matrix is the identity."""
    path = tmp_path / "old.toml"
    path.write_text("[gyro]\noffset = [0.01, -0.02, 0.003]\n\n[accel]\n"
                    "offset = [0.1, 0.2, 0.3]\nmatrix = [[1.01, 0.0, 0.0], [0.0, 0.99, 0.0], "
                    "[0.0, 0.0, 1.0]]\n\n[mag]\noffset = [0.0, 0.0, 0.0]\n"
                    "matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n")
    cal = SensorCalibration.load(path)
    assert cal.gyro_matrix.tolist() == np.eye(3).tolist()
    raw = np.array([0.5, 0.5, 0.5])
    np.testing.assert_array_equal(cal.gyro(raw), raw - cal.gyro_offset)
    assert "[gyro]\noffset = [0.01, -0.02, 0.003]\nmatrix = [" in cal.to_toml()


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
    from bridge.app.cli import build_parser
    from bridge.app.run_cli import config_from_args

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
    assert "scale and cross-axis from 15 turns" in printed
    np.testing.assert_allclose(cal.gyro_matrix @ GYRO_ERROR, np.eye(3), atol=1e-3)
    assert cli_main(["calibrate", str(log), "-o", str(out), "--no-gyro-matrix"]) == 0
    assert "scale and cross-axis" not in capsys.readouterr().out
    offset_only = SensorCalibration.load(out)
    assert np.array_equal(offset_only.gyro_matrix, np.eye(3))
    np.testing.assert_array_equal(offset_only.gyro_offset, cal.gyro_offset)
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


# --- implausible files (hostile-input sweep) --------------------------------------------

@pytest.mark.parametrize("text, message", [
    ("[gyro]\noffset = [10, 10, 10]\n", r"gyro\.offset is not a plausible offset .*rad/s"),
    ("[accel]\noffset = [1e308, 1e308, 1e308]\n", r"accel\.offset is not a plausible offset"),
    ("[accel]\noffset = [100, 0, 0]\n", r"accel\.offset is not a plausible offset .*m/s\^2"),
    ("[mag]\noffset = [1e6, 0, 0]\n", r"mag\.offset is not a plausible offset .*gauss"),
    ("[accel]\noffset = [true, false, true]\n", r"accel\.offset must be numbers, not true/false"),
    ("[gyro]\nmatrix = [[true, 0, 0], [0, 1, 0], [0, 0, 1]]\n",
     r"gyro\.matrix must be numbers, not true/false"),
])
def test_implausible_offsets_and_booleans_are_refused(tmp_path, text, message):
    """Offsets far beyond any MEMS sensor's (a wrong unit or file) made the estimate
    silently wrong; TOML booleans passed as the numbers 1 and 0."""
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        SensorCalibration.load(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_offsets_are_bounded_when_built_in_code_too():
    with pytest.raises(ValueError, match="gyro_offset is not a plausible offset"):
        SensorCalibration(gyro_offset=np.array([1.0, 0.0, 0.0]))  # 57 °/s
    with pytest.raises(ValueError, match="must be numbers, not true/false"):
        SensorCalibration(accel_offset=np.array([True, False, False]))
    # Realistic worst cases pass: MPU6050 ±20 °/s, ±80 mg; hard iron of a few gauss.
    SensorCalibration(gyro_offset=np.radians([20.0, -20.0, 20.0]),
                      accel_offset=np.array([0.8, -0.8, 1.2]), mag_offset=np.array([3, 0, 0]))


@pytest.mark.filterwarnings("error")  # a numpy RuntimeWarning must not reach the user
def test_huge_matrix_is_refused_without_a_numpy_warning(tmp_path):
    path = tmp_path / "huge.toml"
    path.write_text("[accel]\nmatrix = [[1e300, 0, 0], [0, 1e300, 0], [0, 0, 1e300]]\n")
    with pytest.raises(ValueError, match=r"accel\.matrix is not a plausible correction"):
        SensorCalibration.load(path)


def test_a_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "binary.toml"
    path.write_bytes(b"\xff\xfe bad")
    with pytest.raises(ValueError, match=r"not valid TOML \(not UTF-8 text") as info:
        SensorCalibration.load(path)
    assert str(info.value).startswith(f"{path}: ")


# --- correction matrices of implausible scale (hostile-input sweep) ---------------------

@pytest.mark.parametrize("text, message", [
    # 100·I passed as "a multiple of the identity", then every accelerometer sample was
    # implausible after scaling and the eskf output froze without a word.
    ("[accel]\nmatrix = [[100, 0, 0], [0, 100, 0], [0, 0, 100]]\n",
     r"accel\.matrix is not a plausible correction \(scale \|det\|\^\(1/3\) = 100, "),
    ("[gyro]\nmatrix = [[100, 0, 0], [0, 100, 0], [0, 0, 100]]\n",
     r"gyro\.matrix is not a plausible correction \(scale \|det\|\^\(1/3\) = 100, "),
    ("[accel]\nmatrix = [[0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]]\n",
     r"accel\.matrix is not a plausible correction \(scale .* = 0\.5, not in 0\.8\.\.1\.25"),
    ("[gyro]\nmatrix = [[1.4, 0, 0], [0, 1.4, 0], [0, 0, 1.4]]\n",
     r"gyro\.matrix is not a plausible correction \(scale .* = 1\.4, not in 0\.8\.\.1\.25"),
    # The magnetometer's scale is free, but not to where the field vanishes or overflows.
    ("[mag]\nmatrix = [[1e7, 0, 0], [0, 1e7, 0], [0, 0, 1e7]]\n",
     r"mag\.matrix is not a plausible correction \(scale .* = 1e\+07, not in 1e-06\.\.1e\+06"),
    ("[mag]\nmatrix = [[1e-7, 0, 0], [0, 1e-7, 0], [0, 0, 1e-7]]\n",
     r"mag\.matrix is not a plausible correction \(scale .* = 1e-07, not in 1e-06\.\.1e\+06"),
])
def test_matrices_of_implausible_scale_are_refused(tmp_path, text, message):
    path = tmp_path / "scale.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        SensorCalibration.load(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)


def test_plausible_scales_still_load_and_the_magnetometer_scale_is_free():
    """MEMS scale errors of 15 % with cross-axis terms pass; a magnetometer matrix may
    carry any unit change (gauss to microtesla: 100) since only its direction is used."""
    tilt = np.array([[0.0, 0.02, -0.01], [0.015, 0.0, 0.02], [-0.02, 0.01, 0.0]])
    SensorCalibration(gyro_matrix=1.15 * np.eye(3) + tilt, accel_matrix=0.85 * np.eye(3) + tilt,
                      mag_matrix=100.0 * (SOFT_IRON + tilt))
    SensorCalibration(mag_matrix=1e-3 * np.eye(3))
    with pytest.raises(ValueError, match=r"accel_matrix is not a plausible correction \(scale"):
        SensorCalibration(accel_matrix=100.0 * np.eye(3))


@pytest.mark.filterwarnings("error")  # a numpy RuntimeWarning must not reach the user
@pytest.mark.parametrize("table", ["gyro", "accel", "mag"])
@pytest.mark.parametrize("matrix", [
    "[[1e308, 0, 0], [0, 1, 0], [0, 0, 1]]",
    "[[1, 0, 0], [0, 1e308, 0], [0, 0, 1e-300]]",  # scale 1e2.7, wildly anisotropic
    "[[1e308, 1e308, 0], [-1e308, 1e308, 0], [0, 0, 1]]",
    "[[1e-300, 0, 0], [0, 1, 0], [0, 0, 1]]",
    # |det|^(1/3) beyond the largest float (1.8e308): must not raise OverflowError.
    "[[1.7e308, 1.7e308, 1.7e308], [1.7e308, -1.7e308, 1.7e308], [1.7e308, 1.7e308, -1.7e308]]",
])
def test_an_absurd_magnitude_is_not_called_singular(tmp_path, table, matrix):
    """A 1e308 entry overflowed the row norms to inf and the matrix was refused as
    'singular'; it is a not plausible correction, and the message must say that."""
    path = tmp_path / "absurd.toml"
    path.write_text(f"[{table}]\nmatrix = {matrix}\n")
    with pytest.raises(ValueError, match=rf"{table}\.matrix is not a plausible correction"):
        SensorCalibration.load(path)


@pytest.mark.filterwarnings("error")
def test_a_singular_matrix_of_huge_entries_is_still_called_singular(tmp_path):
    path = tmp_path / "flat.toml"
    path.write_text("[mag]\nmatrix = [[1e308, 0, 0], [1e308, 0, 0], [0, 0, 1]]\n")
    with pytest.raises(ValueError, match=r"mag\.matrix is singular"):
        SensorCalibration.load(path)


def test_run_command_refuses_a_calibration_of_implausible_scale(tmp_path, capsys):
    """The sweep's reproduction: `run --calibration X.toml` with ``[accel] matrix = 100·I``
    ran with a frozen eskf; it must stop before starting, naming the file and the key."""
    path = tmp_path / "x.toml"
    path.write_text("[accel]\nmatrix = [[100, 0, 0], [0, 100, 0], [0, 0, 100]]\n")
    assert cli_main(["run", "--duration", "3", "--calibration", str(path)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "accel.matrix is not a plausible correction" in err
