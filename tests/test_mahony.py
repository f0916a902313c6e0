"""Mahony's PI complementary filter on analytic motions.

Expected behaviour is derived, not measured:

* Consistent, noise-free sensors under a constant body rate: the correction is zero when
  the estimate is right, so the filter follows ``q0 ⊗ exp(ω·t/2)`` up to the first-order
  step's own error.
* Static, gyro silent, estimate tilted by θ from the truth: the correction ``kp·(â × v̂)``
  turns the predicted gravity direction toward the measured one at ``kp·sin θ`` rad/s,
  so ``θ̇ = −kp·sin θ`` and ``tan(θ/2)`` decays as ``exp(−kp·t)``:
  ``t(θ0 → θ1) = ln(tan(θ0/2) / tan(θ1/2)) / kp`` (with ki = 0).
* Constant gyro bias, static: the linearised loop is ``s² + kp·s + ki``; the integral
  settles at minus the bias, which the filter exposes as ``bias`` (true = gyro − bias).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from attitude_support import FIELD_NED, TILT, G, constant_rate, deg, static

import estimators
from estimators import quat as Q
from estimators.metrics import attitude_errors

AXES = {"x": np.array([1.0, 0.0, 0.0]), "y": np.array([0.0, 1.0, 0.0]),
        "z": np.array([0.0, 0.0, 1.0])}


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("use_mag", [False, True])
def test_follows_constant_rate_about_each_axis(axis, use_mag):
    q0 = Q.from_euler(0.3, -0.4, 2.0)
    truth, gyr, acc, mag = constant_rate(2.0 * AXES[axis], 3.0, 400.0, q0)
    q = estimators.batch("mahony", gyr, acc, mag if use_mag else None, rate_hz=400.0,
                         q0=q0, kp=1.0, ki=0.05)
    err = attitude_errors(q, truth)
    # First-order step error: 2·atan(|ω|dt/2) vs |ω|dt is ~1e-7 rad per step; the
    # correction keeps it from accumulating.
    assert deg(err.inclination).max() < 1e-3
    if use_mag:
        assert deg(err.total).max() < 1e-3


@pytest.mark.parametrize("use_mag", [False, True])
def test_initialises_from_first_sample_at_the_paper_tilt(use_mag):
    gyr, acc, mag = static(TILT, 0.1, 100.0)
    q = estimators.batch("mahony", gyr, acc, mag if use_mag else None, rate_hz=100.0)
    err = attitude_errors(q, np.broadcast_to(TILT, q.shape))
    assert deg(err.inclination).max() < 1e-9
    if use_mag:
        assert deg(err.total).max() < 1e-9


def test_static_tilt_converges_at_the_rate_kp_predicts():
    kp, rate = 0.74, 200.0
    theta0 = float(Q.angle_between(TILT, Q.identity()))  # 18.4°: start level, truth tilted
    theta1 = math.radians(0.5)
    t_pred = math.log(math.tan(theta0 / 2) / math.tan(theta1 / 2)) / kp  # 4.9 s
    gyr, acc, _ = static(TILT, 2.0 * t_pred, rate)
    q = estimators.batch("mahony", gyr, acc, rate_hz=rate, q0=Q.identity(), kp=kp, ki=0.0)
    incl = attitude_errors(q, np.broadcast_to(TILT, q.shape)).inclination
    t = np.arange(1, len(q) + 1) / rate
    # Within 3 % of the predicted time (the first-order step only perturbs it slightly),
    # and along the predicted curve at half that time.
    assert incl[t <= 0.97 * t_pred].min() > theta1
    assert incl[t >= 1.03 * t_pred].max() < theta1
    half = np.searchsorted(t, t_pred / 2)
    expected = 2 * math.atan(math.tan(theta0 / 2) * math.exp(-kp * t[half]))
    assert abs(incl[half] - expected) < math.radians(0.05)


@pytest.mark.parametrize("mag_mode", ["full", "heading"])
def test_integral_learns_constant_gyro_bias(mag_mode):
    """Tilt axes: loop s² + kp·s + ki (slow pole ~9 s here). Yaw: the magnetometer's
    error about the vertical is cos²(dip)·sin ψ, so its gains shrink by cos²(dip) = 0.15:
    s² + 0.15·s + 0.015, decaying as exp(-0.076·t). 150 s is > 10 time constants."""
    bias = np.array([0.02, -0.03, 0.015])  # rad/s, ~1-2 °/s like an uncalibrated MPU6050
    rate, kp, ki = 100.0, 1.0, 0.1
    gyr, acc, mag = static(TILT, 150.0, rate, bias)
    est = estimators.create("mahony", rate_hz=rate, kp=kp, ki=ki, mag_mode=mag_mode)
    result = est.run(gyr, acc, mag)
    assert np.allclose(est.bias, bias, atol=2e-5)
    assert np.allclose(result.bias[-1], est.status.bias)
    assert deg(attitude_errors(result.q[-1], TILT).total) < 0.01
    # Without the integral a P controller holds a standing error of ~|bias|/gain (> 2°).
    p_only = estimators.batch("mahony", gyr, acc, mag, rate_hz=rate, kp=kp, ki=0.0)
    assert deg(attitude_errors(p_only[-1], TILT).total) > 1.0


def test_integral_is_clamped_by_bias_limit():
    limit = 0.1
    gyr, acc, mag = static(TILT, 30.0, 100.0, np.array([0.0, 0.5, 0.0]))
    est = estimators.create("mahony", rate_hz=100.0, kp=0.5, ki=0.5, bias_limit=limit)
    result = est.run(gyr, acc, mag)
    assert np.abs(result.bias).max() <= limit + 1e-15
    assert est.bias[1] == pytest.approx(limit)


def test_ki_uses_dt_so_the_gain_does_not_depend_on_the_rate():
    bias = np.array([0.0, 0.03, 0.0])
    final = []
    for rate in (100.0, 1000.0):
        gyr, acc, _ = static(TILT, 10.0, rate, bias)
        final.append(estimators.run("mahony", gyr, acc, rate_hz=rate, kp=0.5, ki=0.05).bias[-1])
    # The seed's per-sample ``exInt += ex·Ki`` would make these differ tenfold.
    assert np.allclose(final[0], final[1], rtol=0.02, atol=1e-5)


def test_heading_only_magnetometer_never_tilts_the_estimate():
    """Start with a 30° heading error. Heading-only: the error about the vertical is
    cos²(dip)·sin ψ, so ψ follows tan(ψ/2) ∝ exp(-kp·cos²(dip)·t) with no tilt at all.
    Full field: the error also has horizontal parts, which tilt the estimate meanwhile."""
    rate, kp = 100.0, 1.0
    gyr, acc, mag = static(TILT, 60.0, rate)
    psi0 = math.radians(30.0)
    q0 = Q.multiply(Q.from_euler(0.0, 0.0, psi0), TILT)
    out = {}
    for mode in ("full", "heading"):
        q = estimators.batch("mahony", gyr, acc, mag, rate_hz=rate, q0=q0, kp=kp, ki=0.0,
                             mag_mode=mode)
        out[mode] = attitude_errors(q, np.broadcast_to(TILT, q.shape))
    assert deg(out["heading"].inclination).max() < 1e-4
    assert deg(out["full"].inclination).max() > 1.0
    cos2_dip = (FIELD_NED[0] ** 2 + FIELD_NED[1] ** 2) / float(FIELD_NED @ FIELD_NED)
    t = np.arange(1, len(gyr) + 1) / rate
    expected = 2 * np.arctan(math.tan(psi0 / 2) * np.exp(-kp * cos2_dip * t))
    assert deg(np.abs(out["heading"].heading - expected)).max() < 0.05
    assert deg(out["heading"].heading[-1]) < 0.01  # predicted 0.0035°
    assert deg(out["full"].heading[-1]) < 0.5  # converges too, slowed by the tilt coupling


def test_unusable_accelerometer_still_integrates_gyro_and_counts():
    w = np.array([0.0, 0.0, 1.0])
    rate = 100.0
    truth, gyr, acc, mag = constant_rate(w, 1.0, rate, TILT)
    acc = acc.copy()
    acc[10:60] = [np.nan, 0.0, 0.0]  # NaN
    acc[60:70] = 0.0  # zero norm
    acc[70:80] = [0.0, 0.0, -16 * G]  # saturated axis
    est = estimators.create("mahony", rate_hz=rate, q0=Q.multiply(TILT, Q.identity()))
    q = est.run(gyr, acc, mag).q
    # The seed returned early (``if(ax*ay*az==0) return;``) and froze the attitude here.
    err = attitude_errors(q, truth)
    assert deg(err.total).max() < 1e-3
    assert est.counters.acc_unusable == 70
    assert np.all(np.isfinite(q))


def test_bad_samples_never_poison_the_state():
    rate = 100.0
    gyr, acc, mag = static(TILT, 2.0, rate)
    gyr[50] = [np.nan, 0.0, 0.0]
    gyr[51] = [np.inf, 0.0, 0.0]
    mag[60:70] = np.nan
    mag[70] = 0.0
    est = estimators.create("mahony", rate_hz=rate, q0=TILT)
    q = est.run(gyr, acc, mag).q
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(est.bias))
    assert deg(attitude_errors(q, np.broadcast_to(TILT, q.shape)).total).max() < 1e-6
    c = est.counters
    assert (c.skipped, c.mag_unusable) == (2, 11)
    # update() takes the same path and, per sample, the same numbers.
    one = estimators.create("mahony", rate_hz=rate, q0=TILT)
    for i in range(len(gyr)):
        last = one.update(gyr[i], acc[i], mag[i])
    assert np.array_equal(last, q[-1])


def test_parameters_are_validated():
    with pytest.raises(ValueError, match="mag_mode"):
        estimators.create("mahony", mag_mode="compass")
    with pytest.raises(ValueError, match="kp"):
        estimators.create("mahony", kp=-1.0)
    with pytest.raises(ValueError, match="valid"):
        estimators.create("mahony", twoKp=1.0)
    assert estimators.create("mahony", mag_mode=1).params.mag_mode == "heading"
