"""Every estimator parameter has a range of values that mean something, and a value
outside it is refused in one line, in the units the user typed (a new-user sweep found
values that broke the filters' arithmetic with exit 0: a noise of 1e308 froze the
attitude, 1e-200 divided by zero on every sample)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import estimators
from estimators import quat as Q
from estimators.base import CommonParams
from estimators.metrics import attitude_errors
from estimators.spec import EstimatorSpec

NAMES = ("eskf", "euler", "dcm", "quaternion", "mahony", "madgwick", "kalman")
#: Parameters checked by code of their own rather than by a range.
OWN_CHECKS = {("euler", "gimbal_margin")}
COMMON = {f.name for f in dataclasses.fields(CommonParams)}


def _own_params(name: str) -> list[dataclasses.Field]:
    cls = estimators.estimator_class(name)
    return [f for f in dataclasses.fields(cls.Params) if f.name not in COMMON]


def test_every_numeric_parameter_has_a_range():
    missing = [(name, f.name) for name in NAMES for f in _own_params(name)
               if isinstance(f.default, float) and (name, f.name) not in OWN_CHECKS
               and f.name not in estimators.estimator_class(name).Params.BOUNDS]
    assert missing == []


def test_every_range_holds_its_default():
    for name in NAMES:
        params = estimators.estimator_class(name).Params
        for key, (lo, hi) in params.BOUNDS.items():
            default = next(f.default for f in dataclasses.fields(params) if f.name == key)
            assert lo <= default <= hi, (name, key)


@pytest.mark.parametrize("spec, param", [
    ("eskf:velocity_scale=1e-200", "velocity_scale"),  # was ZeroDivisionError per sample
    ("eskf:flight_accel_noise=1e-308", "flight_accel_noise"),
    ("madgwick:beta=1e308", "beta"),  # was a frozen attitude, 142° off
    ("mahony:kp=1e308", "kp"),
    ("kalman:p0=1e308", "p0"),
    ("kalman:measurement_noise=1e308", "measurement_noise"),
    ("eskf:gyro_noise=1e308", "gyro_noise"),
    ("eskf:gyro_rate_noise=1e308", "gyro_rate_noise"),
    ("eskf:bias_rw=1e308", "bias_rw"),
    ("eskf:bias_init_dps=1e308", "bias_init"),
    ("eskf:tilt_init_deg=1e308", "tilt_init"),
    ("eskf:heading_init_deg=1e308", "heading_init"),
    ("eskf:mag_noise=1e308", "mag_noise"),
    ("eskf:rest_noise=1e308", "rest_noise"),
    ("eskf:mag_delay=1e6", "mag_delay"),
    ("eskf:rest_time=0", "rest_time"),  # was 92° off: every moment a rest
    ("eskf:drag_sigma_init=1e308", "drag_sigma_init"),
    ("eskf:gravity=1e6", "gravity"),
    ("eskf:update_period=1e308", "update_period"),
    ("eskf:drag=1e308", "drag"),
    ("eskf:aid_density=-1", "aid_density"),
    ("eskf:aid_heading=-1", "aid_heading"),
    ("mahony:exact=-1", "exact"),
    ("madgwick:original_mag_quirk=inf", "original_mag_quirk"),
    ("dcm:exact=1e-308", "exact"),
])
def test_absurd_values_are_refused_naming_the_parameter(spec, param):
    with pytest.raises(ValueError, match=f"parameter '{param}'") as err:
        EstimatorSpec.parse(spec)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("spec, shown", [
    ("eskf:gyr_range_dps=-1", "-1 deg/s, as gyr_range_dps"),
    ("eskf:declination_deg=200", "200 deg, as declination_deg"),
    ("eskf:tilt_init_deg=400", "400 deg, as tilt_init_deg"),
])
def test_angles_are_reported_in_the_degrees_typed(spec, shown):
    with pytest.raises(ValueError, match=shown):
        EstimatorSpec.parse(spec)


def _static_then_turning(rate_hz: float = 200.0) -> tuple[np.ndarray, ...]:
    """A tilted board held still for 2 s, then turning about its vertical at 1 rad/s for
    2 s (NED, field with a 60° dip): the samples and the true attitudes."""
    n = int(4 * rate_hz)
    t = np.arange(n) / rate_hz
    yaw = np.where(t < 2.0, 0.0, t - 2.0)
    tilt = Q.from_euler(np.radians(10.0), np.radians(-5.0), 0.0)
    truth = Q.multiply(np.stack([Q.from_euler(0.0, 0.0, y) for y in yaw]), tilt)
    field = np.array([math.cos(math.radians(60)), 0.0, math.sin(math.radians(60))])
    gravity_up = np.array([0.0, 0.0, -9.80665])  # specific force at rest, NED
    acc = Q.rotate(Q.conjugate(truth), np.broadcast_to(gravity_up, (n, 3)))
    mag = Q.rotate(Q.conjugate(truth), np.broadcast_to(field, (n, 3)))
    gyr = np.zeros((n, 3))
    gyr[t >= 2.0] = Q.rotate(Q.conjugate(tilt), np.array([0.0, 0.0, 1.0]))
    return gyr, acc, mag, truth


@pytest.mark.parametrize("name", NAMES)
def test_every_range_end_keeps_a_working_filter(name):
    """At either end of each range the estimate stays a finite unit quaternion within a
    loose bound of a simple truth: the ranges exclude the values that break the
    arithmetic, not merely poor settings."""
    gyr, acc, mag, truth = _static_then_turning()
    bounds = estimators.estimator_class(name).Params.BOUNDS
    for key, ends in bounds.items():
        for value in ends:
            if not math.isfinite(value):
                continue
            est = estimators.create(name, rate_hz=200.0, **{key: value})
            q = est.run(gyr, acc, mag).q
            assert np.all(np.isfinite(q)), (key, value)
            np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6,
                                       err_msg=f"{key}={value}")
            incl = np.degrees(attitude_errors(q, truth).inclination)
            assert np.nanmax(incl[:300]) < 45.0, (key, value, np.nanmax(incl[:300]))


def test_the_listing_shows_each_range_in_the_units_typed():
    from estimators.spec import user_param_docs

    docs = user_param_docs(estimators.estimator_class("madgwick"))
    assert docs["beta_dps"].startswith("5.72958 (0..572.958); ")
    assert user_param_docs(estimators.estimator_class("eskf"))["rest_time"].startswith(
        "1.5 (0.001..10000); ")
