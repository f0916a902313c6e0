"""The common machinery in estimators/_core.py and base.py, exercised through the simplest
estimator (``quaternion``: exact gyro integration, no correction), so that every number
below follows from the inputs alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

import estimators
from estimators import _core
from estimators import quat as Q

G = 9.80665


def _body(truth: np.ndarray, world_vec: np.ndarray) -> np.ndarray:
    return Q.rotate(Q.conjugate(truth), np.asarray(world_vec, dtype=float))


# --- initialisation ----------------------------------------------------------------

def test_init_from_accelerometer_only_sets_tilt_and_yaw_zero():
    truth = Q.from_euler(math.radians(15.9), math.radians(9.2), math.radians(70.0))
    est = estimators.create("quaternion")
    q = est.update([1.0, 2.0, 3.0], _body(truth, [0.0, 0.0, -G]))
    roll, pitch, yaw = Q.to_euler(q)
    assert roll == pytest.approx(math.radians(15.9), abs=1e-12)
    assert pitch == pytest.approx(math.radians(9.2), abs=1e-12)
    assert yaw == pytest.approx(0.0, abs=1e-12)  # no heading information: body x north


def test_init_from_accelerometer_and_magnetometer_gives_the_full_attitude():
    truth = Q.from_euler(math.radians(-30.0), math.radians(50.0), math.radians(-135.0))
    field = [0.19, -0.02, 0.44]  # declination is not modelled: only the horizontal part
    est = estimators.create("quaternion")
    q = est.update([0.0, 0.0, 0.0], _body(truth, [0.0, 0.0, -G]), _body(truth, field))
    # Magnetic north = the field's horizontal direction, here rotated by atan2(-0.02, 0.19).
    decl = Q.from_euler(0.0, 0.0, math.atan2(-0.02, 0.19))
    assert Q.angle_between(q, Q.multiply(Q.conjugate(decl), truth)) < 1e-12


def test_init_with_body_x_vertical_uses_body_y_for_heading():
    """Nose straight up and no magnetometer: 'body x north' is impossible, the fallback
    must still give a finite attitude with the correct (vertical) nose."""
    truth = Q.from_euler(0.0, math.pi / 2.0, 0.0)
    q = estimators.create("quaternion").update([0.0] * 3, _body(truth, [0.0, 0.0, -G]))
    assert np.all(np.isfinite(q))
    assert np.allclose(Q.rotate(q, [1.0, 0.0, 0.0]), [0.0, 0.0, -1.0], atol=1e-12)


def test_unusable_magnetometer_at_init_falls_back_to_accelerometer_only():
    truth = Q.from_euler(0.2, -0.1, 1.0)
    acc = _body(truth, [0.0, 0.0, -G])
    est = estimators.create("quaternion")
    q = est.update([0.0] * 3, acc, [np.nan, 0.0, 0.0])
    assert Q.angle_between(q, Q.from_acc_mag(acc)) < 1e-12
    assert est.counters.mag_unusable == 1


def test_waits_for_a_usable_accelerometer_and_counts_what_it_skipped():
    est = estimators.create("quaternion")
    for bad in ([np.nan] * 3, [0.0, 0.0, 0.0], [0.0, 0.0, 16 * G]):
        assert np.array_equal(est.update([0.3, 0.0, 0.0], bad), Q.identity())
        assert est.status.initialising
    est.update([0.3, 0.0, 0.0], [0.0, 0.0, -G])
    status = est.status
    assert not status.initialising
    assert status.counters.samples == 4 and status.counters.acc_unusable == 3
    assert status.counters.skipped == 0


# --- sample validation and counters ---------------------------------------------------

def test_accelerometer_saturation_threshold_follows_acc_range():
    """An axis at >= 99.9 % of full scale is clipped: the sample's accelerometer is unused."""
    est = estimators.create("quaternion", q0=Q.identity(), acc_range=2.0 * G)
    est.update([0.0] * 3, [0.0, 0.0, -0.999 * 2.0 * G])
    assert est.counters.acc_unusable == 1
    est.update([0.0] * 3, [0.0, 0.0, -0.998 * 2.0 * G])
    assert est.counters.acc_unusable == 1


def test_saturated_gyro_is_counted_but_still_integrated():
    full = math.radians(250.0)
    est = estimators.create("quaternion", q0=Q.identity(), gyr_range=full, rate_hz=1000.0)
    q = est.update([0.0, 0.0, full], [0.0, 0.0, -G])
    assert est.counters.gyr_saturated == 1
    assert Q.angle_between(q, Q.from_rotvec([0.0, 0.0, full / 1000.0])) < 1e-14


def test_gyro_beyond_full_scale_is_clipped_to_it():
    """A sensor cannot report more than its full scale: a rate up to twice it is a
    saturated reading (or a scale error) and integrates as the full scale."""
    full = math.radians(250.0)
    est = estimators.create("quaternion", q0=Q.identity(), gyr_range=full, rate_hz=1000.0)
    q = est.update([0.0, -1.9 * full, 0.3], [0.0, 0.0, -G])
    assert est.counters.gyr_saturated == 1 and est.counters.skipped == 0
    assert Q.angle_between(q, Q.from_rotvec([0.0, -full / 1000.0, 0.3 / 1000.0])) < 1e-14


@pytest.mark.parametrize("value", [2.01, 4.0, 1e6, 1e20, -1e300])
@pytest.mark.parametrize("name", ["quaternion", "mahony", "madgwick", "kalman", "eskf"])
def test_gyro_far_beyond_full_scale_is_a_corrupt_sample_and_skipped(name, value):
    """One corrupt gyro value (x full scale) must not turn the attitude: every estimator
    skips the sample and counts it, and ends where the clean run ends."""
    full = math.radians(2000.0)
    n = 400
    gyr = np.zeros((n, 3))
    acc = np.tile([0.0, 0.0, -G], (n, 1))
    clean = estimators.create(name, rate_hz=200.0).run(gyr, acc)
    gyr[n // 2, 1] = value * full
    est = estimators.create(name, rate_hz=200.0)
    res = est.run(gyr, acc)
    assert est.counters.skipped == 1 and est.counters.gyr_saturated == 0
    assert Q.angle_between(res.q[-1], clean.q[-1]) < 1e-9


@pytest.mark.parametrize("dt", [0.0, -0.001, np.nan, np.inf, -np.inf, 0.0501])
def test_bad_dt_is_skipped_and_counted(dt):
    est = estimators.create("quaternion", q0=Q.identity(), max_dt=0.05)
    q = est.update([1.0, 0.0, 0.0], [0.0, 0.0, -G], dt=dt)
    assert np.array_equal(q, Q.identity())
    counters = est.counters
    assert (counters.samples, counters.skipped, counters.bad_dt) == (1, 1, 1)


def test_dt_at_max_dt_is_used():
    est = estimators.create("quaternion", q0=Q.identity(), max_dt=0.05)
    q = est.update([1.0, 0.0, 0.0], [0.0, 0.0, -G], dt=0.05)
    assert Q.angle_between(q, Q.from_rotvec([0.05, 0.0, 0.0])) < 1e-15
    assert est.counters.skipped == 0


def test_non_finite_gyro_is_skipped_but_not_a_dt_problem():
    est = estimators.create("quaternion", q0=Q.identity())
    est.update([np.nan, 0.0, 0.0], [0.0, 0.0, -G])
    est.update([0.0, -np.inf, 0.0], [0.0, 0.0, -G])
    counters = est.counters
    assert (counters.samples, counters.skipped, counters.bad_dt) == (2, 2, 0)


def test_dt_defaults_to_the_rate_and_overrides_it():
    w = np.array([0.0, 0.0, 2.0])
    est = estimators.create("quaternion", q0=Q.identity(), rate_hz=250.0)
    assert Q.angle_between(est.update(w, [0.0, 0.0, -G]), Q.from_rotvec(w / 250.0)) < 1e-15
    q = est.update(w, [0.0, 0.0, -G], dt=0.01)
    assert Q.angle_between(q, Q.from_rotvec(w * (1.0 / 250.0 + 0.01))) < 1e-15


def test_batch_flags_mark_each_sample():
    gyr = np.zeros((6, 3))
    gyr[3] = np.nan
    acc = np.tile([0.0, 0.0, -G], (6, 1))
    acc[0] = np.nan  # before initialisation
    acc[4] = 0.0  # after
    dt = np.array([0.01, 0.01, -1.0, 0.01, 0.01, 0.01])
    result = estimators.run("quaternion", gyr, acc, dt=dt)
    assert result.initialised.tolist() == [False, True, True, True, True, True]
    assert result.skipped.tolist() == [False, False, True, True, False, False]
    unusable = (result.flags & _core.F_ACC_UNUSABLE) != 0
    assert unusable.tolist() == [True, False, False, False, True, False]
    assert not result.acc_rejected.any() and not result.mag_rejected.any()
    assert result.bias.shape == (6, 3) and not result.bias.any()


def test_run_accepts_scalar_dt_and_empty_input():
    w = np.array([0.5, 0.0, 0.0])
    est = estimators.create("quaternion", q0=Q.identity())
    q = est.run(np.tile(w, (10, 1)), np.tile([0.0, 0.0, -G], (10, 1)), dt=0.02).q
    assert Q.angle_between(q[-1], Q.from_rotvec(w * 0.2)) < 1e-14
    empty = est.run(np.zeros((0, 3)), np.zeros((0, 3)))
    assert empty.q.shape == (0, 4)
    assert est.counters.samples == 10


@pytest.mark.parametrize("kwargs", [
    {"gyr": np.zeros((5, 2)), "acc": np.zeros((5, 3))},
    {"gyr": np.zeros((5, 3)), "acc": np.zeros((4, 3))},
    {"gyr": np.zeros((5, 3)), "acc": np.zeros((5, 3)), "mag": np.zeros((4, 3))},
    {"gyr": np.zeros((5, 3)), "acc": np.zeros((5, 3)), "dt": np.ones(4)},
])
def test_run_rejects_mismatched_shapes(kwargs):
    with pytest.raises(ValueError):
        estimators.create("quaternion").run(**kwargs)


def test_update_rejects_wrong_shapes():
    est = estimators.create("quaternion")
    with pytest.raises(ValueError):
        est.update([0.0, 0.0], [0.0, 0.0, -G])
    with pytest.raises(ValueError):
        est.update([0.0] * 3, [0.0, 0.0, -G], mag=[1.0, 0.0])


# --- status, outputs, reset ---------------------------------------------------------------

def test_status_is_a_snapshot():
    est = estimators.create("quaternion", q0=Q.identity())
    est.update([0.0, 0.0, 1.0], [0.0, 0.0, -G])
    status = est.status
    q_before = status.q.copy()
    status.q[:] = 0.0  # mutating the snapshot must not reach the estimator
    assert Q.angle_between(est.q, q_before) == 0.0
    est.update([0.0, 0.0, 1.0], [np.nan] * 3)
    assert status.counters.samples == 1 and est.counters.samples == 2
    assert not status.acc_rejected and not status.mag_rejected
    assert np.array_equal(status.bias, np.zeros(3))


def test_update_returns_a_new_array_each_time():
    est = estimators.create("quaternion", q0=Q.identity())
    first = est.update([0.0, 0.0, 1.0], [0.0, 0.0, -G])
    second = est.update([0.0, 0.0, 1.0], [0.0, 0.0, -G])
    assert first is not second and not np.array_equal(first, second)


def test_enu_output_and_q0():
    """A level FRD body heading north: in ENU its x axis is +y (north) and z is -z (down)."""
    est = estimators.create("quaternion", world="ENU")
    q = est.update([0.0] * 3, [0.0, 0.0, -G], [0.2, 0.0, 0.4])
    assert np.allclose(Q.to_dcm(q), [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
                       atol=1e-12)
    assert Q.angle_between(est.q, q) == 0.0
    q0 = Q.from_euler(0.1, 0.2, 0.3)
    enu = estimators.create("quaternion", world="ENU", q0=q0)
    ned = estimators.create("quaternion", world="NED", q0=Q.enu_to_ned(q0))
    w = [0.3, -0.2, 0.1]
    assert Q.angle_between(enu.update(w, [np.nan] * 3),
                           Q.ned_to_enu(ned.update(w, [np.nan] * 3))) < 1e-15


def test_reset_forgets_state_and_counters():
    est = estimators.create("quaternion")
    est.update([0.0] * 3, [0.0, 1.0, -G])
    est.update([np.nan] * 3, [0.0, 0.0, -G])
    est.reset()
    assert est.status.initialising and est.counters.samples == 0
    assert np.array_equal(est.q, Q.identity())
    est.reset(q0=Q.from_euler(0.0, 0.0, 1.0))
    assert not est.status.initialising
    assert Q.angle_between(est.q, Q.from_euler(0.0, 0.0, 1.0)) < 1e-15


def test_parameter_values_are_checked():
    with pytest.raises(ValueError, match="exact"):
        estimators.create("quaternion", exact="yes")
    with pytest.raises(ValueError, match="max_dt"):
        estimators.create("quaternion", max_dt=float("nan"))
    assert set(estimators.estimator_class("quaternion").param_docs()) == {
        "acc_range", "gyr_range", "max_dt", "declination", "aid_timeout", "imu_delay", "exact"}


@pytest.mark.parametrize("world", ["NED", "ENU"])
@pytest.mark.parametrize("name", ["quaternion", "mahony", "eskf"])
def test_declination_turns_magnetic_into_true_heading(name, world):
    """A level body facing true north in a field declined 10° east: the magnetometer alone
    says heading -10°; with declination=10° the output heading is true north."""
    d = np.radians(10.0)
    mag = np.array([0.2 * np.cos(d), 0.2 * np.sin(d), 0.45])  # NED field, body = NED
    acc = np.array([0.0, 0.0, -9.81])
    truth = np.array([1.0, 0.0, 0.0, 0.0])
    if world == "ENU":
        truth = Q.ned_to_enu(truth)
    for declination, expected_yaw in ((0.0, -d), (d, 0.0)):
        est = estimators.create(name, world=world, declination=declination)
        for _ in range(50):
            q = est.update(np.zeros(3), acc, mag, dt=0.01)
        err = Q.multiply(q, Q.conjugate(truth))  # world-frame error: a pure yaw here
        yaw_err = 2.0 * np.arctan2(err[3], err[0])
        sign = -1.0 if world == "ENU" else 1.0  # ENU's z is up: yaw sign flips
        assert abs(sign * yaw_err - expected_yaw) < 1e-9
        # q0 given in the output frame round-trips through the internal magnetic frame
        est2 = estimators.create(name, world=world, declination=declination, q0=q)
        assert Q.angle_between(est2.q, q) < 1e-12


def test_estimator_spec_parses_overrides_and_names_what_is_valid():
    from estimators.spec import EstimatorSpec

    spec = EstimatorSpec.parse("mahony:kp=0.5,mag_mode=full,exact=true")
    assert spec.params == {"kp": 0.5, "mag_mode": "full", "exact": True}
    assert spec.label == "mahony:kp=0.5,mag_mode=full,exact=True"
    est = spec.create(200.0, declination=0.1)
    assert est.params.kp == 0.5 and est.params.declination == 0.1
    # the spec's own override wins over a site-wide default
    assert EstimatorSpec.parse("eskf:declination=0.2").create(declination=0.1
                                                               ).params.declination == 0.2
    with pytest.raises(ValueError, match="valid"):
        EstimatorSpec.parse("nosuch")
    with pytest.raises(ValueError, match="kp"):
        EstimatorSpec.parse("mahony:kq=1")
    with pytest.raises(ValueError, match="k=v"):
        EstimatorSpec.parse("mahony:kp")
