"""Madgwick's gradient-descent filter on analytic motions.

Expected behaviour, derived from the update ``q̇ = ½ q ⊗ ω − beta · ∇f/|∇f|``:

* the correction has quaternion rate ``beta``, i.e. rotates the estimate at most at
  ``2·beta`` rad/s: from a wrong start the error can shrink no faster, and (while the
  gradient is mostly tangential) shrinks at nearly that rate, so a tilt error θ0 is gone
  after about ``θ0 / (2·beta)``;
* the normalised step never vanishes, so with perfect data the estimate chatters around
  the truth by at most one step's correction, ``2·beta·dt``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from attitude_support import TILT, G, constant_rate, deg, static

import estimators
from estimators import quat as Q
from estimators.metrics import attitude_errors

AXES = {"x": np.array([1.0, 0.0, 0.0]), "y": np.array([0.0, 1.0, 0.0]),
        "z": np.array([0.0, 0.0, 1.0])}


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("use_mag", [False, True])
def test_follows_constant_rate_about_each_axis(axis, use_mag):
    rate, beta = 400.0, 0.1
    q0 = Q.from_euler(0.3, -0.4, 2.0)
    truth, gyr, acc, mag = constant_rate(2.0 * AXES[axis], 3.0, rate, q0)
    q = estimators.batch("madgwick", gyr, acc, mag if use_mag else None, rate_hz=rate,
                         q0=q0, beta=beta)
    err = attitude_errors(q, truth)
    chatter = 2.0 * beta / rate
    assert err.inclination.max() < chatter
    if use_mag:
        assert err.total.max() < chatter


@pytest.mark.parametrize("use_mag", [False, True])
def test_static_tilt_converges_at_rate_two_beta(use_mag):
    rate, beta = 200.0, 0.1
    theta0 = float(attitude_errors(Q.identity(), TILT).inclination)  # 18.3°
    t_pred = theta0 / (2.0 * beta)  # 1.6 s
    gyr, acc, mag = static(TILT, 3.0 * t_pred, rate)
    q = estimators.batch("madgwick", gyr, acc, mag if use_mag else None, rate_hz=rate,
                         q0=Q.identity(), beta=beta)
    incl = attitude_errors(q, np.broadcast_to(TILT, q.shape)).inclination
    t = np.arange(1, len(q) + 1) / rate
    assert np.all(incl >= theta0 - 2.0 * beta * t - 1e-9)  # never faster than 2·beta
    assert incl[t >= 1.25 * t_pred].max() < math.radians(0.1)


def test_magnetometer_fixes_heading():
    rate, beta = 200.0, 0.1
    gyr, acc, mag = static(TILT, 10.0, rate)
    q0 = Q.multiply(Q.from_euler(0.0, 0.0, math.radians(30.0)), TILT)
    q = estimators.batch("madgwick", gyr, acc, mag, rate_hz=rate, q0=q0, beta=beta)
    err = attitude_errors(q, np.broadcast_to(TILT, q.shape))
    assert deg(err.total[-1]) < 0.05
    six_d = estimators.batch("madgwick", gyr, acc, None, rate_hz=rate, q0=q0, beta=beta)
    assert deg(attitude_errors(six_d[-1], TILT).heading) > 29.0  # nothing observes yaw


def test_original_mag_quirk_only_changes_the_magnetometer_weight():
    """The original C code's reference field is half the measured one: the magnetometer
    pulls half as hard against the accelerometer. From a 60° heading error the full-
    strength version tilts the estimate more on the way and fixes the heading sooner."""
    rate, beta = 200.0, 0.1
    gyr, acc, mag = static(TILT, 5.0, rate)
    q0 = Q.multiply(Q.from_euler(0.0, 0.0, math.radians(60.0)), TILT)
    err = {}
    for quirk in (False, True):
        q = estimators.batch("madgwick", gyr, acc, mag, rate_hz=rate, q0=q0, beta=beta,
                             original_mag_quirk=quirk)
        err[quirk] = attitude_errors(q, np.broadcast_to(TILT, q.shape))
    assert err[True].inclination.max() < err[False].inclination.max()
    assert deg(err[False].heading[-1]) < 30.0 < deg(err[True].heading[-1])
    # Without a magnetometer the flag changes nothing at all.
    six_d = [estimators.batch("madgwick", gyr, acc, rate_hz=rate, q0=q0, original_mag_quirk=f)
             for f in (False, True)]
    assert np.array_equal(six_d[0], six_d[1])


def test_unusable_accelerometer_still_integrates_gyro():
    rate = 100.0
    truth, gyr, acc, mag = constant_rate(np.array([0.0, 1.0, 0.0]), 1.0, rate, TILT)
    acc = acc.copy()
    acc[10:40] = np.nan
    acc[40:50] = 0.0
    acc[50:60] = [16 * G, 0.0, 0.0]
    beta = 0.1
    est = estimators.create("madgwick", rate_hz=rate, q0=TILT, beta=beta)
    q = est.run(gyr, acc, mag).q
    assert attitude_errors(q, truth).total.max() < 2.0 * beta / rate  # chatter only
    assert est.counters.acc_unusable == 50


def test_bad_samples_never_poison_the_state():
    rate = 100.0
    gyr, acc, mag = static(TILT, 2.0, rate)
    gyr[20] = np.nan
    acc[30] = np.inf
    mag[40:45] = np.nan
    mag[45] = 0.0
    est = estimators.create("madgwick", rate_hz=rate, q0=TILT)
    q = est.run(gyr, acc, mag).q
    assert np.all(np.isfinite(q))
    assert deg(attitude_errors(q, np.broadcast_to(TILT, q.shape)).total).max() < 0.1
    c = est.counters
    assert (c.skipped, c.acc_unusable, c.mag_unusable) == (1, 1, 6)


def test_parameters_are_validated():
    with pytest.raises(ValueError, match="beta"):
        estimators.create("madgwick", beta=-0.1)
    with pytest.raises(ValueError, match="valid"):
        estimators.create("madgwick", zeta=0.1)
