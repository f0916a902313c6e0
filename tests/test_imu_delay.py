"""An autopilot's low-pass-filtered IMU stream (imu.filter_delay) and the estimators'
``imu_delay``: the output carried forward by the filter's group delay."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

import estimators
from bridge.vehicle.imu_delay import ImuDelay
from estimators import quat as Q
from estimators.metrics import attitude_errors
from imu import filter_delay
from imu.filter_delay import butterworth2_delay_s, imu_filter_delay

G = 9.80665
FIELD_NED = np.array([0.2, 0.0, 0.45])
RATE = 400.0
PX4, ARDUPILOT, QUAD, ROVER = 12, 3, 2, 10


def _swinging(seconds: float = 20.0) -> tuple[np.ndarray, ...]:
    """A body swinging in roll, pitch and yaw (0.3-0.7 Hz, up to 1.3 rad/s), seen by
    sensors after ArduPilot's default 20 Hz 2-pole Butterworth low-pass (gyro and
    accelerometer alike), as RAW_IMU carries them. Returns gyro, acc, mag, truth."""
    n = round(seconds * RATE)
    t = np.arange(n) / RATE
    w = np.stack([0.5 * np.sin(2 * np.pi * 0.5 * t), 0.4 * np.sin(2 * np.pi * 0.7 * t + 1.0),
                  0.3 * np.sin(2 * np.pi * 0.3 * t)], axis=1) * 2.0
    truth = Q.identity(n)
    for i in range(1, n):
        truth[i] = Q.multiply(truth[i - 1], Q.from_rotvec(0.5 * (w[i - 1] + w[i]) / RATE))
    body = Q.conjugate(truth)
    acc = Q.rotate(body, np.array([0.0, 0.0, -G]))
    mag = Q.rotate(body, FIELD_NED)
    b, a = signal.butter(2, 20.0, fs=RATE)
    gyr_f = signal.lfilter(b, a, w, axis=0, zi=signal.lfilter_zi(b, a)[:, None] * w[:1])[0]
    acc_f = signal.lfilter(b, a, acc, axis=0, zi=signal.lfilter_zi(b, a)[:, None] * acc[:1])[0]
    return gyr_f, acc_f, mag, truth


def test_delay_of_a_two_pole_butterworth():
    """√2/(2π·f_c): 11.25 ms at ArduPilot's default 20 Hz, and what a discrete 2-pole
    Butterworth at 400 Hz actually delays a slow signal by (its group delay at 1 Hz)."""
    assert butterworth2_delay_s(20.0) == pytest.approx(0.011254, abs=1e-6)
    b, a = signal.butter(2, 20.0, fs=RATE)
    _, gd = signal.group_delay((b, a), w=[1.0], fs=RATE)
    assert gd[0] / RATE == pytest.approx(butterworth2_delay_s(20.0), rel=0.02)


def test_which_stream_is_late_and_by_how_much():
    assert imu_filter_delay(PX4, {"INS_GYRO_FILTER": 20.0}, QUAD) == filter_delay.NONE
    assert imu_filter_delay(None, {}, None) == filter_delay.NONE
    default = imu_filter_delay(ARDUPILOT, {}, QUAD)
    assert default.ms == pytest.approx(11.254, abs=1e-3)
    assert default.source == "ArduPilot default INS_GYRO_FILTER 20 Hz"
    assert imu_filter_delay(ARDUPILOT, {}, ROVER).source.endswith("4 Hz")  # Rover's default
    own = imu_filter_delay(ARDUPILOT, {"INS_GYRO_FILTER": 40.0}, QUAD)
    assert (round(own.ms, 3), own.source) == (5.627, "INS_GYRO_FILTER 40 Hz")
    assert imu_filter_delay(ARDUPILOT, {"INS_GYRO_FILTER": 0.0}, QUAD).seconds == 0.0
    for bad in (math.nan, -5.0, 1.0, math.inf):  # no cut-off: the default, said so
        got = imu_filter_delay(ARDUPILOT, {"INS_GYRO_FILTER": bad}, QUAD)
        assert got.seconds == default.seconds, got
        assert got.source.startswith(default.source + " (INS_GYRO_FILTER = "), got


def test_carrying_the_output_forward_removes_the_filters_lag():
    """Attitude from a 20 Hz low-passed stream lags the body by the filter's delay; with
    ``imu_delay`` what is left is what the filter took from the motion, not its lag
    (measured, RMS total: eskf 0.598° -> 0.098°, mahony 0.579° -> 0.140°; the
    magnetometer here is not low-passed and not late: eskf's mag_delay 0)."""
    gyr, acc, mag, truth = _swinging()
    delay = butterworth2_delay_s(20.0)
    for name, limit in (("eskf", 0.14), ("mahony", 0.20)):
        given = {"mag_delay": 0.0} if name == "eskf" else {}
        late = estimators.batch(name, gyr, acc, mag, rate_hz=RATE, q0=truth[0], **given)
        now = estimators.batch(name, gyr, acc, mag, rate_hz=RATE, q0=truth[0],
                               imu_delay=delay, **given)
        err_late = np.degrees(np.sqrt(np.mean(attitude_errors(late, truth).total ** 2)))
        err_now = np.degrees(np.sqrt(np.mean(attitude_errors(now, truth).total ** 2)))
        assert err_late > 0.5, (name, err_late)
        assert err_now < limit, (name, err_now)


def test_imu_delay_is_the_same_per_sample_and_in_batch_in_any_frame():
    gyr, acc, mag, _ = _swinging(3.0)
    for world in ("NED", "ENU"):
        one = estimators.create("eskf", rate_hz=RATE, world=world, imu_delay=0.01)
        each = np.array([one.update(gyr[i], acc[i], mag[i]) for i in range(len(gyr))])
        assert np.abs(one.q - each[-1]).max() == 0.0  # the property says the same
        batch = estimators.batch("eskf", gyr, acc, mag, rate_hz=RATE, world=world,
                                 imu_delay=0.01)
        assert np.abs(batch - each).max() <= 1e-9
    ned = estimators.batch("eskf", gyr, acc, mag, rate_hz=RATE, imu_delay=0.01)
    enu = estimators.batch("eskf", gyr, acc, mag, rate_hz=RATE, world="ENU", imu_delay=0.01)
    assert np.abs(enu - Q.ned_to_enu(ned)).max() < 1e-9


def test_set_imu_delay_changes_the_output_not_the_estimate():
    gyr, acc, mag, _ = _swinging(3.0)
    built = estimators.create("eskf", rate_hz=RATE, mag_delay=0.02, imu_delay=0.011)
    told = estimators.create("eskf", rate_hz=RATE, mag_delay=0.02)
    told.set_imu_delay(0.011)
    assert np.array_equal(built.run(gyr, acc, mag).q, told.run(gyr, acc, mag).q)
    # the magnetometer is 9 ms older than the late gyro, not 20: the estimate is that of
    # mag_delay 9 ms, carried forward by 11 ms
    plain = estimators.create("eskf", rate_hz=RATE, mag_delay=0.009).run(gyr, acc, mag)
    late = estimators.batch("eskf", gyr, acc, mag, rate_hz=RATE, mag_delay=0.02,
                            imu_delay=0.011)
    turned = Q.angle_between(plain.q, late)
    rate = np.linalg.norm(gyr - plain.bias, axis=1)
    assert np.allclose(turned, rate * 0.011, atol=1e-9)
    # switched while running: the next output is the same estimate turned forward
    live = estimators.create("eskf", rate_hz=RATE)
    live.run(gyr, acc, mag)
    before = live.q
    live.set_imu_delay(0.011)
    rate = np.linalg.norm(gyr[-1] - live.bias)
    assert Q.angle_between(before, live.q) == pytest.approx(rate * 0.011, abs=1e-9)
    live.set_imu_delay(0.0)
    assert np.abs(live.q - before).max() == 0.0


@pytest.mark.parametrize("bad", [-0.001, 0.2, math.nan, math.inf])
def test_an_imu_delay_no_filter_has_is_refused(bad):
    with pytest.raises(ValueError, match="imu_delay"):
        estimators.create("eskf", imu_delay=bad)
    with pytest.raises(ValueError, match="imu_delay"):
        estimators.create("mahony").set_imu_delay(bad)


def test_the_smoother_is_carried_forward_like_the_online_filter():
    """(measured: smoothed 0.572° RMS total without imu_delay, 0.080° with it)"""
    gyr, acc, mag, truth = _swinging(8.0)
    delay = butterworth2_delay_s(20.0)
    res = estimators.smooth("eskf", gyr, acc, mag, rate_hz=RATE, q0=truth[0],
                            imu_delay=delay, mag_delay=0.0)
    online = estimators.batch("eskf", gyr, acc, mag, rate_hz=RATE, q0=truth[0],
                              imu_delay=delay, mag_delay=0.0)
    assert np.abs(res.online.q - online).max() <= 1e-9
    err = np.degrees(np.sqrt(np.mean(attitude_errors(res.q, truth).total ** 2)))
    assert err < 0.115, err


def test_live_delay_follows_the_autopilot_and_its_parameter():
    d = ImuDelay(1)
    assert d.plan(ARDUPILOT, QUAD)  # ArduPilot's default at once...
    assert d.status() == {"ms": 11.25, "source": "ArduPilot default INS_GYRO_FILTER 20 Hz"}
    assert d.param_to_send(0.0) == "INS_GYRO_FILTER"  # ... and its own value asked
    assert d.param_to_send(0.5) is None
    assert not d.on_param("COMPASS_DEC", 0.2)
    assert d.on_param("INS_GYRO_FILTER", 40.0)
    assert d.status() == {"ms": 5.63, "source": "INS_GYRO_FILTER 40 Hz"}
    assert d.param_to_send(5.0) is None  # answered
    assert not d.plan(ARDUPILOT, QUAD)  # a disarm: asked again, its value kept meanwhile
    assert d.param_to_send(6.0) == "INS_GYRO_FILTER"
    assert d.seconds == pytest.approx(butterworth2_delay_s(40.0))
    assert d.on_param("INS_GYRO_FILTER", math.nan)  # nonsense: the default again
    assert d.seconds == pytest.approx(butterworth2_delay_s(20.0))
    assert d.plan(PX4, QUAD) and d.seconds == 0.0 and d.param_to_send(9.0) is None


def test_a_nonsense_parameter_falls_back_to_the_default_with_a_warning(caplog):
    d = ImuDelay(7)
    d.plan(ARDUPILOT, QUAD)
    d.param_to_send(0.0)
    d.on_param("INS_GYRO_FILTER", -3.0)
    assert d.seconds == pytest.approx(butterworth2_delay_s(20.0))
    assert any(r.levelname == "WARNING" and "INS_GYRO_FILTER = -3.0 is no cut-off" in
               r.getMessage() for r in caplog.records)


def test_the_table_says_how_late_the_imu_is():
    from bridge.app.table import vehicle_lines

    late = {"imu_stream": {"message": "RAW_IMU", "asked_hz": 250.0},
            "imu_delay": {"ms": 11.25, "source": "INS_GYRO_FILTER 20 Hz"}}
    assert vehicle_lines(1, late)[1].endswith(", 11.2 ms late (INS_GYRO_FILTER 20 Hz)")
    on_time = {**late, "imu_delay": {"ms": 0.0, "source": "none"}}
    assert "late" not in vehicle_lines(1, on_time)[1]
