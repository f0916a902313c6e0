"""Replay of every development log and a BROAD trial equals an independent computation.

The oracle reads the raw file with pyulog / pymavlink / numpy in the test, converts
units itself, runs the estimator through ``estimators.run`` and scores with scipy.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from _replay_oracle import reference_on, run_and_score, wxyz_to_rot
from scipy.spatial.transform import Rotation

import replay

os.environ["MAVLINK20"] = "1"
ESTIMATOR = "mahony"  # any registered filter works; mahony uses acc and mag
# The oracle runs the filter unaided: what is checked here is reading, units, alignment and
# scoring. (Aiding from the logs' velocities has its own tests in test_replay_real_logs.)
UNAIDED = {"aid": "none"}
KEYS = ("total_deg", "heading_deg", "inclination_deg", "roll_deg", "pitch_deg", "yaw_deg")


def assert_scores_match(score: replay.Score, oracle: dict[str, float]) -> None:
    assert score.samples == oracle["samples"]
    for key in KEYS:
        assert getattr(score, key) == pytest.approx(oracle[key], rel=1e-6, abs=1e-7), key


def ulog_oracle(path) -> tuple[dict[str, float], str, int]:
    from pyulog import ULog

    log = ULog(str(path))
    topics = {d.name: d.data for d in log.data_list if d.multi_id == 0}
    sc = topics["sensor_combined"]
    t0 = int(sc["timestamp"][0])  # PX4 may use epoch µs: subtract in integers first

    def seconds(stamps):
        return (stamps.astype(np.int64) - t0) / 1e6

    t = seconds(sc["timestamp"])
    gyr = np.column_stack([sc[f"gyro_rad[{i}]"] for i in range(3)])
    acc = np.column_stack([sc[f"accelerometer_m_s2[{i}]"] for i in range(3)])
    vm = topics["vehicle_magnetometer"]
    tm = seconds(vm["timestamp_sample"] if "timestamp_sample" in vm else vm["timestamp"])
    m = np.column_stack([vm[f"magnetometer_ga[{i}]"] for i in range(3)])
    held = np.searchsorted(tm, t, side="right") - 1  # last magnetometer reading so far
    start = int(np.argmax(held >= 0))
    t, gyr, acc, mag = t[start:], gyr[start:], acc[start:], m[held[start:]]
    name = ("vehicle_attitude_groundtruth" if "vehicle_attitude_groundtruth" in topics
            else "vehicle_attitude")
    att = topics[name]
    # SITL's groundtruth leaves timestamp_sample at 0: then only `timestamp` is a time.
    sample_time = att.get("timestamp_sample")
    usable = sample_time is not None and np.all(sample_time > 0)
    t_ref = seconds(sample_time if usable else att["timestamp"])
    q_ref = np.column_stack([att[f"q[{i}]"] for i in range(4)])
    ref, inside = reference_on(t_ref, q_ref, t)
    kind = "truth" if name.endswith("groundtruth") else "autopilot"
    # PX4's own declination parameter [deg]: what replay applies (references are true north)
    declination = log.initial_parameters["EKF2_MAG_DECL"]
    return (run_and_score(ESTIMATOR, t, gyr, acc, mag, ref, inside,
                          declination_deg=declination), kind, len(t))


@pytest.mark.parametrize("name", [
    "pyulog_sample_log_small.ulg",
    "pyulog_sample_logging_tagged_and_default_params.ulg",
    "pyulog_sample_px4_events.ulg",
])
def test_ulog_replay_matches_independent_scoring(data_dir, name):
    path = data_dir / "logs" / name
    oracle, kind, n = ulog_oracle(path)
    ev = replay.evaluate(replay.load(path), [ESTIMATOR], **UNAIDED)
    assert ev.recording.n == n
    assert ev.reference_kind == kind
    assert_scores_match(ev.scores[ESTIMATOR], oracle)
    # A static or slowly moving log: the filter agrees with PX4 / truth within degrees.
    assert ev.scores[ESTIMATOR].inclination_deg < 2.0
    assert ev.prepared.declination.source == "vehicle parameter EKF2_MAG_DECL"


def test_sitl_log_with_groundtruth_is_scored_against_truth(data_dir):
    path = data_dir / "logs" / "pyulog_sample_logging_tagged_and_default_params.ulg"
    assert replay.load(path).reference.kind == "truth"
    assert replay.load(path, reference="autopilot").reference.source == "vehicle_attitude"


def test_tlog_replay_matches_independent_scoring(data_dir):
    from pymavlink import mavutil

    path = data_dir / "logs" / "dronekit_flight_replay_flight.tlog"
    conn = mavutil.mavlink_connection(str(path))
    imu, att, dec, cutoff = [], [], [], []
    while (msg := conn.recv_match(type=["RAW_IMU", "ATTITUDE", "PARAM_VALUE"])) is not None:
        if msg.get_type() == "PARAM_VALUE":
            if msg.param_id == "COMPASS_DEC":
                dec.append(msg.param_value)
            if msg.param_id == "INS_GYRO_FILTER":
                cutoff.append(msg.param_value)
            continue
        (imu if msg.get_type() == "RAW_IMU" else att).append(msg)
    t_all = np.array([m.time_usec for m in imu]) / 1e6
    # The vehicle rebooted once (board time jumps back); the longer session is replayed.
    cut = int(np.flatnonzero(np.diff(t_all) < -1.0)[0]) + 1
    assert len(t_all) - cut > cut
    rows = imu[cut:]
    t = t_all[cut:]
    # ArduPilot's integers are its floats truncated toward zero: k stands for k ± ½
    def middle(counts: list[list[int]]) -> np.ndarray:
        k = np.array(counts, dtype=float)
        return k + 0.5 * np.sign(k)

    gyr = middle([[m.xgyro, m.ygyro, m.zgyro] for m in rows]) * 1e-3  # mrad/s
    acc = middle([[m.xacc, m.yacc, m.zacc] for m in rows]) * 9.80665e-3  # mG
    mag = middle([[m.xmag, m.ymag, m.zmag] for m in rows]) * 1e-3  # mGauss
    start = rows[0]._timestamp - 1.0
    att = [m for m in att if m._timestamp >= start]
    t_ref = np.array([m.time_boot_ms for m in att]) / 1e3
    euler = np.array([[m.yaw, m.pitch, m.roll] for m in att])
    q_ref = Rotation.from_euler("ZYX", euler).as_quat()[:, [3, 0, 1, 2]]
    ref, inside = reference_on(t_ref, q_ref, t)
    # ArduPilot's COMPASS_DEC is in radians; its RAW_IMU is the gyro after its
    # INS_GYRO_FILTER 2-pole Butterworth low-pass, sqrt(2)/(2 pi f) late
    assert cutoff[-1] == 20.0
    oracle = run_and_score(ESTIMATOR, t, gyr, acc, mag, ref, inside,
                           declination_deg=np.degrees(dec[-1]),
                           imu_delay_s=np.sqrt(2.0) / (2.0 * np.pi * cutoff[-1]))

    rec = replay.load(path)
    assert rec.source == "RAW_IMU" and rec.n == len(t) and rec.board == "ardupilot"
    np.testing.assert_allclose(rec.acc, acc)
    # At 2.9 Hz replay refuses to score by default, and says why ...
    assert "too slow" in replay.evaluate(rec, [ESTIMATOR]).not_run
    # ... but the alignment and scoring path still equals the independent one.
    ev = replay.evaluate(rec, [ESTIMATOR], min_rate_hz=0.0, **UNAIDED)
    assert ev.reference_kind == "autopilot"
    assert ev.prepared.declination.source == "vehicle parameter COMPASS_DEC"
    assert ev.prepared.imu_delay.source == "INS_GYRO_FILTER 20 Hz"
    assert_scores_match(ev.scores[ESTIMATOR], oracle)
    # Level on the ground: the accelerometer reads about +1 g upward (-z in FRD).
    assert np.median(rec.acc[:20, 2]) == pytest.approx(-9.8, abs=0.5)


def test_broad_trial_matches_independent_scoring(data_dir):
    path = data_dir / "broad" / "10_undisturbed_slow_translation_A.npz"
    d = np.load(path)
    n = len(d["gyr"])
    t = np.arange(n) / float(d["rate"])
    q_ref = d["quat_ref"]
    valid = d["movement"] & np.all(np.isfinite(q_ref), axis=1)
    ref = wxyz_to_rot(np.where(np.isfinite(q_ref), q_ref, [1.0, 0, 0, 0]))
    oracle = run_and_score(ESTIMATOR, t, d["gyr"], d["acc"], d["mag"], ref, valid,
                           world="ENU")
    ev = replay.evaluate(replay.load(path), [ESTIMATOR], **UNAIDED)
    assert ev.reference_kind == "truth" and ev.recording.world == "ENU"
    assert_scores_match(ev.scores[ESTIMATOR], oracle)
