"""The whole-session scores against the truth (``session_vs_truth`` in the status, the
summary's last line per vehicle): every truth sample counted once, for every estimator
and the vehicle's own attitude, and the same number the replay of the session's record
finds. Real UDP, real pymavlink encoding, the real emulator and the real replay."""

from __future__ import annotations

import json

import numpy as np
import pytest
from bridge_support import UdpListener, async_test, running_bridge, stream_emulator

from bridge.app.cli import main
from bridge.app.table import summary
from bridge.estimate.session import SessionScores
from bridge.vehicle.ring import TimeRing
from estimators import quat as Q
from hil import EmulatorConfig


@async_test
async def test_session_scores_are_the_replays_numbers(tmp_path, capsys):
    record = tmp_path / "session.tlog"
    cfg = EmulatorConfig(profile="flight", duration_s=15.0, seed=5, fast=True)
    listener = UdpListener()
    out_port = await listener.start()
    async with running_bridge(estimators=["eskf", "mahony"], out_rate=50.0,
                              imu_rate=cfg.imu_rate_hz, max_source_rate=1e7,
                              record=str(record)) as bridge:
        await stream_emulator(bridge, cfg, out_port)
        bridge.publish_status()
        status = bridge.last_status[cfg.sysid]
        text = summary(bridge)
    listener.close()
    session = status["session_vs_truth"]
    assert set(session) == {"eskf", "mahony", "(vehicle own)"}
    # every truth sample once: the emulator sends its truth at the IMU rate, so about as
    # many as the IMU samples the estimators saw
    imu = status["estimator_counters"]["eskf"]["samples"]
    assert 0.9 * imu <= session["eskf"]["samples"] <= imu
    assert "against the truth over the whole session" in text and "eskf " in text
    out = tmp_path / "replay.json"
    assert main(["replay", str(record), "-e", "eskf", "-e", "mahony", "--json", str(out),
                 "-q"]) == 0
    capsys.readouterr()
    replayed = json.loads(out.read_text())["estimators"]
    # the same samples, the same estimators, the emulator's truth stamped on the board
    # clock, every series interpolated to the truth's times: equal but for the status's
    # rounding to 0.001 deg (measured: 0.05 % apart at most, the same in every run). The
    # replay takes the emulator's own ATTITUDE, not the bridge's ATTITUDE_QUATERNION.
    for label in ("eskf", "mahony", "autopilot"):
        for part in ("total_deg", "inclination_deg"):
            live = session["(vehicle own)" if label == "autopilot" else label][part]
            assert abs(live - replayed[label][part]) <= 0.001 * replayed[label][part], \
                (label, part)


def test_each_truth_sample_counts_once_across_ticks_and_a_reboot():
    """Ticks that overlap count nothing twice; after a reboot (the board clock starts
    at 0 again) the new timeline is counted too, on top of the old sums."""
    truth, est = TimeRing(5000, 4), TimeRing(5000, 4)
    tilt = Q.from_axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(1.0))
    scores = SessionScores()

    def feed(t0: float, n: int) -> None:
        for k in range(n):
            t = t0 + k * 0.01
            truth.push(t, Q.identity())
            est.push(t, tilt)

    feed(0.0, 500)
    scores.update(truth, {"eskf": est})
    scores.update(truth, {"eskf": est})  # nothing new
    feed(5.0, 500)
    scores.update(truth, {"eskf": est})
    first = scores.to_dict()["eskf"]
    assert first["samples"] == 1000
    assert first["inclination_deg"] == pytest.approx(1.0, abs=1e-6)
    truth.clear()
    est.clear()
    scores.new_timeline()
    feed(0.0, 300)
    scores.update(truth, {"eskf": est})
    assert scores.to_dict()["eskf"]["samples"] == 1300


def test_a_slower_series_is_interpolated_to_the_truth_not_paired_with_its_nearest():
    """The vehicle's own attitude comes at 50 Hz, the truth at 200 Hz: an attitude that
    is exactly the truth at its own instants scores (almost) nothing while the body
    turns at 60°/s, as in the replay. Paired with its nearest sample instead, up to
    10 ms away, it was charged about 0.3° (live 0.514° against the replay's 0.489° in a
    PX4 flight)."""
    rate_deg_s = 60.0
    truth, own, est = TimeRing(5000, 4), TimeRing(5000, 4), TimeRing(5000, 4)

    def attitude(t: float) -> np.ndarray:
        return Q.from_euler(np.array([0.1]), np.array([0.05]),
                            np.array([np.radians(rate_deg_s) * t]))[0]

    for k in range(2000):  # 10 s at 200 Hz
        t = k / 200.0
        truth.push(t, attitude(t))
        est.push(t, attitude(t))
        if k % 4 == 0:
            own.push(t, attitude(t))
    scores = SessionScores()
    scores.update(truth, {"eskf": est}, own)
    got = scores.to_dict()
    assert got["(vehicle own)"]["samples"] >= 1990
    assert got["(vehicle own)"]["total_deg"] < 0.005, got
    assert got["eskf"]["total_deg"] < 0.005, got


def test_a_slower_series_behind_the_estimators_has_its_newest_truth_scored_later():
    """At a status tick the estimators have reached the newest truth sample but the
    vehicle's own 50 Hz attitude has not: those samples are scored at a later tick, not
    dropped. Dropping them scored the vehicle's own attitude over a tick-dependent subset
    (a live session 0.24 % off its replay's number)."""
    truth, own, est = TimeRing(20000, 4), TimeRing(20000, 4), TimeRing(20000, 4)
    rate = np.radians(60.0)

    def attitude(t: float) -> np.ndarray:
        return Q.from_euler(np.array([0.1]), np.array([0.05]), np.array([rate * t]))[0]

    ticked, at_end = SessionScores(), SessionScores()
    own_tilt = Q.from_axis_angle(np.array([0.0, 1.0, 0.0]), np.radians(2.0))
    for k in range(2000):  # 10 s at 200 Hz, a tick every 0.25 s
        t = k / 200.0
        truth.push(t, attitude(t))
        est.push(t, attitude(t))
        if k % 4 == 0:
            own.push(t, Q.multiply(attitude(t), own_tilt))
        if k % 50 == 47:  # the last own sample is 15 ms behind the estimators
            ticked.update(truth, {"eskf": est}, own)
    ticked.update(truth, {"eskf": est}, own)
    at_end.update(truth, {"eskf": est}, own)
    assert ticked.to_dict() == at_end.to_dict()
    assert ticked.to_dict()["(vehicle own)"]["samples"] >= 1990


def test_a_stopped_series_does_not_hold_the_estimators_back():
    truth, own, est = TimeRing(20000, 4), TimeRing(20000, 4), TimeRing(20000, 4)
    scores = SessionScores()
    for k in range(2000):
        t = k / 200.0
        truth.push(t, Q.identity())
        est.push(t, Q.identity())
        if t < 1.0:
            own.push(t, Q.identity())
        if k % 50 == 49:
            scores.update(truth, {"eskf": est}, own)
    got = scores.to_dict()
    assert got["eskf"]["samples"] == 2000
    assert 190 <= got["(vehicle own)"]["samples"] <= 200


def test_a_truth_on_an_imu_sample_counts_when_the_stream_pauses_after_it():
    """The truth is placed at the board time of the IMU sample read before it. An IMU
    stream that pauses for a few steps (a loaded autopilot) leaves that truth on an
    estimate's own time with the next estimate beyond the gap the pairing allows: on a
    sample nothing is interpolated, so it counts; truth inside the gap does not."""
    truth, est = TimeRing(5000, 4), TimeRing(5000, 4)
    tilt = Q.from_axis_angle(np.array([0.0, 1.0, 0.0]), np.radians(2.0))
    t_imu = np.r_[np.arange(0, 100) * 0.004, 0.4 + 0.02 + np.arange(0, 100) * 0.004]
    for t in t_imu:  # one truth per IMU sample, on its time; a 20-ms pause after 0.396 s
        est.push(float(t), tilt)
        truth.push(float(t), Q.identity())
    truth.push(0.405, Q.identity())  # a truth inside the pause: no estimate around it
    scores = SessionScores()
    scores.update(truth, {"eskf": est})
    got = scores.to_dict()["eskf"]
    assert got["samples"] == len(t_imu)
    assert got["inclination_deg"] == pytest.approx(2.0, abs=1e-6)
