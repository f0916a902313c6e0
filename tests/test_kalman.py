"""The quaternion Kalman filter (seed 002) against its own closed-form behaviour.

With P₀, Q and R multiples of I and H = I, P stays a multiple of I (A is a scaled
rotation of R⁴: AAᵀ = (1 + |ω|²dt²/4)·I for the first-order A, = I for the exact one).
The filter then reduces to scalars: ``p⁻ = s·p + Q·dt``, ``k = p⁻/(p⁻ + R/dt)``,
``p = (1 − k)p⁻`` and ``q ← normalise((1 − k)q⁻ + k·z)``. For a fixed measurement z at
quaternion-space angle φ from q, that nlerp gives ``tan φ' = (1−k) sin φ / (k + (1−k) cos φ)``
and the attitude error is 2φ. z is fixed when the error is a pure roll about north or
a pure pitch about east and the field is horizontal (the shortest arc from the predicted
to the measured down is then exactly the error, and the field seen through the prediction
keeps pointing north) — the paper's two static tests, roll 15.9° and pitch 9.2°, taken
separately as in its Fig. 5(a)/(b).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import estimators
from estimators import quat as Q

G = 9.80665
ROLL, PITCH = math.radians(15.9), math.radians(9.2)  # the paper's static test attitude
FIELD_NED = np.array([0.2, 0.0, 0.45])  # dip 66°, about Berlin's
FIELD_HORIZONTAL = np.array([0.2, 0.0, 0.0])  # magnetic equator
DEFAULTS = estimators.estimator_class("kalman").Params()


def _static(truth: np.ndarray, n: int, with_mag: bool,
            field: np.ndarray = FIELD_NED) -> tuple[np.ndarray, np.ndarray | None]:
    acc = np.tile(Q.rotate(Q.conjugate(truth), np.array([0.0, 0.0, -G])), (n, 1))
    mag = np.tile(Q.rotate(Q.conjugate(truth), field), (n, 1)) if with_mag else None
    return acc, mag


def _scalar_recursion(rate: float, n: int, angle0: float, p0: float, q_density: float,
                      r_density: float) -> tuple[np.ndarray, np.ndarray]:
    """Attitude error (rad) and p after each of n static samples with a fixed z."""
    dt = 1.0 / rate
    phi, p = angle0 / 2.0, p0
    errors, ps = np.empty(n), np.empty(n)
    for i in range(n):
        p_pred = p + q_density * dt
        k = p_pred / (p_pred + r_density / dt)
        p = (1.0 - k) * p_pred
        phi = math.atan2((1.0 - k) * math.sin(phi), k + (1.0 - k) * math.cos(phi))
        errors[i], ps[i] = 2.0 * phi, p
    return errors, ps


@pytest.mark.parametrize("rate", [100.0, 1000.0, 8000.0])
@pytest.mark.parametrize("truth", [Q.from_euler(ROLL, 0.0, 0.0), Q.from_euler(0.0, PITCH, 0.0)],
                         ids=["roll15.9", "pitch9.2"])
def test_static_tilt_converges_as_the_scalar_recursion(rate, truth):
    """Started level: the error follows the scalar recursion sample by sample, and with the
    defaults (τ = √(R/Q) ≈ 3.2 s, independent of the rate) it is below 0.1° within 8 s."""
    n = round(8.0 * rate)
    acc, mag = _static(truth, n, with_mag=True, field=FIELD_HORIZONTAL)
    est = estimators.create("kalman", rate_hz=rate, q0=Q.identity())
    q = est.run(np.zeros((n, 3)), acc, mag).q
    expected, ps = _scalar_recursion(rate, n, Q.angle_between(Q.identity(), truth),
                                     DEFAULTS.p0, DEFAULTS.process_noise,
                                     DEFAULTS.measurement_noise)
    assert np.abs(Q.angle_between(q, truth) - expected).max() < 1e-9
    assert np.allclose(est.covariance, ps[-1] * np.eye(4), rtol=1e-9, atol=1e-12 * ps[-1])
    assert math.degrees(Q.angle_between(q[-1], truth)) < 0.1
    assert np.allclose(Q.canonical(est.measurement), Q.canonical(truth), atol=1e-12)


@pytest.mark.parametrize("yaw_error_deg", [30.0, -150.0])
def test_heading_error_converges_as_the_scalar_recursion(yaw_error_deg):
    """Level, heading off by a yaw error δ, dipped field: the down vectors agree (r = 1) and
    the field seen through the prediction is rotated by exactly δ, so z is the truth and the
    recursion holds again — also for a large error (-150°); below 0.1° within 20 s."""
    truth = Q.from_euler(0.0, 0.0, math.radians(10.0))
    q0 = Q.from_euler(0.0, 0.0, math.radians(10.0 + yaw_error_deg))
    rate, n = 200.0, 4000  # 20 s
    acc, mag = _static(truth, n, with_mag=True)
    q = estimators.batch("kalman", np.zeros((n, 3)), acc, mag, rate_hz=rate, q0=q0)
    expected, _ = _scalar_recursion(rate, n, math.radians(abs(yaw_error_deg)), DEFAULTS.p0,
                                    DEFAULTS.process_noise, DEFAULTS.measurement_noise)
    assert np.abs(Q.angle_between(q, truth) - expected).max() < 1e-9
    assert math.degrees(Q.angle_between(q[-1], truth)) < 0.1


def test_combined_tilt_with_dipped_field_converges():
    """Roll and pitch together under a 66° dip: z is no longer fixed (the heading measured
    through a wrongly tilted prediction is off by ~tilt error·tan(dip)), so the heading
    converges more slowly than the tilt. The inclination still follows the scalar rate:
    below 0.1° within 8 s; the total error is below 0.2° within 15 s."""
    from estimators import metrics

    truth = Q.from_euler(ROLL, PITCH, 0.0)
    rate = 200.0
    n = round(15.0 * rate)
    acc, mag = _static(truth, n, with_mag=True)
    q = estimators.batch("kalman", np.zeros((n, 3)), acc, mag, rate_hz=rate, q0=Q.identity())
    errors = metrics.attitude_errors(q, truth)
    assert math.degrees(errors.inclination[round(8.0 * rate) - 1]) < 0.1
    assert math.degrees(errors.total[-1]) < 0.2
    assert math.degrees(errors.total[round(1.0 * rate)]) > 1.0  # it does take its time


def test_convergence_time_is_rate_independent():
    """Q and R are densities: the error after 1 s differs by < 3 % between 100 Hz and 8 kHz
    (with per-sample variances the 8 kHz filter would be ~80× faster)."""
    truth = Q.from_euler(ROLL, PITCH, 0.0)
    err = {}
    for rate in (100.0, 8000.0):
        n = round(1.0 * rate)
        acc, mag = _static(truth, n, with_mag=True)
        q = estimators.batch("kalman", np.zeros((n, 3)), acc, mag, rate_hz=rate,
                             q0=Q.identity())
        err[rate] = Q.angle_between(q[-1], truth)
    assert err[100.0] > math.radians(1.0)  # still converging: the comparison means something
    assert err[100.0] == pytest.approx(err[8000.0], rel=0.03)


def test_without_magnetometer_tilt_converges_and_yaw_is_kept():
    """No magnetometer: the measurement takes its heading from the prediction, so the tilt
    converges (within 10 s, as the scalar rate says) while yaw stays near the initial 40°
    instead of being pulled to 0."""
    yaw = math.radians(40.0)
    truth = Q.from_euler(ROLL, PITCH, yaw)
    n = 2000
    acc, _ = _static(truth, n, with_mag=False)
    q = estimators.batch("kalman", np.zeros((n, 3)), acc, rate_hz=200.0,
                         q0=Q.from_euler(0.0, 0.0, yaw))
    roll, pitch, yaw_est = Q.to_euler(q[-1])
    assert abs(roll - ROLL) < math.radians(0.1) and abs(pitch - PITCH) < math.radians(0.1)
    # The corrections are rotations about horizontal axes; composed, they shift the Z-Y-X
    # yaw by a term of second order in the tilt: at most sin(15.9°)·sin(9.2°) ≈ 2.5°.
    assert abs(yaw_est - yaw) < math.sin(ROLL) * math.sin(PITCH)


def test_vertical_magnetometer_is_ignored_for_heading():
    """A field straight down carries no heading: yaw must come from the prediction, not
    from the fallback reference used for initialisation."""
    yaw = math.radians(-120.0)
    truth = Q.from_euler(0.0, 0.0, yaw)
    n = 500
    acc, _ = _static(truth, n, with_mag=False)
    mag = np.tile([0.0, 0.0, 0.5], (n, 1))  # level body: vertical in body too
    q = estimators.batch("kalman", np.zeros((n, 3)), acc, mag, q0=truth)
    assert Q.angle_between(q, truth).max() < 1e-12


def test_measurement_is_kept_on_the_prediction_hemisphere():
    """q and −q are the same attitude. The update is given z on the far hemisphere of q:
    it must move q toward the attitude of z by the nlerp fraction k, as for +z (without the
    flip, q + k(−z − q) would head for the origin and, normalised, lose the attitude)."""
    from estimators import kalman

    est = estimators.create("kalman", q0=Q.identity())
    target = Q.from_euler(0.3, -0.2, 0.5)
    results = []
    for sign in (1.0, -1.0):
        state = est._state.copy()
        state[kalman.Z_START:kalman.Z_START + 4] = sign * target
        p, r = DEFAULTS.p0, 0.02
        kalman._update(state, r)
        q = state[0:4] / np.linalg.norm(state[0:4])
        results.append(q)
        k = p / (p + r)
        phi = Q.angle_between(Q.identity(), target) / 2.0
        expected = 2.0 * math.atan2((1.0 - k) * math.sin(phi), k + (1.0 - k) * math.cos(phi))
        assert Q.angle_between(q, target) == pytest.approx(expected, abs=1e-12)
        assert np.allclose(state[kalman.P_START:kalman.P_START + 16].reshape(4, 4),
                           (1.0 - k) * p * np.eye(4), atol=1e-15)
    assert np.allclose(results[0], results[1], atol=1e-15)


def test_upside_down_reading_does_not_produce_nan():
    """An accelerometer exactly opposite to the predicted down has no shortest arc: the
    sample corrects nothing rather than inventing an axis, and nothing becomes NaN."""
    est = estimators.create("kalman", q0=Q.identity())
    q = est.update([0.0, 0.0, 0.0], [0.0, 0.0, G])
    assert np.all(np.isfinite(q)) and Q.angle_between(q, Q.identity()) < 1e-12


@pytest.mark.parametrize("exact", [True, False])
def test_predict_only_when_accelerometer_unusable(exact):
    """NaN accelerometer: pure prediction. The attitude is the exact rotation (exact A) or
    the 2·atan(|ω|dt/2) rotation (first-order A, renormalised), and P grows as
    p ← s·p + Q·dt with s = 1 (exact) or 1 + |ω|²dt²/4."""
    w, rate, n = np.array([0.4, -1.1, 2.0]), 200.0, 400
    dt, wn = 1.0 / rate, float(np.linalg.norm(w))
    q0 = Q.from_euler(0.2, 0.1, -0.5)
    est = estimators.create("kalman", rate_hz=rate, q0=q0, exact=exact)
    q = est.run(np.tile(w, (n, 1)), np.full((n, 3), np.nan)).q
    step = wn * dt if exact else 2.0 * math.atan(wn * dt / 2.0)
    k = np.arange(1, n + 1)
    expected = Q.multiply(q0, Q.from_rotvec(np.outer(k * step, w / wn)))
    assert Q.angle_between(q, expected).max() < 1e-10
    s = 1.0 if exact else 1.0 + (wn * dt) ** 2 / 4.0
    p = DEFAULTS.p0
    for _ in range(n):
        p = s * p + DEFAULTS.process_noise * dt
    assert np.allclose(est.covariance, p * np.eye(4), rtol=1e-12, atol=1e-12 * p)
    assert est.counters.acc_unusable == n and est.counters.skipped == 0


def test_tracks_rotation_with_consistent_measurements():
    """Rotating at a constant rate with acc and mag consistent with the truth: the
    prediction is exact and z equals it, so the estimate stays on the truth."""
    w, rate, n = np.array([0.5, 1.5, -1.0]), 500.0, 1000
    q0 = Q.from_euler(0.1, -0.2, 1.0)
    truth = Q.multiply(q0, Q.from_rotvec(np.outer(np.arange(1, n + 1) / rate, w)))
    acc = Q.rotate(Q.conjugate(truth), np.array([0.0, 0.0, -G]))
    mag = Q.rotate(Q.conjugate(truth), FIELD_NED)
    q = estimators.batch("kalman", np.tile(w, (n, 1)), acc, mag, rate_hz=rate, q0=q0)
    assert Q.angle_between(q, truth).max() < 1e-9


@pytest.mark.parametrize("key", ["process_noise", "measurement_noise", "p0"])
@pytest.mark.parametrize("bad", [0.0, -1e-3, float("inf")])
def test_noise_parameters_must_be_positive(key, bad):
    with pytest.raises(ValueError, match=key):
        estimators.create("kalman", **{key: bad})


def test_smaller_measurement_noise_converges_faster():
    """τ = √(R/Q): R four times smaller halves the time constant, so after the same time
    the error is smaller; checked against the scalar recursion with those values."""
    truth = Q.from_euler(ROLL, 0.0, 0.0)
    rate, n = 1000.0, 2000
    acc, mag = _static(truth, n, with_mag=True, field=FIELD_HORIZONTAL)
    fast = {"measurement_noise": DEFAULTS.measurement_noise / 4.0}
    q = estimators.batch("kalman", np.zeros((n, 3)), acc, mag, rate_hz=rate,
                         q0=Q.identity(), **fast)
    expected, _ = _scalar_recursion(rate, n, Q.angle_between(Q.identity(), truth),
                                    DEFAULTS.p0, DEFAULTS.process_noise,
                                    fast["measurement_noise"])
    slow, _ = _scalar_recursion(rate, n, Q.angle_between(Q.identity(), truth), DEFAULTS.p0,
                                DEFAULTS.process_noise, DEFAULTS.measurement_noise)
    assert abs(Q.angle_between(q[-1], truth) - expected[-1]) < 1e-9
    assert expected[-1] < 0.6 * slow[-1]
